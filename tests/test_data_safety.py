"""What dali guarantees about a user's data (docs/data-safety.md): `--out` is only ever a new
path or a dali artifact and never an input; replacing an artifact is crash-safe at every step and
the next run recovers; skip decisions hash the input files; one writer per output."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset
from dali_cli.store.atomic_dir import (
    OutputBusyError,
    OutputLock,
    mark_leftover,
    recover_interrupted,
)
from dali_cli.store.manifest import BuildResult, content_hash, read_manifest, run_stage
from dali_cli.store.output_paths import OutputPathError

ROOT = Path(__file__).resolve().parents[1]


def quiet(_message):
    pass


def build_boxes(value: float):
    def build(out: Path) -> BuildResult:
        write_boxes(out, BoxTable.from_arrays(["a"], np.full((1, 7), value)))
        (out / "payload.bin").write_bytes(bytes(4096) + str(value).encode())
        return BuildResult(counts={"value": value})

    return build


def make_target(path: Path) -> Path:
    """A tiny frame set with labels, as `dali synth` would write (no manifest)."""
    rng = np.random.default_rng(0)
    frames = [(f"{i:06d}", rng.uniform(-5, 5, (50, 4)).astype(np.float32)) for i in range(2)]
    write_frameset(path, frames, sensor="kitti")
    boxes = np.array([[10.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0]] * 2)
    write_boxes(path, BoxTable.from_arrays(["000000", "000001"], boxes))
    return path


def snapshot(path: Path) -> dict[str, bytes]:
    return {
        p.relative_to(path).as_posix(): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file()
    }


# --- what --out may be -------------------------------------------------------------------------


def test_synth_refuses_an_existing_user_directory_and_keeps_its_contents(tmp_path):
    """`dali synth --out mydir` must not wipe mydir/important.txt and mydir/sub/."""
    mydir = tmp_path / "mydir"
    (mydir / "sub").mkdir(parents=True)
    (mydir / "important.txt").write_text("precious")
    result = CliRunner().invoke(
        main, ["synth", "--sensor", "kitti", "--frames", "1", "--out", str(mydir)]
    )
    assert result.exit_code != 0
    assert "mydir exists" in result.output and "manifest" in result.output
    assert (mydir / "important.txt").read_text() == "precious" and (mydir / "sub").is_dir()
    dry = CliRunner().invoke(
        main, ["synth", "--sensor", "kitti", "--frames", "1", "--out", str(mydir), "--dry-run"]
    )
    assert dry.exit_code != 0 and (mydir / "important.txt").is_file()


def test_pseudo_label_refuses_its_own_target_as_out(tmp_path):
    """`dali pseudo-label ... --data T --out T` must not delete T/frames.zarr."""
    target = make_target(tmp_path / "T")
    model = tmp_path / "model"  # never opened: the output check comes first
    model.mkdir()
    (model / "model.json").write_text("{}")
    before = snapshot(target)
    result = CliRunner().invoke(
        main,
        [
            "pseudo-label",
            "--model",
            str(model),
            "--data",
            str(target),
            "--scale",
            "1",
            "--out",
            str(target),
        ],
    )
    assert result.exit_code != 0 and "target input" in result.output
    assert snapshot(target) == before


def test_export_kitti_refuses_its_input_as_out(tmp_path):
    """`dali export kitti T2 --calib-root K --out T2` must not delete T2's frames and boxes."""
    target = make_target(tmp_path / "T2")
    calib = tmp_path / "K" / "training" / "calib"
    calib.mkdir(parents=True)
    before = snapshot(target)
    result = CliRunner().invoke(
        main,
        ["export", "kitti", str(target), "--calib-root", str(tmp_path / "K"), "--out", str(target)],
    )
    assert result.exit_code != 0 and "input" in result.output
    assert snapshot(target) == before


@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_that_is_inside_or_contains_an_input_is_refused(tmp_path, where):
    source = make_target(tmp_path / "data" / "source")
    out = {
        "same": source,
        "inside": source / "derived",
        "contains": tmp_path / "data",
    }[where]
    before = snapshot(tmp_path / "data")
    with pytest.raises(OutputPathError, match="source input"):
        run_stage("demo", out, {"source": source}, {}, build_boxes(1.0), echo=quiet)
    assert snapshot(tmp_path / "data") == before


