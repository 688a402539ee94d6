"""`dali library` (placeholder until the PPCG issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("library", "PPCG issue")
