"""Spawned workers die with their parent (a `kill -9` of `dali synth --workers 2`
must not leave the workers and the resource tracker sleeping forever)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def children_of(pid: int) -> set[int]:
    """pids whose parent is `pid` (from /proc)."""
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            found.add(int(entry.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")
@pytest.mark.parametrize("kind", ["pool", "synth"])
def test_workers_and_resource_tracker_die_with_a_killed_parent(tmp_path, kind):
    if kind == "pool":
        script = textwrap.dedent(
            """
            import time
            from dali_cli.runtime.workers import process_pool
            with process_pool(2) as pool:
                list(pool.map(time.sleep, [0.01, 0.01]))  # both workers started
                print("ready", flush=True)
                pool.submit(time.sleep, 3600)
                time.sleep(3600)
            """
        )
        command = [sys.executable, "-c", script]
    else:
        command = [
            sys.executable,
            "-c",
            "from dali_cli.cli import main; main()",
            "synth",
            "--sensor",
            "kitti",
            "--frames",
            "40",
            "--workers",
            "2",
            "--out",
            str(tmp_path / "s"),
        ]
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    parent = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        spawned: set[int] = set()
        while time.monotonic() < deadline:  # the workers (2) and the resource tracker
            spawned = children_of(parent.pid)
            if len(spawned) >= 3:
                break
            time.sleep(0.1)
        assert len(spawned) >= 3, f"only {spawned} started"
        time.sleep(0.5)
        spawned = children_of(parent.pid)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(alive(p) for p in spawned):
            time.sleep(0.1)
        assert not [p for p in spawned if alive(p)], "orphaned workers are still running"
    finally:
        if parent.poll() is None:
            parent.kill()
