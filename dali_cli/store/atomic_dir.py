"""Crash-safe replacement of an artifact directory, the lock that serializes writers of one
output, and recovery of what an interrupted replacement left (docs/data-safety.md).

Every run that writes `<out>` holds its lock (`.<out>.lock`) and a run token (random, unique per
run, never per pid: in a container every start may have the same pid). The token is written
into the lock file before any name of the run is taken, so the lock file a killed run leaves
names what it owned. The stage runner builds the new artifact in `<out>.tmp-<pid>-<token>` and
commits it with `replace_directory`. On Linux the commit is one `renameat2(RENAME_EXCHANGE)`:
`<out>` always holds a complete artifact, the old one or the new one. Where the exchange is not
available it takes two renames (`<out>` → `<out>.old-<pid>-<token>`, then the new directory →
`<out>`); a crash between them leaves `<out>` missing and the complete old artifact in the
retired directory, which `recover_interrupted` (run by every stage, lock held, before it looks
at `<out>`) puts back.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import re
import secrets
import shutil
import stat
from collections.abc import Callable, Iterable
from pathlib import Path

from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError, WriteError
from dali_cli.store.output_paths import OutputPathError, is_dali_artifact

RENAME_EXCHANGE = 2
AT_FDCWD = -100
# at most this many tokens of killed runs are carried in a lock file (one page: its rewrite
# never needs a new block on a full disk)
MAX_TOKENS = 32
LOCK_TEXT = re.compile(rb"\s*(?:\d+(?:\s+[0-9a-f]{16})*)?\s*")


class OutputBusyError(StageError):
    """Another live dali process is writing the same output."""


def after_step(name: str) -> None:
    """Called between the steps of a replacement; crash-injection tests replace it."""


def run_token() -> str:
    """A token unique to one run (64 random bits): part of every name the run creates."""
    return secrets.token_hex(8)


# A directory dali creates beside an output (`<out>.tmp-<pid>-<token>` while building,
# `<out>.old-<pid>-<token>` while replacing) holds this file, written when dali creates or
# retires it and deleted last when dali removes it. Recovery touches only directories holding
# it, naming that very output and kind, or named with the token of a killed run of that output
# that its lock file recorded: never a directory by its name alone (a user's `out.old-2023`
# backup is not dali's).
LEFTOVER_MARKER = ".dali-leftover.json"


def leftover_path(out: Path, kind: str, token: str) -> Path:
    """The `kind` ("tmp" or "old") directory of this run for `out`."""
    return out.parent / f"{out.name}.{kind}-{os.getpid()}-{token}"


def token_of(path: Path, out: Path, kind: str) -> str | None:
    """The run token in the name `<out>.<kind>-<pid>-<token>`, None for any other name."""
    match = re.fullmatch(rf"{re.escape(out.name)}\.{kind}-\d+-([0-9a-f]{{16}})", path.name)
    return match.group(1) if match else None


def mark_leftover(directory: Path, out: Path, kind: str) -> None:
    """Record in `directory` that dali created it as the `kind` ("tmp" or "old") of `out`."""
    document = {"dali": "leftover", "kind": kind, "out": out.name, "pid": os.getpid()}
    (directory / LEFTOVER_MARKER).write_text(json.dumps(document) + "\n")


def unmark(directory: Path) -> None:
    (directory / LEFTOVER_MARKER).unlink(missing_ok=True)


def remove_tree(directory: Path) -> None:
    """Delete dali's directory `directory`, its leftover marker last: killed at any instant,
    what remains is still marked as dali's."""
    try:
        children = list(directory.iterdir())
    except OSError:
        return
    for child in children:
        if child.name == LEFTOVER_MARKER:
            continue
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
    after_step("emptied")
    unmark(directory)
    shutil.rmtree(directory, ignore_errors=True)


def is_leftover(directory: Path, out: Path, kind: str) -> bool:
    """`directory` is a `kind` leftover dali created for `out` (its marker says so)."""
    if directory.is_symlink() or not directory.is_dir():
        return False
    marker = directory / LEFTOVER_MARKER
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


def leftovers(out: Path, kind: str, tokens: Iterable[str] = ()) -> list[Path]:
    """`<out>.<kind>-*` directories dali created for `out`: marked as its leftovers, or named
    with one of `tokens` (runs of `out` that were killed, from its lock file). Called with the
    output lock held, so no live dali process is using them: the lock, not a pid (which a
    restart in a fresh PID namespace gives out again), proves the writer that left them is
    gone; and this run's own names are not taken yet."""
    tokens = set(tokens)
    found = []
    for path in out.parent.glob(f"{glob_escape(out.name)}.{kind}-*"):
        if path.is_symlink() or not path.is_dir():
            continue
        if token_of(path, out, kind) in tokens or is_leftover(path, out, kind):
            found.append(path)
    return found


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[]" else c for c in name)


def recover_interrupted(
    out: Path, echo: Callable[[str], None] = console.echo, tokens: Iterable[str] = ()
) -> list[str]:
    """Restore or clean what an interrupted run on `out` left; returns what was done.

    Only directories dali marked as its own leftovers of `out` (LEFTOVER_MARKER), or named with
    the token of a killed run of `out` (`tokens`, from the lock file), are touched:
    - `<out>` missing and a complete artifact in a retired `<out>.old-*`: renamed back to
      `<out>` (the newest if several).
    - retired `<out>.old-*` when `<out>` is complete: deleted.
    - `<out>.tmp-*` (killed builds, or the old artifact after an exchange): deleted.
    - a marker left in `<out>` itself (killed while retiring it): removed.
    Call it with the output lock held.
    """
    tokens = tuple(tokens)
    done = []
    retired = leftovers(out, "old", tokens)
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
            remove_tree(path)
            done.append(f"removed {path.name} (left by an interrupted replacement)")
    for path in leftovers(out, "tmp", tokens):
        remove_tree(path)
        done.append(f"removed {path.name} (left by a run that was killed)")
    for line in done:
        echo(f"recovery: {line}")
    return done


