"""`dali pretrain` (placeholder until the detector issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("pretrain", "detector issue")