def test_out_under_a_file_and_out_dot_are_clear_errors(tmp_path, monkeypatch):
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(OutputPathError, match="file.txt is a file, not a directory"):
        run_stage("demo", tmp_path / "file.txt" / "out", {}, {}, build_boxes(1.0), echo=quiet)
    (tmp_path / "work").mkdir()
    (tmp_path / "work" / "notes.txt").write_text("mine")
    monkeypatch.chdir(tmp_path / "work")
    result = CliRunner().invoke(main, ["synth", "--sensor", "kitti", "--frames", "1", "--out", "."])
    assert (
        result.exit_code != 0 and "manifest" in result.output and "Traceback" not in result.output
    )
    assert (tmp_path / "work" / "notes.txt").read_text() == "mine"


def test_an_existing_artifact_is_replaced(tmp_path):
    out = tmp_path / "out"
    run_stage("demo", out, {}, {"v": 1}, build_boxes(1.0), echo=quiet)
    outcome = run_stage("demo", out, {}, {"v": 2}, build_boxes(2.0), echo=quiet)
    assert outcome.status == "ran" and read_manifest(out)["params"] == {"v": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it


# --- crash-safe replacement --------------------------------------------------------------------

CRASH_SCRIPT = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    from dali_cli.store import atomic_dir
    from dali_cli.store.artifacts import BoxTable, write_boxes
    from dali_cli.store.manifest import BuildResult, run_stage

    out, step, exchange, value = sys.argv[1], sys.argv[2], sys.argv[3] == "1", float(sys.argv[4])
    print(os.getpid(), flush=True)
    if not exchange:
        atomic_dir._exchange = lambda a, b: False
    def after_step(name):
        if name == step:
            os._exit(137)  # as if killed: no cleanup, no finally blocks
    atomic_dir.after_step = after_step
    def build(tmp):
        if step == "build":
            os._exit(137)
        write_boxes(tmp, BoxTable.from_arrays(["a"], np.full((1, 7), value)))
        return BuildResult(counts={"value": value})
    run_stage("demo", out, {}, {"v": value}, build, echo=lambda m: None)
    """
)


def _value_at(out: Path) -> float | None:
    """The artifact's recorded value if `out` is complete (manifest written last), else None."""
    manifest = read_manifest(out)
    return None if manifest is None else manifest["outputs"]["counts"]["value"]


@pytest.mark.parametrize(
    "exchange, step",
    [
        (True, "build"),
        (True, "created"),
        (True, "marked"),
        (True, "exchanged"),
        (True, "unmarked"),
        (True, "emptied"),
        (False, "build"),
        (False, "retired"),
        (False, "renamed"),
        (False, "emptied"),
    ],
)
def test_a_replace_killed_at_any_step_loses_nothing_and_the_next_run_recovers(
    tmp_path, exchange, step
):
    out = tmp_path / "out"
    run_stage("demo", out, {}, {"v": 1.0}, build_boxes(1.0), echo=quiet)
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    crashed = subprocess.run(
        [sys.executable, "-c", CRASH_SCRIPT, str(out), step, "1" if exchange else "0", "2.0"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert crashed.returncode == 137, crashed.stderr
    leftovers = sorted(p.name for p in tmp_path.glob("out.old-*"))
    # the invariant: `out` is the complete old or new artifact, or missing with the complete old
    # one kept in out.old-<pid>
    if out.exists():
        assert _value_at(out) in (1.0, 2.0)
    else:
        assert step == "retired" and len(leftovers) == 1
        assert _value_at(tmp_path / leftovers[0]) == 1.0
    # the next run of any stage on that path restores or cleans, then decides as usual
    messages: list[str] = []
    outcome = run_stage("demo", out, {}, {"v": 2.0}, build_boxes(2.0), echo=messages.append)
    assert _value_at(out) == 2.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    if step == "retired":
        assert any("restored" in m for m in messages) and outcome.status == "ran"
    if step in ("renamed", "exchanged", "unmarked", "emptied"):
        assert outcome.status == "skipped"  # the new artifact was complete: up to date


def pid_namespaces_unavailable() -> str | None:
    """Why a process cannot be started in a fresh PID namespace here (None when it can)."""
    if shutil.which("unshare") is None:
        return "no unshare(1) on this machine"
    for flags in (["-pf", "--mount-proc"], ["-Upf", "--mount-proc"]):
        probe = subprocess.run(["unshare", *flags, "true"], capture_output=True, timeout=30)
        if probe.returncode == 0:
            return None
    return "unshare -pf / -Upf is not permitted here (no CAP_SYS_ADMIN, no user namespaces)"


def in_fresh_pid_namespace(*args: str) -> subprocess.CompletedProcess:
    """CRASH_SCRIPT with `args` as the first process of a new PID namespace, as in a container
    restart: every start gets the same pid."""
    flags = ["-pf", "--mount-proc"]
    if subprocess.run(["unshare", *flags, "true"], capture_output=True).returncode != 0:
        flags = ["-Upf", "--mount-proc"]
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    command = ["unshare", *flags, sys.executable, "-c", CRASH_SCRIPT, *args]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)


KILL_STEPS = [  # (exchange, step, replacing an artifact)
    *[(True, step, True) for step in ("build", "created", "marked", "exchanged", "unmarked",
                                       "emptied")],
    *[(False, step, True) for step in ("retired", "renamed", "emptied")],
    *[(True, step, False) for step in ("build", "created", "renamed")],
]  # fmt: skip


@pytest.mark.parametrize("exchange, step, replacing", KILL_STEPS)
def test_a_run_killed_at_any_step_in_a_fresh_pid_namespace_is_finished_by_the_rerun(
    tmp_path, exchange, step, replacing
):
    """In a container every restart has the same pid: a run killed right after it created its
    temporary directory (before marking it), or while deleting the artifact it replaced, must
    not leave anything the rerun (same pid) refuses or leaves behind."""
    reason = pid_namespaces_unavailable()
    if reason:
        pytest.skip(reason)
    out = tmp_path / "out"
    if replacing:
        run_stage("demo", out, {}, {"v": 1.0}, build_boxes(1.0), echo=quiet)
    flag = "1" if exchange else "0"
    crashed = in_fresh_pid_namespace(str(out), step, flag, "2.0")
    assert crashed.returncode == 137, crashed.stderr
    if out.exists():  # never half an artifact, never none when there was one
        assert _value_at(out) in (1.0, 2.0)
    else:
        assert not replacing or any(_value_at(p) == 1.0 for p in tmp_path.glob("out.old-*"))
    assert len(list(tmp_path.iterdir())) > 1, "the kill left nothing to recover: no test"
    rerun = in_fresh_pid_namespace(str(out), "none", flag, "2.0")
    assert rerun.returncode == 0, rerun.stderr
    assert rerun.stdout.split()[0] == crashed.stdout.split()[0]  # the same pid again
    assert "Traceback" not in rerun.stderr
    assert _value_at(out) == 2.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no remnant, no lock


def test_recovery_restores_the_newest_complete_retired_artifact_only_when_out_is_missing(tmp_path):
    out = tmp_path / "out"
    run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet)
    dead = _dead_pid()
    mark_leftover(out, out, "old")  # what replace_directory does before retiring it
    os.rename(out, tmp_path / f"out.old-{dead}")
    half_built = tmp_path / f"out.tmp-{dead}"  # a half-built directory of the same dead run
    half_built.mkdir()
    mark_leftover(half_built, out, "tmp")
    done = recover_interrupted(out, quiet)
    assert _value_at(out) == 1.0 and len(done) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet).status == "skipped"


