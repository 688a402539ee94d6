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
import json
import os
import shutil
import stat
from collections.abc import Callable
from pathlib import Path

from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError
from dali_cli.store.output_paths import OutputPathError, is_dali_artifact

RENAME_EXCHANGE = 2
AT_FDCWD = -100


class OutputBusyError(StageError):
    """Another live dali process is writing the same output."""


def after_step(name: str) -> None:
    """Called between the steps of a replacement; crash-injection tests replace it."""


# A directory dali creates beside an output (`<out>.tmp-<pid>` while building, `<out>.old-<pid>`
# while replacing) holds this file, written when dali creates or retires it. Recovery touches
# only directories holding it, naming that very output and kind: never a directory by its name
# alone (a user's `out.old-2023` backup is not dali's).
LEFTOVER_MARKER = ".dali-leftover.json"


def mark_leftover(directory: Path, out: Path, kind: str) -> None:
    """Record in `directory` that dali created it as the `kind` ("tmp" or "old") of `out`."""
    document = {"dali": "leftover", "kind": kind, "out": out.name, "pid": os.getpid()}
    (directory / LEFTOVER_MARKER).write_text(json.dumps(document) + "\n")


def unmark(directory: Path) -> None:
    (directory / LEFTOVER_MARKER).unlink(missing_ok=True)


def is_leftover(directory: Path, out: Path, kind: str) -> bool:
    """`directory` is a `kind` leftover dali created for `out` (its marker says so)."""
    if directory.is_symlink() or not directory.is_dir():
        return False
    marker = directory / LEFTOVER_MARKER
    from dali_cli.runtime.errors import StageError
    from dali_cli.store.regular_files import read_json_file

    try:
        document = read_json_file(marker, "leftover marker")
    except (StageError, OSError, ValueError):
        return False
    return (
        isinstance(document, dict)
        and document.get("dali") == "leftover"
        and document.get("kind") == kind
        and document.get("out") == out.name
    )


def leftovers(out: Path, kind: str) -> list[Path]:
    """`<out>.<kind>-<pid>` directories dali created for `out` (marked), other than this
    process's. Called with the output lock held, so no live dali process is using them: the
    lock, not the pid (which the system may have given to another process since), proves the
    writer that left them is gone."""
    found = []
    for path in out.parent.glob(f"{glob_escape(out.name)}.{kind}-*"):
        _, _, pid = path.name.rpartition(f".{kind}-")
        if pid.isdigit() and int(pid) != os.getpid() and is_leftover(path, out, kind):
            found.append(path)
    return found


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[]" else c for c in name)


def recover_interrupted(out: Path, echo: Callable[[str], None] = console.echo) -> list[str]:
    """Restore or clean what an interrupted run on `out` left; returns what was done.

    Only directories dali marked as its own leftovers of `out` are touched (LEFTOVER_MARKER):
    - `<out>` missing and a complete artifact in a retired `<out>.old-<pid>` (a crash between
      the two renames of a replacement): renamed back to `<out>` (the newest if several).
    - retired `<out>.old-<pid>` when `<out>` is complete: deleted.
    - `<out>.tmp-<pid>` (killed builds, or the old artifact after an exchange): deleted.
    - a marker left in `<out>` itself (killed while retiring it): removed.
    Call it with the output lock held.
    """
    done = []
    retired = leftovers(out, "old")
    if not out.exists():
        complete = [p for p in retired if is_dali_artifact(p)]
        if complete:
            newest = max(complete, key=lambda path: path.stat().st_mtime_ns)
            os.rename(newest, out)
            unmark(out)
            done.append(f"restored {out} from {newest.name} (a replacement was interrupted)")
            retired = [path for path in retired if path != newest]
    elif out.is_dir() and not out.is_symlink():
        unmark(out)
    if out.exists():
        for path in retired:
            shutil.rmtree(path, ignore_errors=True)
            done.append(f"removed {path.name} (left by an interrupted replacement)")
    for path in leftovers(out, "tmp"):
        shutil.rmtree(path, ignore_errors=True)
        done.append(f"removed {path.name} (left by a run that was killed)")
    for line in done:
        echo(f"recovery: {line}")
    return done


def remove_own(path: Path, out: Path, kind: str) -> None:
    """Clear `path` (this process's `kind` name beside `out`) for dali to create: removed when
    it is dali's marked leftover, refused (OutputPathError) when it is anything else."""
    if not (path.exists() or path.is_symlink()):
        return
    if not is_leftover(path, out, kind):
        raise OutputPathError(
            f"{path} exists and was not created by dali for {out.name}; move or delete it "
            "yourself, then rerun"
        )
    shutil.rmtree(path)


def make_temporary(out: Path) -> Path:
    """`<out>.tmp-<pid>`, new and marked as dali's; a directory of that name dali did not
    create is refused, not deleted."""
    temporary = out.parent / f"{out.name}.tmp-{os.getpid()}"
    remove_own(temporary, out, "tmp")
    temporary.mkdir()
    mark_leftover(temporary, out, "tmp")
    return temporary


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
        unmark(target)
        after_step("renamed")
        return
    if exchange:
        mark_leftover(target, target, "tmp")  # once exchanged, the old artifact is a marked .tmp-*
        try:
            exchanged = _exchange(new, target)
        except BaseException:
            unmark(target)
            raise
        if exchanged:
            unmark(target)
            after_step("exchanged")
            shutil.rmtree(new, ignore_errors=True)
            return
        unmark(target)
    retired = target.parent / f"{target.name}.old-{os.getpid()}"
    remove_own(retired, target, "old")
    mark_leftover(target, target, "old")
    os.rename(target, retired)
    after_step("retired")
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(retired, target)
        unmark(target)
        raise
    unmark(target)
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
            try:  # never through a link: it would write our pid into its target; a FIFO
                flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK  # must not block
                fd = os.open(self.path, flags, 0o644)
            except OSError as error:
                if error.errno not in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
                    raise
                raise OutputPathError(
                    f"{self.path}: the lock file of {self.out} is not a regular file dali "
                    "made (a symbolic link, a directory or a device); move or delete it "
                    "yourself, then rerun"
                ) from None
            info = os.fstat(fd)
            regular = stat.S_ISREG(info.st_mode) and info.st_nlink == 1  # a hard link: not ours
            held = os.pread(fd, 64, 0) if regular else b""
            if not regular or not (held == b"" or held.strip().isdigit()):
                os.close(fd)  # a user's file of that name: dali writes only its own pid files
                raise OutputPathError(
                    f"{self.path}: the lock file of {self.out} is not a lock dali made (a "
                    "regular file with one link, holding a pid); move or delete it yourself, "
                    "then rerun"
                )
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
