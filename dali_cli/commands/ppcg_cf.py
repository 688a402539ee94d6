"""`dali ppcg-cf` (placeholder until the PPCG issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("ppcg-cf", "PPCG issue")
