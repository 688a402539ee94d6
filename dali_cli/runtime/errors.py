"""The error contract between the library, the stages and the CLI (no click here).

A stage, a reader or a writer that refuses its input raises a `StageError` whose message names
the file, frame and field; a wrong parameter raises `ParameterError` naming the stage argument(s)
(`fields`, e.g. ("range_m",)). The command line maps both to click errors in one place
(`dali_cli.cli.LazyGroup.invoke`): a `ParameterError` becomes a usage error (exit 2) that names
the command's flags for those arguments (`range_m` -> `--range-m`), any other `StageError` an
error message (exit 1). Engines (Ray, torch.distributed) and tests call stages without click and
catch these plain exceptions.
"""

from __future__ import annotations


class StageError(Exception):
    """Bad input: a missing or malformed file, an artifact made from other inputs, ...

    `message` names the path (and row, frame, field where there is one); `path` is the offending
    file or directory when known.
    """

    def __init__(self, message: str, *, path: str | None = None):
        super().__init__(message)
        self.message = str(message)
        self.path = None if path is None else str(path)

    def __reduce__(self):  # picklable across worker processes, keywords included
        return (_rebuild, (type(self), self.message, self.__dict__))

    def __str__(self) -> str:
        return self.message


class WriteError(StageError):
    """Writing an output failed (disk full, quota, read-only, permissions, an I/O error):
    nothing was committed, so the previous output at that path, if any, is intact. The message
    names the output, the file when it differs, the system's reason and, for a full disk, the
    bytes it needed and had where known (`error.needed`, `error.free`)."""

    def __init__(self, out, error: OSError):
        reason = error.strerror or str(error) or type(error).__name__
        details = []
        if error.filename and str(error.filename) != str(out):
            details.append(str(error.filename))
        needed, free = getattr(error, "needed", None), getattr(error, "free", None)
        if needed:
            details.append(
                f"needs {size_text(needed)}"
                + (f", {size_text(free)} free" if free is not None else "")
            )
        where = f" ({'; '.join(details)})" if details else ""
        super().__init__(
            f"{out}: writing failed: {reason}{where}; nothing was replaced or changed (the "
            "previous output, if any, is intact)",
            path=str(out),
        )


def size_text(count: int) -> str:
    """`count` bytes for a person: 1544768 -> "1.5 MB (1544768 bytes)"."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= size:
            return f"{count / size:.1f} {unit} ({count} bytes)"
    return f"{count} bytes"


class ParameterError(StageError):
    """A parameter value a stage cannot run with. `fields` are the stage's argument names
    (snake_case, as in its signature); the CLI renders them as its flags."""

    def __init__(self, fields: str | tuple[str, ...], message: str):
        self.fields = (fields,) if isinstance(fields, str) else tuple(fields)
        super().__init__(message)

    def __str__(self) -> str:
        return f"{' / '.join(self.fields)}: {self.message}"


def _rebuild(cls, message: str, state: dict) -> StageError:
    error = Exception.__new__(cls)
    Exception.__init__(error, message)
    error.__dict__.update(state)
    return error
