"""How many CPU cores this process may use: the one count the ray caster, the synth workers and
torch's threads go by (no torch import here)."""

from __future__ import annotations

import os


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask), at least 1.

    A stage that runs alone uses every one of them. The 1-minute load average is not a guide: in
    a `make` chain it still counts the stage that just finished, so a load-based choice trained
    `make demo` on 1 of 2 cores (1.7 vs 2.4 frames/s). To share the machine, pass
    `--threads` (e.g. `TRAIN_FLAGS="--threads 1"` for `make -j2` on two cores).
    """
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)
