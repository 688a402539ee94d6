"""`dali view` (placeholder until the importers issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("view", "importers issue")
