"""Crash-safe replacement of an artifact directory, the lock that serializes writers of one
output, and recovery of what an interrupted replacement left (docs/data-safety.md).

The stage runner builds the new artifact in `<out>.tmp-<pid>` and commits it with
`replace_directory`. On Linux the commit is one `renameat2(RENAME_EXCHANGE)`: `<out>` always
holds a complete artifact, the old one or the new one. Where the exchange is not available it
takes two renames (`<out>` → `<out>.old-<pid>`, then the new directory → `<out>`); a crash
between them leaves `<out>` missing and the complete old artifact in `<out>.old-<pid>`, which
`recover_interrupted` (run by every stage before it looks at `<out>`) puts back.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError
from dali_cli.store.output_paths import is_dali_artifact

RENAME_EXCHANGE = 2
AT_FDCWD = -100


class OutputBusyError(StageError):
    """Another live dali process is writing the same output."""


def after_step(name: str) -> None:
    """Called between the steps of a replacement; crash-injection tests replace it."""


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _pid_of(path: Path, marker: str) -> int | None:
    """pid in a `<name>.<marker>-<pid>` leftover's name, None if it is not one."""
    head, _, pid = path.name.rpartition(f".{marker}-")
    return int(pid) if head and pid.isdigit() else None


def leftovers(out: Path, marker: str) -> list[tuple[Path, int]]:
    """`<out>.<marker>-<pid>` directories of processes that are gone, with their pids."""
    found = []
    for path in out.parent.glob(f"{glob_escape(out.name)}.{marker}-*"):
        pid = _pid_of(path, marker)
        if pid is not None and path.is_dir() and pid != os.getpid() and not process_alive(pid):
            found.append((path, pid))
    return found


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[]" else c for c in name)


def recover_interrupted(out: Path, echo: Callable[[str], None] = console.echo) -> list[str]:
    """Restore or clean what an interrupted run on `out` left; returns what was done.

    - `<out>` missing and a complete artifact in `<out>.old-<pid>` of a dead process (a crash
      between the two renames of a replacement): renamed back to `<out>` (the newest if several).
    - `<out>.old-<pid>` of dead processes when `<out>` is complete: deleted.
    - `<out>.tmp-<pid>` of dead processes (killed builds, or the old artifact after an exchange):
      deleted.
    Call it with the output lock held.
    """
    done = []
    retired = leftovers(out, "old")
    if not out.exists():
        complete = [(p, pid) for p, pid in retired if is_dali_artifact(p)]
        if complete:
            newest = max(complete, key=lambda item: item[0].stat().st_mtime_ns)[0]
            os.rename(newest, out)
            done.append(f"restored {out} from {newest.name} (a replacement was interrupted)")
            retired = [item for item in retired if item[0] != newest]
    if out.exists():
        for path, _ in retired:
            shutil.rmtree(path, ignore_errors=True)
            done.append(f"removed {path.name} (left by an interrupted replacement)")
    for path, _ in leftovers(out, "tmp"):
        shutil.rmtree(path, ignore_errors=True)
        done.append(f"removed {path.name} (left by a run that was killed)")
    for line in done:
        echo(f"recovery: {line}")
    return done


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE); False when unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_uint,
    ]
    if renameat2(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(b))


def replace_directory(new: Path, target: Path, exchange: bool = True) -> None:
    """Make the complete directory `new` the artifact at `target`, replacing one that exists.

    At every instant `target` is the complete old or new artifact, or (two-rename fallback only,
    between its renames) missing with the old one complete in `<target>.old-<pid>`.
    """
    if not target.exists():
        os.rename(new, target)
        after_step("renamed")
        return
    if exchange and _exchange(new, target):
        after_step("exchanged")
        shutil.rmtree(new, ignore_errors=True)  # now the old artifact; a crash leaves a .tmp-*
        return
    retired = target.parent / f"{target.name}.old-{os.getpid()}"
    if retired.exists():
        shutil.rmtree(retired)
    os.rename(target, retired)
    after_step("retired")
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(retired, target)
        raise
    after_step("renamed")
    shutil.rmtree(retired, ignore_errors=True)


class OutputLock:
    """Exclusive lock on one output path, held while a stage checks and writes it.

    A second process that asks for the same output while the first holds it gets
    OutputBusyError naming the holder's pid. The lock is `flock` on `.<name>.lock` beside the
    output (released by the kernel when the holder dies); the file is removed on release.
    """

    def __init__(self, out: Path):
        self.out = out
        self.path = out.parent / f".{out.name}.lock"
        self._fd: int | None = None

    def __enter__(self) -> OutputLock:
        self.out.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise OutputBusyError(
                    f"{self.out} is being written by another dali process (pid {holder}); "
                    "wait for it to finish, then rerun (it will be up to date)"
                ) from None
            try:  # the file we locked may have been unlinked by a holder releasing it
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is None:
            return
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        os.close(self._fd)  # releases the flock
        self._fd = None
