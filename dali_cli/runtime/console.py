"""What stages and library code print (no click): progress lines on stdout, warnings on stderr,
coloured only on a terminal. The CLI's own output stays with click."""

from __future__ import annotations

import sys

_COLOURS = {"red": "\033[31m", "yellow": "\033[33m"}
_BOLD, _RESET = "\033[1m", "\033[0m"


def echo(message: str) -> None:
    """One line on stdout."""
    print(message, file=sys.stdout, flush=True)


def info(message: str) -> None:
    """One line on stderr (logs of what ran where; stdout stays for results)."""
    print(message, file=sys.stderr, flush=True)


def warn(message: str, colour: str = "red", bold: bool = True) -> None:
    """`WARNING: message` on stderr (red and bold on a terminal, as click.secho did)."""
    line = f"WARNING: {message}"
    stream = sys.stderr
    if getattr(stream, "isatty", lambda: False)():
        line = f"{_BOLD if bold else ''}{_COLOURS.get(colour, '')}{line}{_RESET}"
    print(line, file=stream, flush=True)
