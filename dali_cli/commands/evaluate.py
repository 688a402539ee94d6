"""`dali eval` (placeholder until the evaluation issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("eval", "evaluation issue")
