"""One file written atomically: into a hidden temporary beside it, then renamed onto it, so a
reader (or a crash) never sees half a file. Whole artifact directories: dali_cli.store.atomic_dir."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from dali_cli.runtime.errors import WriteError


def write_atomically(path: str | Path, write: Callable[[Path], None]) -> Path:
    """`write(temporary)`, then rename the temporary onto `path` (parents created). The
    temporary (`.<name>.<pid>.part`, same directory, same file system) is removed when `write`
    fails; `path` then keeps its previous content."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        write(temporary)
        os.replace(temporary, path)
    except OSError as error:
        raise WriteError(path, error) from None
    finally:
        temporary.unlink(missing_ok=True)
    return path


def write_text_atomically(path: str | Path, text: str) -> Path:
    """`text` into `path` (UTF-8), atomically."""
    return write_atomically(path, lambda temporary: temporary.write_text(text, encoding="utf-8"))