def test_recovery_never_adopts_a_directory_by_its_name(tmp_path):
    """A user's `out.old-2023` backup and `out.tmp-1999` scratch directory, named like dali's
    leftovers but not created by dali, are neither restored nor deleted, whether `out` exists
    or not; a leftover whose pid now names a live process is still dali's to clean."""
    out = tmp_path / "out"
    run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet)
    backup = tmp_path / "out.old-2023"
    shutil.copytree(out, backup)  # a complete dali artifact, copied by the user
    scratch = tmp_path / "out.tmp-1999"
    scratch.mkdir()
    (scratch / "notes.txt").write_text("mine")
    reused = tmp_path / f"out.tmp-{os.getppid()}"  # dali's, its pid now a live process
    reused.mkdir()
    mark_leftover(reused, out, "tmp")
    before = {p: snapshot(p) for p in (backup, scratch)}
    messages: list[str] = []
    run_stage("demo", out, {}, {}, build_boxes(2.0), force=True, echo=messages.append)
    assert {p: snapshot(p) for p in (backup, scratch)} == before
    assert not reused.exists() and not any("out.old-2023" in m for m in messages)
    shutil.rmtree(out)
    run_stage("demo", out, {}, {}, build_boxes(3.0), echo=quiet)
    assert _value_at(out) == 3.0 and {p: snapshot(p) for p in (backup, scratch)} == before


