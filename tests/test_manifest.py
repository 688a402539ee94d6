"""Stage runner: atomic output, manifest contents, skip / force / dry-run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dali_cli import __version__
from dali_cli.runtime.errors import StageError
from dali_cli.store.artifacts import BoxTable, read_boxes, write_boxes
from dali_cli.store.manifest import (
    BuildResult,
    check_made_from,
    content_hash,
    hash_tree,
    read_manifest,
    run_stage,
)


def make_input(path, seed=0):
    path.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    write_boxes(path, BoxTable.from_arrays(["a", "b"], rng.uniform(1, 2, (2, 7))))
    return path


class CountingBuild:
    def __init__(self, n_boxes=3):
        self.calls = 0
        self.n_boxes = n_boxes

    def __call__(self, out):
        self.calls += 1
        write_boxes(out, BoxTable.from_arrays(["x"] * self.n_boxes, np.ones((self.n_boxes, 7))))
        return BuildResult(counts={"boxes": self.n_boxes}, timings={"fake_seconds": 0.5})


def no_echo(_message):
    pass


def test_manifest_records_inputs_params_counts(tmp_path):
    source = make_input(tmp_path / "in")
    out = tmp_path / "out"
    outcome = run_stage(
        "demo",
        out,
        {"source": source},
        {"k": 3, "t": (1, 2)},
        CountingBuild(),
        seed=7,
        echo=no_echo,
    )
    assert outcome.status == "ran"
    manifest = read_manifest(out)
    assert manifest == outcome.manifest
    assert manifest["stage"] == "demo" and manifest["dali_version"] == __version__
    assert manifest["params"] == {"k": 3, "t": [1, 2]}
    assert manifest["seed"] == 7
    assert manifest["inputs"]["source"][0]["path"] == str(source)
    assert manifest["inputs"]["source"][0]["hash"] == hash_tree(source)
    assert manifest["outputs"]["counts"] == {"boxes": 3}
    assert manifest["timings"]["fake_seconds"] == 0.5 and manifest["timings"]["wall_seconds"] >= 0
    assert manifest["content_hash"] == hash_tree(out)
    assert len(read_boxes(out)) == 3
    # downstream stages see the recorded content hash
    assert content_hash(out) == manifest["content_hash"]


def test_rerun_is_skipped_until_inputs_or_params_change(tmp_path):
    source = make_input(tmp_path / "in")
    out = tmp_path / "out"
    build = CountingBuild()
    run_stage("demo", out, {"source": source}, {"k": 3}, build, echo=no_echo)
    messages = []
    outcome = run_stage("demo", out, {"source": source}, {"k": 3}, build, echo=messages.append)
    assert outcome.status == "skipped" and build.calls == 1
    assert "up to date" in messages[0]
    outcome = run_stage("demo", out, {"source": source}, {"k": 4}, build, echo=no_echo)
    assert (
        outcome.status == "ran" and "parameters changed: k" in outcome.reason and build.calls == 2
    )
    make_input(source, seed=1)  # same file names, other content
    outcome = run_stage("demo", out, {"source": source}, {"k": 4}, build, echo=no_echo)
    assert outcome.status == "ran" and "inputs changed: source" in outcome.reason
    outcome = run_stage("demo", out, {"source": source}, {"k": 4}, build, force=True, echo=no_echo)
    assert outcome.status == "ran" and outcome.reason == "forced" and build.calls == 4


def test_dry_run_writes_nothing_and_explains(tmp_path):
    source = make_input(tmp_path / "in")
    out = tmp_path / "out"
    build = CountingBuild()
    messages = []
    outcome = run_stage(
        "demo", out, {"source": source}, {}, build, dry_run=True, echo=messages.append
    )
    assert outcome.status == "dry-run" and build.calls == 0 and not out.exists()
    assert "would run" in messages[0] and "no output yet" in messages[0]
    run_stage("demo", out, {"source": source}, {}, build, echo=no_echo)
    before = read_manifest(out)
    outcome = run_stage(
        "demo", out, {"source": source}, {"new": 1}, build, dry_run=True, echo=no_echo
    )
    assert outcome.status == "dry-run" and read_manifest(out) == before


class Boom(RuntimeError):
    pass


def test_failure_mid_write_keeps_old_artifact_and_leaves_no_tmp(tmp_path):
    source = make_input(tmp_path / "in")
    out = tmp_path / "out"
    run_stage("demo", out, {"source": source}, {"k": 1}, CountingBuild(3), echo=no_echo)
    before = (out / "manifest.json").read_text()

    def failing_build(tmp):
        write_boxes(tmp, BoxTable.from_arrays(["y"], np.ones((1, 7))))
        (tmp / "partial.bin").write_bytes(b"half")
        raise Boom("disk on fire")

    with pytest.raises(Boom):
        run_stage("demo", out, {"source": source}, {"k": 2}, failing_build, echo=no_echo)
    assert (out / "manifest.json").read_text() == before
    assert len(read_boxes(out)) == 3 and not (out / "partial.bin").exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name not in ("in", "out")]
    assert leftovers == []


def test_failure_on_first_run_leaves_nothing(tmp_path):
    out = tmp_path / "out"

    def failing_build(tmp):
        (tmp / "x").write_text("1")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_stage("demo", out, {}, {}, failing_build, echo=no_echo)
    assert list(tmp_path.iterdir()) == []


def test_output_without_manifest_is_refused_not_wiped(tmp_path):
    from dali_cli.store.output_paths import OutputPathError

    out = tmp_path / "out"
    out.mkdir()
    (out / "stray.txt").write_text("old")
    build = CountingBuild()
    with pytest.raises(OutputPathError, match="without a dali manifest"):
        run_stage("demo", out, {}, {}, build, echo=no_echo)
    assert build.calls == 0 and (out / "stray.txt").read_text() == "old"


def test_missing_input_is_an_error(tmp_path):

    with pytest.raises(StageError, match="input not found"):
        run_stage(
            "demo",
            tmp_path / "out",
            {"source": tmp_path / "absent"},
            {},
            CountingBuild(),
            echo=no_echo,
        )
    assert not (tmp_path / "out").exists()


def test_hash_tree_sees_renames_and_content(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f.txt").write_text("1")
    first = hash_tree(tmp_path / "a")
    (tmp_path / "a" / "f.txt").write_text("2")
    second = hash_tree(tmp_path / "a")
    (tmp_path / "a" / "f.txt").rename(tmp_path / "a" / "g.txt")
    third = hash_tree(tmp_path / "a")
    assert len({first, second, third}) == 3
    (tmp_path / "a" / "manifest.json").write_text(json.dumps({"x": 1}))
    assert hash_tree(tmp_path / "a") == third  # the manifest itself is not content


def test_check_made_from_refuses_an_artifact_of_another_input(tmp_path):

    target, other = make_input(tmp_path / "target", seed=1), make_input(tmp_path / "other", seed=2)
    out = tmp_path / "pseudo"
    run_stage("demo", out, {"target": target}, {}, CountingBuild(), echo=no_echo)
    check_made_from(out, "target", target)  # the right one passes
    with pytest.raises(StageError, match="made from target .*target, not from .*other"):
        check_made_from(out, "target", other)
    check_made_from(out, "library", other)  # a role the manifest does not record: unchecked
    check_made_from(target, "target", other)  # no manifest (hand-made table): unchecked


def test_stale_temporaries_dali_marked_are_removed_and_others_kept(tmp_path):
    import os

    from dali_cli.store.atomic_dir import mark_leftover

    source = make_input(tmp_path / "in")
    out = tmp_path / "out"
    dead = _dead_pid()
    stale = tmp_path / f"out.tmp-{dead}"
    (stale / "frames.zarr").mkdir(parents=True)
    mark_leftover(stale, out, "tmp")  # what the stage runner writes when it creates one
    unmarked = tmp_path / f"out.tmp-{os.getppid()}"  # named like one, not created by dali: kept
    unmarked.mkdir()
    run_stage("demo", out, {"source": source}, {}, CountingBuild(), echo=no_echo)
    assert not stale.exists() and unmarked.is_dir() and (out / "manifest.json").is_file()


def _dead_pid() -> int:
    import subprocess

    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid  # reaped: no process has this pid now (pids are not reused this fast)
