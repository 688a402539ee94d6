"""`dali report` (placeholder until the retrain issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("report", "retrain issue")