def test_a_directory_named_like_this_runs_temporary_is_neither_used_nor_refused(tmp_path):
    """Temporary names carry a run token, not only the pid: a directory `out.tmp-<my pid>`
    (a user's, or one a run with this pid left in another PID namespace) is never this run's
    name, so the run neither writes into it nor stops at it."""
    out = tmp_path / "out"
    mine = tmp_path / f"out.tmp-{os.getpid()}"
    mine.mkdir()
    (mine / "keep.txt").write_text("mine")
    assert run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet).status == "ran"
    assert snapshot(mine) == {"keep.txt": b"mine"} and _value_at(out) == 1.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", mine.name]


def test_the_lock_file_never_follows_a_symbolic_link(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / ".out.lock").symlink_to(victim)
    with pytest.raises(OutputPathError, match="lock file"):
        run_stage("demo", tmp_path / "out", {}, {}, build_boxes(1.0), echo=quiet)
    assert victim.read_text() == "precious" and not (tmp_path / "out").exists()
    (tmp_path / ".out.lock").unlink()
    (tmp_path / ".out.lock").write_text("my notes")  # a user's file of that name
    with pytest.raises(OutputPathError, match="lock file"):
        run_stage("demo", tmp_path / "out", {}, {}, build_boxes(1.0), echo=quiet)
    assert (tmp_path / ".out.lock").read_text() == "my notes"
    (tmp_path / ".out.lock").write_text("12345\n")  # a dead run's lock: taken over
    assert run_stage("demo", tmp_path / "out", {}, {}, build_boxes(1.0), echo=quiet).status == "ran"


def test_a_directory_with_a_metrics_file_is_an_eval_output_only_for_eval(tmp_path):
    """`{"sizes": 1, "mine": "precious"}` is not dali's metrics file; and even a real eval
    directory is only eval's to replace, never another stage's."""
    evald = tmp_path / "evald"
    evald.mkdir()
    (evald / "metrics.json").write_text('{"sizes": 1, "mine": "precious"}')
    for stage in ("synth", "eval"):
        with pytest.raises(OutputPathError, match="without a dali manifest"):
            run_stage(stage, evald, {}, {}, build_boxes(1.0), echo=quiet)
    (evald / "metrics.json").write_text('{"Car": {"bev": {}}, "sizes": {"pred": [4, 2, 1.5]}}')
    with pytest.raises(OutputPathError, match="without a dali manifest"):
        run_stage("synth", evald, {}, {}, build_boxes(1.0), echo=quiet)
    assert run_stage("eval", evald, {}, {}, build_boxes(1.0), echo=quiet).status == "ran"


# --- one writer per output -------------------------------------------------------------------


def test_a_second_writer_of_the_same_output_is_refused(tmp_path):
    """Two identical commands on one --out must not both report success."""
    out = tmp_path / "out"
    build = build_boxes(1.0)
    with OutputLock(out.resolve()):  # another process is building `out`
        with pytest.raises(OutputBusyError, match=rf"pid {os.getpid()}"):
            run_stage("demo", out, {}, {}, build, echo=quiet)
    assert not out.exists()
    run_stage("demo", out, {}, {}, build, echo=quiet)  # released: the next run goes ahead
    assert _value_at(out) == 1.0 and not (tmp_path / ".out.lock").exists()


