"""`dali ptsn-sweep` (placeholder until the PTSN issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("ptsn-sweep", "PTSN issue")
