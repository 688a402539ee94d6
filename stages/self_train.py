"""Stage: self-train — fine-tune a final model on the raw target frames with its own pseudo labels,
in the PTSN-scaled frame (the paper's ‡ for nuScenes → KITTI). Same checkpoint format and training
body as pretrain and retrain; target labels are never read (the boxes come from --pseudo).

Which frame: the pseudo boxes of `dali pseudo-label` are de-scaled to the original target frame,
but the model that made them sees the target scaled by ŝ about the ground (`Detector.predict(...,
scale=ŝ)`), and `dali eval --scale-from PTSN_DIR` evaluates it that way. So self-training scales the
target points *and* the pseudo boxes by ŝ (`scale_about_ground`): the network keeps learning the
scaled frame it is evaluated in, and the fine-tuned model is evaluated with the same ŝ
(`--scale-from` of the sweep that made the pseudo labels). Training on the original frame instead
would teach it target-sized cars at s = 1, and evaluating that with ŝ would shrink every box twice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dali_cli.detector.training_stage import (
    PreparedTraining,
    TrainingOptions,
    attach_database,
    run_training_stage,
    seeded_network,
)
from dali_cli.runtime.errors import StageError
from dali_cli.store.manifest import StageOutcome, check_made_from, content_hash


def pseudo_label_scale(pseudo: Path) -> float:
    """The scale ŝ at which the pseudo boxes of `pseudo` were made: its scale.json (the
    ScaleResult pseudo-label writes), or, for outputs of earlier versions without one, the
    boxes' `scale` column."""
    from dali_cli.store.artifacts import read_boxes
    from dali_cli.store.scale_file import read_scale, scale_path

    if scale_path(pseudo).is_file():
        return read_scale(pseudo).scale
    table = read_boxes(pseudo)
    if "scale" not in table.columns:
        raise StageError(
            f"{pseudo}: no scale.json and no 'scale' column in boxes.parquet (not from "
            "`dali pseudo-label`); give the scale"
        )
    scales = np.unique(np.asarray(table["scale"], np.float64))
    if len(scales) != 1 or not (np.isfinite(scales[0]) and scales[0] > 0):
        raise StageError(
            f"{pseudo}/boxes.parquet: expected one positive 'scale' for every box, "
            f"got {scales[:5].tolist()}; give --scale S"
        )
    return float(scales[0])


def run_self_train(
    init: str | Path,
    target: str | Path,
    pseudo: str | Path,
    out: str | Path,
    *,
    training: TrainingOptions = TrainingOptions(),
    scale: float | None = None,
    pseudo_from: str | Path | None = None,
    sensors_path: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """Fine-tune the model of `init` on `target`'s frames with the boxes of `pseudo` (made from
    `target`, or from `pseudo_from`: the same scans at more beams, whose frame ids `target`
    shares), both scaled by ŝ (default: the pseudo labels' own scale), with `training`;
    write to `out`."""
    init, target, pseudo, out = Path(init), Path(target), Path(pseudo), Path(out)
    check_made_from(pseudo, "target", target if pseudo_from is None else pseudo_from)
    train_scale = pseudo_label_scale(pseudo) if scale is None else float(scale)
    params = {"scale": train_scale}
    inputs = {"init": init, "target": target, "pseudo": pseudo}
    if pseudo_from is not None:
        inputs["pseudo_from"] = Path(pseudo_from)

    def prepare() -> PreparedTraining:
        from dali_cli import detector
        from dali_cli.detector.data import scale_about_ground
        from dali_cli.detector.scans_for import for_scans_of

        previous = detector.Detector.load(init)
        config = for_scans_of(previous.config, target, sensors_path)  # adapted to the target
        # frames from the target, boxes from the pseudo labels: the target's labels stay unread
        data = detector.load_labeled(
            target, config, boxes_dir=pseudo, sensors_path=sensors_path, stream=True
        )
        if data.num_boxes == 0:
            raise StageError(f"{pseudo}: no pseudo boxes with points to train on")
        data = scale_about_ground(data, train_scale)
        attach_database(data, config, training.augment)
        net = seeded_network(config, training.seed, previous.net.state_dict())
        provenance = {
            **previous.meta.get("provenance", {}),
            "stage": "self_train",
            "init": str(init),
            "init_hash": content_hash(init),
            "target": str(target),
            "pseudo": str(pseudo),
            "train_scale": train_scale,
            "seed": training.seed,
        }
        metrics = {
            "frames": len(data),
            "boxes": data.num_boxes,
            "scaled_mean_lwh_m": data.mean_lwh().tolist(),
        }
        return PreparedTraining(
            net, [data], [training.augmentation()], training.settings(),
            meta={
                "card": previous.card.carried_forward("self-train").to_dict(),
                "provenance": provenance,
                "metrics": metrics,
            },
            counts={"target_frames": len(data), "pseudo_boxes": data.num_boxes},
            notes=[
                f"detector: {net.config.name} (not the paper's SECOND-IoU)",
                f"trained in the PTSN-scaled frame (s = {train_scale:.4f}): evaluate with the "
                "--scale-from of the sweep that made the pseudo labels",
                "target labels not read: boxes from the pseudo labels",
            ],
        )  # fmt: skip

    return run_training_stage("self_train", out, inputs, params, prepare, force, dry_run, training)
