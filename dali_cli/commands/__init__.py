"""One module per `dali` subcommand; each defines `command` (a click command or group)."""
