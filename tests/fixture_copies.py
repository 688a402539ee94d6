"""Test helper (not part of the package): writable copies of the read-only fixture trees under
tests/fixtures, for tests that damage a file to check the error it gives."""

from __future__ import annotations

import shutil
from pathlib import Path


def writable_copy(source: Path, dest: Path) -> Path:
    """Copy the tree `source` to `dest` with user-writable permissions (fixtures may be checked
    out read-only); returns `dest`."""
    shutil.copytree(source, dest)
    for path in dest.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    return dest
