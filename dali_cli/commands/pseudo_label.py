"""`dali pseudo-label` (placeholder until the PTSN issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("pseudo-label", "PTSN issue")