def remove_own(path: Path, out: Path, kind: str) -> None:
    """Clear `path` (this run's `kind` name beside `out`) for dali to create: removed when it
    is dali's marked leftover, refused (OutputPathError) when it is anything else."""
    if not (path.exists() or path.is_symlink()):
        return
    if not is_leftover(path, out, kind):
        raise OutputPathError(
            f"{path} exists and was not created by dali for {out.name}; move or delete it "
            "yourself, then rerun"
        )
    remove_tree(path)


def make_temporary(out: Path, token: str | None = None) -> Path:
    """`<out>.tmp-<pid>-<token>`, new and marked as dali's (`token`: the run's, recorded in the
    output's lock file before this name is taken). A full disk while marking it removes it."""
    temporary = leftover_path(out, "tmp", token or run_token())
    remove_own(temporary, out, "tmp")
    temporary.mkdir()
    try:
        after_step("created")
        mark_leftover(temporary, out, "tmp")
    except BaseException:
        remove_tree(temporary)
        raise
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


def replace_directory(
    new: Path, target: Path, exchange: bool = True, token: str | None = None
) -> None:
    """Make the complete directory `new` the artifact at `target`, replacing one that exists.

    At every instant `target` is the complete old or new artifact, or (two-rename fallback only,
    between its renames) missing with the old one complete in `<target>.old-<pid>-<token>`.
    The replaced artifact is deleted marker last (remove_tree).
    """
    if not target.exists():
        os.rename(new, target)
        unmark(target)
        after_step("renamed")
        return
    if exchange:
        mark_leftover(target, target, "tmp")  # once exchanged, the old artifact is a marked .tmp-*
        after_step("marked")
        try:
            exchanged = _exchange(new, target)
        except BaseException:
            unmark(target)
            raise
        if exchanged:
            after_step("exchanged")
            unmark(target)
            after_step("unmarked")
            remove_tree(new)
            return
        unmark(target)
    retired = leftover_path(target, "old", token or run_token())
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
    remove_tree(retired)


def lock_tokens(text: bytes) -> tuple[str, ...] | None:
    """The run tokens a lock file's `text` records (`<pid> <token> <token of a killed run>...`,
    or an older dali's `<pid>`), None when it is no lock file dali wrote."""
    if not LOCK_TEXT.fullmatch(text):
        return None
    return tuple(word.decode() for word in text.split()[1:])


class OutputLock:
    """Exclusive lock on one output path, held while a stage checks and writes it.

    A second process that asks for the same output while the first holds it gets
    OutputBusyError naming the holder's pid (`wait=True`: waits for it instead). The lock is
    `flock` on `.<name>.lock` beside the output (released by the kernel when the holder dies);
    the file holds the holder's pid and run token (`token`), followed by the tokens of killed
    runs it found there (`inherited`: what they created is theirs to clean), and is removed on
    release. A full disk while taking it is a WriteError naming the output; no empty lock file
    is left.
    """

    def __init__(self, out: Path, wait: bool = False):
        self.out = out
        self.path = out.parent / f".{out.name}.lock"
        self.wait = wait
        self.token = run_token()
        self.inherited: tuple[str, ...] = ()
        self._fd: int | None = None

    def __enter__(self) -> OutputLock:
        try:
            fd, held = self._acquire()
        except OSError as error:
            raise WriteError(self.out, error) from None
        self.inherited = lock_tokens(held) or ()
        tokens = [self.token, *[t for t in self.inherited if t != self.token]][:MAX_TOKENS]
        text = f"{os.getpid()} {' '.join(tokens)}".ljust(len(held.rstrip(b"\n"))) + "\n"
        try:  # never shorter than what it overwrites: no truncation, no torn journal
            written = os.pwrite(fd, text.encode(), 0)
            if written != len(text):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
        except OSError as error:
            if not held.strip():  # the empty lock file this run made: not left behind
                self._unlink()
            os.close(fd)
            raise WriteError(self.out, error) from None
        self._fd = fd
        return self

    def _acquire(self) -> tuple[int, bytes]:
        """The locked lock file's descriptor and what it held (a killed run's pid and tokens)."""
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
            held = os.pread(fd, 4096, 0) if regular else b""
            if not regular or lock_tokens(held) is None:
                os.close(fd)  # a user's file of that name: dali writes only its own pid files
                raise OutputPathError(
                    f"{self.path}: the lock file of {self.out} is not a lock dali made (a "
                    "regular file with one link, holding a pid and run tokens); move or delete "
                    "it yourself, then rerun"
                )
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | (0 if self.wait else fcntl.LOCK_NB))
            except BlockingIOError:
                holder = (os.pread(fd, 64, 0).split() or [b"unknown"])[0].decode(errors="replace")
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
                return fd, os.pread(fd, 4096, 0)  # read again: the last holder may have written
            os.close(fd)

    def _unlink(self) -> None:
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    def __exit__(self, *exc) -> None:
        if self._fd is None:
            return
        self._unlink()
        os.close(self._fd)  # releases the flock
        self._fd = None
