"""Stage: retrain — train on the labelled source plus PPCG frame sets (pseudo points + pseudo boxes),
alternating source and PPCG batches, from the previous model or from scratch (paper Alg. 1).
Raw target frames are never read. Same checkpoint format as pretrain."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dali_cli.detector import training_stage
from dali_cli.detector.training_stage import PreparedTraining, TrainingOptions
from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.manifest import StageOutcome, content_hash

INIT_FROM = ("previous", "scratch")
SOURCE_SIZES = ("init", "sn")


def parse_mix(text: str, ppcg_count: int) -> tuple[int, ...]:
    """'1:1' -> source : all PPCG sets pooled; '2:1:1' -> source : each PPCG set separately."""
    try:
        parts = tuple(int(p) for p in text.split(":"))
    except ValueError:
        raise ParameterError("mix", f"must look like 1:1, got '{text}'") from None
    if len(parts) not in (2, 1 + ppcg_count) or min(parts) < 1:
        raise ParameterError(
            "mix",
            f"'{text}': give source:ppcg (pooled) or one positive weight per set "
            f"(source + {ppcg_count} PPCG sets)",
        )
    return parts


def drop_boxless_sets(paths: list[Path], sets: list, weights: tuple[int, ...]):
    """PPCG sets without a single box of the trained labels are left out: their frames still
    hold the target's cars (pseudo-labelling found none, e.g. after a PTSN no-detection
    fallback), and training on them would teach that those cars are background.

    Returns (the kept sets, the mix for [source, *datasets], one message per dropped set)."""
    keep = [i for i, data in enumerate(sets) if data.num_boxes > 0]
    messages = [
        f"PPCG set {paths[i]} has no boxes to train on: left out (its cars would be learned as "
        "background)"
        for i in range(len(sets))
        if i not in keep
    ]
    kept = [sets[i] for i in keep]
    if not kept:
        messages.append("no PPCG set has boxes: this retraining sees the source frames only")
        return kept, (weights[0],), messages
    if len(weights) == 2:  # source : all PPCG sets pooled
        return kept, weights, messages
    return kept, (weights[0], *(weights[1 + i] for i in keep)), messages


def expected_size_of(ptsn_dir: str | Path) -> tuple[float, float, float]:
    """E_est (l, w, h in m) recorded by a ptsn-sweep: the label-free expected target size."""
    from dali_cli.store.scale_file import read_scale

    e_est = read_scale(ptsn_dir).e_est
    if e_est is None or not all(isinstance(v, int | float) and v > 0 for v in e_est):
        raise StageError(f"{ptsn_dir}: scale.json has no valid E_est (l, w, h) to size the source")
    return tuple(float(v) for v in e_est)


def pool(sets: list, name: str):
    """Concatenate labelled sets into one (frame ids prefixed by their set's index)."""
    from dali_cli.detector import LabeledFrames
    from dali_cli.detector.data import chain_points

    first = sets[0]
    return LabeledFrames(
        name=name,
        sensor=first.sensor,
        mount_height_m=first.mount_height_m,
        frame_ids=[f"{i}/{f}" for i, s in enumerate(sets) for f in s.frame_ids],
        points=chain_points([s.points for s in sets]),
        boxes=[b for s in sets for b in s.boxes],
    )


def run_retrain(
    init: str | Path,
    source: str | Path,
    ppcg: list[str | Path],
    out: str | Path,
    *,
    training: TrainingOptions = TrainingOptions(),
    init_from: str = "previous",
    mix: str = "1:1",
    source_size: str = "init",
    target_profile: str | None = None,
    target_size: tuple[float, float, float] | None = None,
    target_size_from: str | Path | None = None,
    labels: tuple[str, ...] = ("Car",),
    sensors_path: str | Path | None = None,
    force: bool = False,
    dry_run: bool = False,
) -> StageOutcome:
    """Retrain the detector of `init` on `source` + the PPCG sets `ppcg` with `training`; write
    a checkpoint to `out`.

    `source_size` "init": the source keeps the size normalization the initial model was trained
    with (SN delta or ROS range, from its model.json). "sn": the source boxes are shifted to the
    target's expected mean size `target_size` (or the E_est of the ptsn-sweep `target_size_from`,
    or `target_profile`'s car_mean_lwh_m: label-free statistics), in-box points scaled with
    them, so source and PPCG labels agree on the target's car size (metres).
    """
    init, source, out = Path(init), Path(source), Path(out)
    ppcg = [Path(p) for p in ppcg]
    weights = checked_mix(ppcg, init_from, mix)
    target_size = shift_size(
        source_size, target_profile, target_size, target_size_from, sensors_path
    )
    params = {
        "init_from": init_from,
        "mix": list(weights),
        "source_size": source_size,
        "target_size": list(target_size) if source_size == "sn" else None,
        "labels": list(labels),
    }
    inputs = {"init": init, "source": source, "ppcg": ppcg}

    def prepare() -> PreparedTraining:
        from dali_cli.detector import Detector
        from dali_cli.detector.scans_for import for_scans_of

        previous = Detector.load(init)
        # adapted to the target: the scans of its PPCG frames (the target's, points replaced)
        config = for_scans_of(previous.config, ppcg[0], sensors_path)
        load = dict(config=config, labels=labels, sensors_path=sensors_path, stream=True)
        shift = (target_size, target_profile) if source_size == "sn" else None
        source_data, source_augmentation, card = load_source(
            source, previous.card, load, training, shift
        )
        pseudo_sets, mix, skipped = load_ppcg_sets(ppcg, weights, load)
        pooled = len(weights) == 2 and pseudo_sets
        datasets = [source_data, *([pool(pseudo_sets, "ppcg")] if pooled else pseudo_sets)]
        for data in datasets:
            training_stage.attach_database(data, config, training.augment)
        augmentations = [source_augmentation] + [training.augmentation() for _ in datasets[1:]]
        state = previous.net.state_dict() if init_from == "previous" else None
        net = training_stage.seeded_network(config, training.seed, state)
        meta = retrain_meta(card, datasets, init, init_from, source, ppcg, weights, training.seed)
        return PreparedTraining(
            net, datasets, augmentations, training.settings(mix=mix),
            meta=meta,
            counts={
                "source_frames": len(source_data),
                "ppcg_frames": int(sum(len(d) for d in pseudo_sets)),
            },
            notes=[
                f"detector: {net.config.name} (not the paper's SECOND-IoU)",
                "raw target frames not used: source + PPCG frame sets only",
                *skipped,
            ],
        )  # fmt: skip

    return training_stage.run_training_stage(
        "retrain", out, inputs, params, prepare, force, dry_run, training
    )


def retrain_meta(
    card, datasets: list, init: Path, init_from: str, source: Path, ppcg: list[Path],
    weights: tuple[int, ...], seed: int,
) -> dict:  # fmt: skip
    """model.json's card (carried forward from `init`'s), provenance and metrics (frames,
    boxes and mean l/w/h of each data set) of a retrained model."""
    provenance = {
        "stage": "retrain",
        "init": str(init),
        "init_hash": content_hash(init),
        "init_from": init_from,
        "source": str(source),
        "source_sensor": datasets[0].sensor,
        "ppcg": [str(p) for p in ppcg],
        "mix": list(weights),
        "size_norm": card.size_norm,
        "sn_delta_lwh": None if card.sn_delta_lwh_m is None else list(card.sn_delta_lwh_m),
        "ros_range": None if card.ros_range is None else list(card.ros_range),
        "target_profile": card.target_profile,
        "seed": seed,
    }
    metrics = {
        "frames": {d.name: len(d) for d in datasets},
        "boxes": {d.name: d.num_boxes for d in datasets},
        "mean_lwh_m": {d.name: d.mean_lwh().tolist() for d in datasets},
    }
    return {
        "card": card.carried_forward("retrain").to_dict(),
        "provenance": provenance,
        "metrics": metrics,
    }


def checked_mix(ppcg: list[Path], init_from: str, mix: str) -> tuple[int, ...]:
    """The batch weights of `mix` for the PPCG sets `ppcg`; ParameterError for no PPCG set, an
    unknown `init_from` or a malformed mix."""
    if not ppcg:
        raise ParameterError("ppcg", "needs at least one PPCG frame set directory")
    if init_from not in INIT_FROM:
        raise ParameterError(
            "init_from", f"must be one of {', '.join(INIT_FROM)}, got '{init_from}'"
        )
    return parse_mix(mix, len(ppcg))


def shift_size(
    source_size: str, target_profile: str | None, target_size, target_size_from, sensors_path
) -> tuple[float, float, float] | None:
    """The target mean car size (l, w, h in m) the source is shifted to (source_size sn: the
    given size, else the E_est of the sweep `target_size_from`, else the profile's), or None
    (init: INIT's own normalization); an unknown source_size is a ParameterError."""
    if source_size not in SOURCE_SIZES:
        raise ParameterError(
            "source_size", f"must be one of {', '.join(SOURCE_SIZES)}, got '{source_size}'"
        )
    if source_size != "sn":
        return target_size
    if target_size is None and target_size_from is not None:
        target_size = expected_size_of(target_size_from)
    return training_stage.target_car_size(
        target_profile, target_size, sensors_path, "source size sn"
    )


def load_source(source: Path, card, load: dict, training: TrainingOptions, shift=None):
    """The labelled source, sized as the retrained model expects; returns (data, augmentation,
    the card to carry forward). `shift` None: the initial model's size normalization (SN delta
    applied to the boxes and their points, or ROS as the augmentation's object scaling).
    `shift` (target size l, w, h in m, target profile): the boxes shifted to that mean size
    (points scaled with them), recorded in the card as SN."""
    from dali_cli.detector import load_labeled, size_normalize

    data = load_labeled(source, **load)
    augmentation = training.augmentation()
    if shift is not None:
        target_size, target_profile = shift
        delta = np.asarray(target_size) - data.mean_lwh()
        data = size_normalize(data, delta)
        card = dataclasses.replace(
            card, size_norm="sn", sn_delta_lwh_m=tuple(float(d) for d in delta),
            ros_range=None, target_profile=target_profile,
        )  # fmt: skip
        return data, augmentation, card
    if card.sn_delta_lwh_m is not None:
        data = size_normalize(data, np.asarray(card.sn_delta_lwh_m))
    if card.ros_range is not None:
        augmentation.object_scale = card.ros_range
    return data, augmentation, card


def load_ppcg_sets(ppcg: list[Path], weights: tuple[int, ...], load: dict):
    """The PPCG frame sets (an empty one is an error), those without boxes left out with a
    warning; returns (sets, mix, messages) as drop_boxless_sets."""
    from dali_cli.detector import load_labeled

    sets = [load_labeled(p, **load) for p in ppcg]
    for path, data in zip(ppcg, sets, strict=True):
        if len(data) == 0:
            raise StageError(f"{path}: PPCG frame set has no frames")
    sets, mix, skipped = drop_boxless_sets(ppcg, sets, weights)
    for message in skipped:
        console.warn(message)
    return sets, mix, skipped
