"""Test helper (not part of the package): the inputs of a model stage run with a stub detector:
a target frame set and a model directory holding only model.json (the stub replaces the network)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dali_cli.store.artifacts import write_frameset


def write_stub_inputs(tmp_path: Path, clouds: list[np.ndarray]) -> tuple[Path, Path]:
    """tmp_path/target (frames "000", "001", ... of the kitti profile) and tmp_path/model."""
    target = tmp_path / "target"
    target.mkdir()
    write_frameset(
        target, [(f"{i:03d}", points) for i, points in enumerate(clouds)], sensor="kitti"
    )
    model = tmp_path / "model"
    model.mkdir()
    (model / "model.json").write_text(json.dumps({"config": {"sensor": "waymo"}}))
    return target, model


def pseudo_label_cli(model: Path, target: Path, out: Path, *options: str):
    """`dali pseudo-label` at s = 1 through the CLI (click's CliRunner result)."""
    from click.testing import CliRunner

    from dali_cli.cli import main

    return CliRunner().invoke(
        main,
        ["pseudo-label", "--model", str(model), "--data", str(target), "--scale", "1.0",
         "--out", str(out), "--no-progress", *options],
    )  # fmt: skip