def test_racing_processes_to_one_new_out_leave_one_complete_artifact(tmp_path):
    out = tmp_path / "out"
    script = textwrap.dedent(
        """
        import sys, time
        import numpy as np
        from dali_cli.store.artifacts import BoxTable, write_boxes
        from dali_cli.store.manifest import run_stage
        def build(tmp):
            time.sleep(1.0)
            write_boxes(tmp, BoxTable.from_arrays(["a"], np.ones((1, 7))))
            return {"value": 1.0}
        run_stage("demo", sys.argv[1], {}, {}, build)
        """
    )
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(out)],
            env=env,
            stderr=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    results = [(run.wait(timeout=120), run.stdout.read() + run.stderr.read()) for run in runs]
    assert "ENOTEMPTY" not in "".join(r[1] for r in results)
    assert sorted(code for code, _ in results) in ([0, 0], [0, 1])  # second refused or up to date
    assert _value_at(out) == 1.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# --- skip decisions hash the files -----------------------------------------------------------


def test_an_input_edited_under_its_unchanged_manifest_makes_consumers_stale(tmp_path):
    """Editing T/boxes.parquet but keeping T's manifest must not leave ppcg-rc 'up to date'."""
    source = tmp_path / "source"
    run_stage("demo", source, {}, {}, build_boxes(1.0), echo=quiet)
    out = tmp_path / "out"
    run_stage("consume", out, {"source": source}, {}, build_boxes(5.0), echo=quiet)
    manifest_bytes = (source / "manifest.json").read_bytes()
    write_boxes(source, BoxTable.from_arrays(["a"], np.full((1, 7), 3.0)))  # hand edit
    assert (source / "manifest.json").read_bytes() == manifest_bytes
    outcome = run_stage("consume", out, {"source": source}, {}, build_boxes(5.0), echo=quiet)
    assert outcome.status == "ran" and "inputs changed: source" in outcome.reason
    # and the edited artifact itself is no longer up to date (synth --dry-run on T)
    outcome = run_stage("demo", source, {}, {}, build_boxes(1.0), dry_run=True, echo=quiet)
    assert outcome.status == "dry-run" and "changed since" in outcome.reason


def test_content_hash_sees_an_edit_that_restores_size_and_mtime(tmp_path):
    """The per-file cache is keyed by identity including ctime, which `touch` cannot restore."""
    path = tmp_path / "data.bin"
    path.write_bytes(b"a" * 100)
    first = content_hash(path)
    stat = path.stat()
    path.write_bytes(b"b" * 100)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    assert content_hash(path) != first
    path.write_bytes(b"a" * 100)
    assert content_hash(path) == first


