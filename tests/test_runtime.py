"""Training threads and the machine record of training manifests: a stage that
runs alone uses every available core whatever the load average says; `--threads` overrides; the
manifest and model.json record threads, device, CPU model and torch version."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner
from test_retrain import SMALL  # the tiny detector config of the training tests
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.runtime import cores
from dali_cli.runtime import machine as runtime
from dali_cli.sensors import get_profile
from dali_cli.store.manifest import read_manifest


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    root = tmp_path_factory.mktemp("runtime")
    write_toy_dataset(
        root / "source", get_profile("kitti"), frames=2, seed=4, cars_per_frame=2,
        x_range_m=(6.0, 20.0), y_range_m=(-8.0, 8.0), beams=16, points_per_beam=200,
    )  # fmt: skip
    (root / "config.json").write_text(json.dumps(SMALL))
    return root


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_cpu_model_is_read_from_cpuinfo(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 7B13\n")
    assert runtime.cpu_model(cpuinfo) == "AMD EPYC 7B13"
    assert runtime.cpu_model(tmp_path / "missing")  # falls back to platform, never empty


def test_training_threads_default_to_every_core_whatever_the_load(monkeypatch):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    monkeypatch.setattr(cores.os, "getloadavg", lambda: (7.5, 7.5, 7.5))  # a busy make chain
    assert runtime.available_cores() == 3
    assert runtime.training_threads(None) == 3
    assert runtime.training_threads(1) == 1
    with pytest.raises(ValueError):
        runtime.training_threads(0)


def pretrain(source, out, *extra):
    args = ["pretrain", "--source", str(source / "source"), "--out", str(out), "--epochs", "1",
            "--detector-config", str(source / "config.json"), "--no-progress", *extra]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return read_manifest(out), json.loads((out / "model.json").read_text())


def test_pretrain_uses_every_core_and_records_the_machine(
    source, tmp_path, monkeypatch, restore_threads
):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(cores.os, "getloadavg", lambda: (1.9, 1.0, 0.5))  # the stage before
    manifest, meta = pretrain(source, tmp_path / "all")
    record = manifest["runtime"]
    assert record["threads"] == 2 and torch.get_num_threads() == 2
    assert record["device"] == "cpu" and record["cpu_model"]
    assert record["torch_version"] == torch.__version__
    assert meta["train"]["runtime"] == record

    manifest, _ = pretrain(source, tmp_path / "one", "--threads", "1")
    assert manifest["runtime"]["threads"] == 1 and torch.get_num_threads() == 1


def test_inference_sets_its_threads_instead_of_torchs_default(monkeypatch, restore_threads):
    """torch's own default follows OMP_NUM_THREADS (a shell's, a Ray worker's) and the physical
    cores; the thread count decides the float sums, so an inference stage sets it as training
    does: every core this process may use, or what it is given."""
    from dali_cli.runtime.device import inference_setup

    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    torch.set_num_threads(1)  # what OMP_NUM_THREADS=1 leaves torch with
    inference_setup({}, "ptsn_sweep")
    assert torch.get_num_threads() == 2
    inference_setup({"threads": 1}, "pseudo_label")
    assert torch.get_num_threads() == 1


def test_pseudo_label_runs_on_the_threads_it_is_given(
    source, tmp_path, monkeypatch, restore_threads
):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    pretrain(source, tmp_path / "model", "--threads", "1")
    for threads in ("1", "2"):
        torch.set_num_threads(3 - int(threads))  # the other count before the stage
        out = tmp_path / f"pseudo{threads}"
        args = ["pseudo-label", "--model", str(tmp_path / "model"), "--data",
                str(source / "source"), "--scale", "1.0", "--threads", threads, "--out", str(out),
                "--no-progress"]  # fmt: skip
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, result.output
        assert read_manifest(out)["runtime"]["threads"] == int(threads)
