"""The error of a missing or malformed artifact, and the JSON reader every artifact file goes
through that raises it (shared by the frame-set and box-table modules)."""

from __future__ import annotations

from pathlib import Path

from dali_cli.runtime.errors import StageError


class ArtifactError(StageError):
    """A missing or malformed artifact; the message names the path and the problem."""


def read_json(path: Path, missing: str, invalid: str):
    """The JSON document of the file `path`. ArtifactError naming the file: `"{path}: {missing}"`
    when it is not a file, `"{path}: {invalid} ({error})"` when it is not UTF-8 JSON."""
    from dali_cli.store.regular_files import (
        SpecialFileError,
        UnreadableFileError,
        read_json_file,
    )

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise ArtifactError(f"{path}: {missing}")
    try:
        return read_json_file(path, "JSON file")
    except SpecialFileError:
        raise
    except UnreadableFileError as error:  # a directory, too large, not UTF-8, not JSON, too deep
        reason = str(error).removeprefix(f"{path}: ")[:200]
        raise ArtifactError(f"{path}: {invalid} ({reason})") from None
    except ValueError as error:  # an integer of 5,000 digits
        raise ArtifactError(f"{path}: {invalid} ({str(error)[:160]})") from None


class TableValueError(ArtifactError, ValueError):
    """A box-table value that cannot be stored (out of its column's range, NaN/inf, a bad frame id);
    a ValueError for library callers, a clean CLI error for users. Names column, row and frame."""
