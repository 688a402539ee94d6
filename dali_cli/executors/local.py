"""The local engine: shards run in this process (one worker) or in a pool of spawned processes
on this machine (dali_cli.runtime.workers.process_pool: workers die with their parent)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, wait
from pathlib import Path

from dali_cli.executors import Executor, Shard, ShardWorker, run_shard
from dali_cli.runtime import console

_worker: ShardWorker | None = None  # the pool process's worker, made once by _start


def _start(factory: Callable[[], ShardWorker]) -> None:
    global _worker
    _worker = factory()


def _run(shard: Shard, root: str) -> dict:
    return run_shard(_worker, shard, Path(root))


class LocalExecutor(Executor):
    name = "local"

    @property
    def serial(self) -> bool:
        return self.workers <= 1

    def _completions(
        self, factory: Callable[[], ShardWorker], shards: list[Shard], directory: Path
    ) -> Iterator[tuple[Shard, dict | BaseException]]:
        if self.workers <= 1:
            worker = factory()
            for shard in shards:
                if self._stopping:
                    return
                try:
                    yield shard, run_shard(worker, shard, directory)
                except Exception as error:
                    yield shard, error
            return
        from dali_cli.runtime.workers import process_pool

        count = min(self.workers, len(shards))
        console.info(f"executor: local process pool, {count} worker(s), {len(shards)} shards")
        pool = process_pool(count, _start, (factory,))  # processes start on first use
        try:
            queue = list(reversed(shards))
            running = {}
            # two shards per worker in flight: a free worker never waits for the driver
            while queue or running:
                while queue and not self._stopping and len(running) < 2 * self.workers:
                    shard = queue.pop()
                    running[pool.submit(_run, shard, str(directory))] = shard
                if not running:
                    break
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    shard = running.pop(future)
                    error = future.exception()
                    yield shard, (error if error is not None else future.result())
        finally:
            # Ctrl-C or a failure: drop what has not started; running shards finish into the
            # temporary directory, which run_stage removes
            pool.shutdown(wait=True, cancel_futures=True)
