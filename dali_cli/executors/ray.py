"""The Ray engine: one actor per worker, on a Ray cluster (`--ray-address ADDR`, e.g. after
`ray start --head`) or on a local Ray instance started for the run (no dashboard).

Each actor calls the stage's worker factory once (the detector, or the model library and its BVHs,
is loaded once per actor) and then runs the shards the driver hands it, one at a time, writing
each into the artifact's temporary directory (which must be on a filesystem every node sees).
A lost actor (its process or node died) is restarted and its shard retried by Ray
(`max_restarts`, `max_task_retries`); an exception raised by the stage's code is not retried (it
would fail again) and stops the run, naming the frames.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from dali_cli.executors import Executor, Shard, ShardWorker, run_shard
from dali_cli.runtime import console
from dali_cli.runtime.errors import StageError

RESTARTS = 2  # times Ray restarts a lost actor and retries its shard
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20  # only shards' small payloads and summaries travel


class _ShardActor:
    """A Ray actor around one stage worker (made once, in the actor's process)."""

    def __init__(self, factory: Callable[[], ShardWorker]):
        self.worker = factory()

    def run(self, shard: Shard, root: str) -> dict:
        return run_shard(self.worker, shard, Path(root))


def _import_ray():
    try:
        import ray
    except ImportError:
        raise StageError(
            "--executor ray needs Ray: pip install -e '.[ray]' (or pip install 'dali[ray]')"
        ) from None
    return ray


class RayExecutor(Executor):
    name = "ray"

    def __init__(self, workers: int | None, address: str | None = None, cpus_per_worker: int = 1):
        super().__init__(workers or 1)
        self._requested = workers
        self.address = address
        self.cpus_per_worker = max(1, int(cpus_per_worker))
        self._started_ray = False
        self._actors: list = []

    def __enter__(self) -> RayExecutor:
        ray = _import_ray()
        started = time.perf_counter()
        if ray.is_initialized():  # e.g. a test session's instance, or a library caller's
            where = "the running Ray instance"
        else:
            options = {"logging_level": logging.WARNING, "log_to_driver": False}
            if self.address is not None:
                ray.init(address=self.address, **options)
                where = f"the Ray cluster at {self.address}"
            else:
                from dali_cli.raycast import available_cores

                cpus = max(self._requested or available_cores(), 1) * self.cpus_per_worker
                ray.init(
                    address="local",  # a new instance, even when a `ray start` one runs here
                    num_cpus=cpus,
                    include_dashboard=False,
                    object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                    **options,
                )
                where = f"a local Ray instance ({cpus} CPUs)"
            self._started_ray = True
        if self._requested is None:
            cluster_cpus = int(ray.cluster_resources().get("CPU", 1))
            self.workers = max(1, cluster_cpus // self.cpus_per_worker)
        self.where = where
        self.started_seconds = time.perf_counter() - started
        console.info(f"executor: ray on {where}, {self.workers} worker(s)")
        return self

    def close(self) -> None:
        ray = _import_ray()
        for actor in self._actors:  # also on Ctrl-C: no actor keeps writing into a removed dir
            try:
                ray.kill(actor)
            except Exception:  # already dead
                pass
        self._actors = []
        if self._started_ray:
            ray.shutdown()
            self._started_ray = False

    def _completions(
        self, factory: Callable[[], ShardWorker], shards: list[Shard], directory: Path
    ) -> Iterator[tuple[Shard, dict | BaseException]]:
        ray = _import_ray()
        started = time.perf_counter()
        actor_class = ray.remote(_ShardActor).options(
            num_cpus=self.cpus_per_worker,
            max_restarts=RESTARTS,
            max_task_retries=RESTARTS,
            # the actors run this process's environment (same interpreter's packages on a
            # local instance; on a cluster, dali must be installed on every node)
            runtime_env={"env_vars": {"OMP_NUM_THREADS": str(self.cpus_per_worker)}},
        )
        self._actors = [actor_class.remote(factory) for _ in range(min(self.workers, len(shards)))]
        self.started_seconds += time.perf_counter() - started
        idle = list(self._actors)
        queue = list(reversed(shards))
        running: dict = {}
        root = str(directory)
        while queue or running:
            while queue and idle and not self._stopping:
                actor, shard = idle.pop(), queue.pop()
                running[actor.run.remote(shard, root)] = (actor, shard)
            if not running:
                break
            ready, _ = ray.wait(list(running), num_returns=1)
            for ref in ready:
                actor, shard = running.pop(ref)
                try:
                    yield shard, ray.get(ref)
                except Exception as error:  # RayTaskError (stage code), ActorDiedError, ...
                    yield shard, error
                idle.append(actor)
