"""Local process pools whose workers die with their parent.

`kill -9` of a stage that had spawned workers used to leave them (and multiprocessing's resource
tracker, about 210 MB each) sleeping forever: a worker blocked on its task queue never learns
that the parent is gone. Every dali pool is made here, with a watchdog thread in each worker that
exits the worker as soon as its parent process is no longer its parent (the kernel re-parents
orphans). The resource tracker exits by itself once no process holds its pipe.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

WATCH_INTERVAL_S = 0.5


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(WATCH_INTERVAL_S)
    os._exit(1)  # orphaned: the stage that started us is gone, and so is anyone to report to


def _start_worker(parent_pid: int, initializer: Callable | None, initargs: tuple) -> None:
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    if initializer is not None:
        initializer(*initargs)


def process_pool(
    workers: int, initializer: Callable | None = None, initargs: tuple = ()
) -> ProcessPoolExecutor:
    """A pool of `workers` spawned processes (not forked: Embree's thread pool and torch do not
    survive a fork) that exit when this process dies; `initializer(*initargs)` runs in each."""
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_start_worker,
        initargs=(os.getpid(), initializer, initargs),
    )
