"""`dali synth` (placeholder until the ray casting and synth issue lands)."""

from dali_cli.commands.common import not_implemented

command = not_implemented("synth", "ray casting and synth issue")