def test_file_hashes_are_cached_across_the_commit_rename(tmp_path, monkeypatch):
    """An artifact's files are hashed while it is built; reading it next must not hash again."""
    import dali_cli.store.file_hashes as file_hashes

    out = tmp_path / "out"
    run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet)
    reads: list[str] = []
    real_open = open

    def counting_open(path, *args, **kwargs):
        reads.append(str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(file_hashes, "open", counting_open, raising=False)
    assert content_hash(out) == read_manifest(out)["content_hash"]
    assert reads == []


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_eval_out_may_not_be_an_input_nor_a_foreign_file(tmp_path):
    target = make_target(tmp_path / "T")
    before = snapshot(target)
    base = ["eval", "--pred", str(target), "--gt", str(target)]
    inside = CliRunner().invoke(main, [*base, "--out", str(target / "metrics.json")])
    assert inside.exit_code != 0 and "inside the pred input" in inside.output
    assert snapshot(target) == before
    foreign = tmp_path / "notes.json"
    foreign.write_text('{"mine": true}')
    refused = CliRunner().invoke(main, [*base, "--out", str(foreign)])
    assert refused.exit_code != 0 and "not a dali metrics file" in refused.output
    assert foreign.read_text() == '{"mine": true}'
    metrics = tmp_path / "eval" / "metrics.json"
    for _ in range(2):  # a dali metrics file is replaced
        result = CliRunner().invoke(main, [*base, "--out", str(metrics)])
        assert result.exit_code == 0, result.output
    assert "sizes" in json.loads(metrics.read_text())


def test_eval_dry_run_to_a_metrics_file_writes_nothing(tmp_path):
    target = make_target(tmp_path / "T")
    base = ["eval", "--pred", str(target), "--gt", str(target)]
    metrics = tmp_path / "eval" / "metrics_kitti.json"
    dry = CliRunner().invoke(main, [*base, "--out", str(metrics), "--dry-run"])
    assert dry.exit_code == 0, dry.output
    assert "would run" in dry.output and not metrics.exists()
    assert not (tmp_path / "eval").exists() or not any((tmp_path / "eval").iterdir())
    written = CliRunner().invoke(main, [*base, "--out", str(metrics)])
    assert written.exit_code == 0 and metrics.is_file()
    before = metrics.read_bytes()
    again = CliRunner().invoke(main, [*base, "--out", str(metrics), "--dry-run"])
    assert again.exit_code == 0 and metrics.read_bytes() == before
    terminal = CliRunner().invoke(main, [*base, "--dry-run"])
    assert terminal.exit_code == 0 and "AP_3D" not in terminal.output


def test_a_file_output_inside_an_artifact_only_where_the_artifact_allows_it(tmp_path):
    """metrics_kitti.json may be added to an eval artifact (the Makefile's KITTI-protocol eval),
    nothing may be written into another stage's artifact behind its manifest."""
    target = make_target(tmp_path / "T")
    base = ["eval", "--pred", str(target), "--gt", str(target)]
    for stage in ("eval", "pseudo-label"):
        run_stage(stage, tmp_path / stage, {}, {}, build_boxes(1.0), echo=quiet)
    added = CliRunner().invoke(
        main, [*base, "--out", str(tmp_path / "eval" / "metrics_kitti.json")]
    )
    assert added.exit_code == 0, added.output
    before = snapshot(tmp_path / "pseudo-label")
    for name in ("metrics_kitti.json", "metrics.json"):
        refused = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "pseudo-label" / name)])
        assert refused.exit_code == 1 and "inside the dali artifact" in refused.output
    assert snapshot(tmp_path / "pseudo-label") == before


# --- a full disk -------------------------------------------------------------------------------


def test_a_lock_that_cannot_be_written_on_a_full_disk_is_named_and_not_left(tmp_path, monkeypatch):
    from dali_cli.runtime.errors import WriteError
    from dali_cli.store import atomic_dir

    def full(*_args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic_dir.os, "pwrite", full)
    out = tmp_path / "out"
    with pytest.raises(WriteError, match=rf"^{out}: writing failed: No space left on device"):
        run_stage("demo", out, {}, {}, build_boxes(1.0), echo=quiet)
    assert list(tmp_path.iterdir()) == []  # no 0-byte .out.lock


def test_torch_save_on_a_full_disk_is_a_write_error_with_the_bytes_it_needed(tmp_path, monkeypatch):
    import torch

    from dali_cli.runtime.errors import WriteError
    from dali_cli.store import disk_space

    def torn(value, path):
        Path(path).write_bytes(b"PK" * 100)  # what torch's writer got out before the disk filled
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 1544768")

    monkeypatch.setattr(torch, "save", torn)
    monkeypatch.setattr(disk_space, "free_bytes", lambda path: 4096)
    out = tmp_path / "out"
    run_stage("demo", out, {}, {"v": 1}, build_boxes(1.0), echo=quiet)
    before = snapshot(out)

    def build(tmp):
        build_boxes(2.0)(tmp)
        disk_space.save_torch({"w": torch.zeros(1000)}, tmp / "model.pt")

    with pytest.raises(WriteError) as caught:
        run_stage("demo", out, {}, {"v": 2}, build, echo=quiet)
    message = str(caught.value)
    assert message.startswith(f"{out}: writing failed: No space left on device")
    assert "model.pt; needs 4.0 kB (4000 bytes), 4.1 kB (4096 bytes) free" in message
    assert "\n" not in message and "nothing was replaced" in message
    assert snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_torch_writer_failure_with_room_left_is_an_io_error_not_a_traceback(
    tmp_path, monkeypatch
):
    import torch

    from dali_cli.store import disk_space

    def broken(value, path):
        raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")

    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(OSError) as caught:
        disk_space.save_torch({"w": torch.zeros(4)}, tmp_path / "m.pt")
    assert caught.value.errno == errno.EIO and "file write failed" in caught.value.strerror
    assert caught.value.filename == str(tmp_path / "m.pt")
