"""Device selection and torchrun data-parallel training, on the CPU with gloo: the device flags
fail cleanly without a GPU, nothing in the train/infer path uses a default device, a 2-rank
DDP step equals the serial step on the same frames as one batch, a 2-rank `torchrun` pretrain
writes one model that `dali eval` reads, and a failing rank fails the stage with no artifact."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_retrain import SMALL, TOY  # the tiny detector and toy frames of the training tests
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.data import Augmentation, load_labeled
from dali_cli.detector.distributed import World, join, launched, leave
from dali_cli.detector.infer import Detector
from dali_cli.detector.model import PillarCenterNet
from dali_cli.detector.train import TrainSettings, train
from dali_cli.detector.training_stage import attach_database
from dali_cli.runtime.device import DeviceError, parse_device_spec, resolve_device
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.runtime.machine import available_cores
from dali_cli.sensors import get_profile

TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
# the CLI as a module, not the venv's console script: runs wherever dali_cli imports (a GPU
# machine's system python with the package on PYTHONPATH has no `dali` beside its python)
DALI = ["-m", "dali_cli.cli"]


@pytest.fixture(scope="module")
def toy_dir(tmp_path_factory):
    directory = tmp_path_factory.mktemp("toy")
    write_toy_dataset(directory, get_profile("kitti"), seed=3, **{**TOY, "frames": 4})
    return directory


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_device_specs_resolve_and_fail_cleanly(no_cuda, monkeypatch):
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    for spec in ("cuda", "cuda:0", "CUDA:1"):
        with pytest.raises(DeviceError, match="no CUDA GPU"):
            resolve_device(spec)
    for spec in ("gpu", "cuda:", "cuda:x", "cpu:0", ""):
        with pytest.raises(ParameterError):
            parse_device_spec(spec)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == torch.device("cuda", 0)
    assert resolve_device("cuda", local_rank=1) == torch.device("cuda", 1)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(DeviceError, match="GPU 2 does not exist"):
        resolve_device("cuda:2")


@pytest.mark.parametrize("command", ["pretrain", "eval", "pseudo-label", "ptsn-sweep"])
def test_cuda_without_a_gpu_is_an_error_and_writes_nothing(no_cuda, toy_dir, tmp_path, command):
    out = tmp_path / "out"
    args = {
        "pretrain": ["--source", str(toy_dir), "--out", str(out), "--epochs", "1"],
        "eval": ["--model", str(toy_dir), "--data", str(toy_dir), "--out", str(out / "m.json")],
        "pseudo-label": ["--model", str(toy_dir), "--data", str(toy_dir), "--scale", "1",
                         "--out", str(out)],
        "ptsn-sweep": ["--model", str(toy_dir), "--data", str(toy_dir), "--out", str(out)],
    }[command]  # fmt: skip
    before = sorted(p.name for p in tmp_path.iterdir())
    result = CliRunner().invoke(main, [command, *args, "--device", "cuda"])
    assert result.exit_code == 1, result.output
    assert "no CUDA GPU" in result.output and "--device cpu" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_threads_are_shared_by_the_local_ranks(monkeypatch):
    from dali_cli.runtime import cores
    from dali_cli.runtime import machine as runtime

    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    assert runtime.training_threads(None) == 8
    assert runtime.training_threads(None, local_processes=3) == 2
    assert runtime.training_threads(None, local_processes=16) == 1
    assert runtime.training_threads(5, local_processes=4) == 5  # --threads wins
    assert launched({"WORLD_SIZE": "1"}) == World()
    world = launched({"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"})
    assert (world.rank, world.size, world.local_rank, world.local_size) == (3, 4, 1, 2)
    with pytest.raises(StageError, match="torchrun"):
        launched({"WORLD_SIZE": "2"})


def test_train_and_predict_run_on_an_explicit_cpu_device(toy_dir):
    """With torch's default device set to 'meta', any tensor the train or inference path made
    without naming its device would land on 'meta' and fail against the CPU tensors."""
    config = DetectorConfig.from_dict(SMALL)
    data = load_labeled(toy_dir, config)
    attach_database(data, config, augment=True)
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    settings = TrainSettings(epochs=1, batch_size=2, seed=0, log_every=1, device="cuda")
    cpu = torch.device("cpu")
    frames = [p - np.array([0, 0, data.mount_height_m, 0], np.float32) for p in data.points]
    with torch.device("meta"):
        result = train(net, [data], [Augmentation()], settings, progress=False, device=cpu)
        predictions = Detector(net, device=cpu).predict(frames)
    assert result.steps == 2 and result.runtime["device"] == "cpu"
    assert all(p.device == cpu for p in net.parameters())
    assert len(predictions) == len(frames)
    assert all(np.isfinite(row["loss"]) for row in result.log)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ddp_step_worker(rank: int, port: int, toy_dir: str, out: str) -> None:
    """One rank of a 2-process gloo group: one optimizer step, 1 frame per rank."""
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
        LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE="2",
    )  # fmt: skip
    world = join(launched(), torch.device("cpu"))
    try:
        net, result = one_step(toy_dir, batch_size=1, world=world)
        if world.is_main:
            torch.save(
                {
                    "weights": net.state_dict(),
                    "grads": {n: p.grad for n, p in net.named_parameters()},
                    "threads": result.runtime["threads"],
                    "log": result.log,
                },
                out,
            )
    finally:
        leave()


def one_step(toy_dir, batch_size: int, world: World | None = None):
    """A fresh net trained for exactly one step of 2 frames (all ranks together), with every
    augmentation (gt sampling included) on."""
    config = DetectorConfig.from_dict(SMALL)
    data = load_labeled(toy_dir, config)
    attach_database(data, config, augment=True)
    torch.manual_seed(0)
    net = PillarCenterNet(config)
    settings = TrainSettings(epochs=0.5, batch_size=batch_size, seed=5, log_every=1)
    extra = {"world": world} if world is not None else {}
    result = train(
        net, [data], [Augmentation()], settings, progress=False, device=torch.device("cpu"),
        **extra,
    )  # fmt: skip
    assert result.steps == 1 and result.frames == 2
    return net, result


def test_ddp_step_equals_the_serial_step_on_the_global_batch(toy_dir, tmp_path):
    out = tmp_path / "ddp.pt"
    torch.multiprocessing.spawn(
        ddp_step_worker, args=(free_port(), str(toy_dir), str(out)), nprocs=2, join=True
    )
    ddp = torch.load(out, weights_only=True)
    serial, serial_result = one_step(toy_dir, batch_size=2)
    assert ddp["threads"] == max(1, available_cores() // 2)  # the cores shared by 2 local ranks
    # the gradients: equal up to float32 reduction-order noise, 1e-4 of each tensor's largest
    # (a scale error, which Adam's first step ~ lr * sign(g) would hide, is not)
    for name, parameter in serial.named_parameters():
        largest = float(parameter.grad.abs().max())
        error = float((ddp["grads"][name] - parameter.grad).abs().max())
        assert error <= 1e-4 * largest + 1e-9, (name, error, largest)
    # the weights after the step: within 1e-5 wherever the gradient stands above that noise
    # (>= 0.2% of the tensor's largest); where |g| is down at the noise, it can flip the sign of
    # Adam's first step, a difference bounded by 2 lr
    lr = serial_result.log[0]["lr"]
    clear_elements = 0
    for name, parameter in serial.named_parameters():
        difference = (ddp["weights"][name] - parameter.detach()).abs()
        gradient = parameter.grad.abs()
        clear = (gradient >= 2e-3 * gradient.max()) | (gradient == 0)  # 0: no Adam step at all
        clear_elements += int(clear.sum())
        assert float(difference[clear].max()) < 1e-5, name
        assert float(difference.max()) <= 2 * lr * (1 + 1e-3), name
    assert clear_elements > 0.5 * sum(p.numel() for p in serial.parameters())
    for name, value in serial.named_buffers():  # batch-norm statistics of the global batch
        assert torch.allclose(ddp["weights"][name].double(), value.double(), atol=1e-5), name
    assert ddp["log"][0]["loss"] == pytest.approx(serial_result.log[0]["loss"], rel=1e-5)


def torchrun_env() -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.pop("WORLD_SIZE", None)
    return env


def small_config(tmp_path: Path) -> Path:
    path = tmp_path / "small.json"
    path.write_text(json.dumps(SMALL))
    return path


@pytest.mark.slow  # two torchrun ranks, end to end
def test_torchrun_pretrain_writes_one_model_that_eval_reads(toy_dir, tmp_path):
    out = tmp_path / "model"
    run = subprocess.run(
        [*TORCHRUN, *DALI, "pretrain", "--source", str(toy_dir), "--out", str(out), "--epochs",
         "1", "--batch-size", "1", "--device", "cpu", "--no-augment", "--no-progress",
         "--detector-config", str(small_config(tmp_path))],
        capture_output=True, text=True, env=torchrun_env(), timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "small.json"]
    manifest = json.loads((out / "manifest.json").read_text())
    runtime = manifest["runtime"]
    assert runtime["world_size"] == 2 and runtime["backend"] == "gloo"
    assert runtime["device"] == "cpu" and runtime["torch_version"] == torch.__version__
    assert manifest["params"]["world_size"] == 2
    assert manifest["outputs"]["counts"]["steps"] == 2  # 4 frames / (1 per rank x 2 ranks)
    assert "rank 1 of 2 (gloo, DDP)" in run.stderr and "rank 0 of 2" in run.stderr
    metrics = tmp_path / "eval" / "metrics.json"
    result = CliRunner().invoke(
        main, ["eval", "--model", str(out), "--data", str(toy_dir), "--device", "cpu",
               "--out", str(metrics)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    document = json.loads(metrics.read_text())
    assert "Car" in document and document["runtime"]["device"] == "cpu"


@pytest.mark.slow  # two torchrun ranks, end to end
def test_a_failing_rank_fails_the_stage_with_no_artifact(toy_dir, tmp_path):
    script = tmp_path / "flaky_dali.py"
    script.write_text(
        "import importlib, os, sys\n"
        "loader = importlib.import_module('dali_cli.detector.loader')\n"
        "if os.environ['RANK'] == '1':\n"
        "    def lost(*args, **kwargs):\n"
        "        raise RuntimeError('rank 1 lost its frames')\n"
        "    loader.augmented_sample = lost\n"
        "from dali_cli.cli import main\n"
        "sys.exit(main())\n"
    )
    out = tmp_path / "model"
    run = subprocess.run(
        [*TORCHRUN, str(script), "pretrain", "--source", str(toy_dir), "--out", str(out),
         "--epochs", "1", "--batch-size", "1", "--device", "cpu", "--no-progress",
         "--detector-config", str(small_config(tmp_path))],
        capture_output=True, text=True, env=torchrun_env(), timeout=600,
    )  # fmt: skip
    assert run.returncode != 0
    assert "rank 1 lost its frames" in run.stderr
    assert not out.exists()
    leftovers = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("model"))
    assert leftovers == [], leftovers


def make_plan(tmp_path: Path, *variables: str) -> list[str]:
    root = Path(__file__).resolve().parents[1]
    run = subprocess.run(
        ["make", "-n", "-C", str(root), "iter2", f"RUN={tmp_path / 'run'}", *variables],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return [line for line in run.stdout.splitlines() if "dali " in line]


def test_make_nproc_runs_the_training_stages_under_torchrun(tmp_path):
    plan = make_plan(tmp_path, "NPROC=2", "DEVICE=cpu")
    training = [line for line in plan if any(f"dali {s} " in line for s in ("pretrain", "retrain"))]
    assert len(training) == 3  # iter0 pretrain, iter1 and iter2 retrain
    assert all("torchrun --standalone --nproc-per-node 2 " in line for line in training)
    assert all("torchrun" not in line for line in plan if line not in training)
    model_stages = [line for line in plan if any(f"dali {s} " in line for s in
                                                 ("pretrain", "retrain", "ptsn-sweep",
                                                  "pseudo-label", "eval"))]  # fmt: skip
    assert model_stages and all("--device cpu" in line for line in model_stages)
    assert all("torchrun" not in line and "--device" not in line for line in make_plan(tmp_path))
