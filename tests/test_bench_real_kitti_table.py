"""bench/real_kitti_table.py over runs whose metrics are written here: mean ± std over the seeds,
every row minus the control paired by seed, and the bootstrap comparisons as `dali compare`
wrote them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from dali_cli.store.artifacts import BoxTable, FrameSetWriter, write_boxes
from tests.test_evaluate import kitti_columns, row_of_cars

ROOT = Path(__file__).resolve().parents[1]
# per seed: (control, x2) AP_BEV@0.7 moderate on the drive; AP_3D is BEV - 20
BEV = {"s0": (40.0, 50.0), "s1": (44.0, 60.0)}


def metrics(bev: float) -> dict:
    block = lambda value: {"easy": value, "moderate": value, "hard": value}  # noqa: E731
    return {
        "Car": {"bev": block(bev), "3d": block(bev - 20)},
        "Car@0.5": {"bev": block(bev + 20), "3d": block(bev + 10)},
    }


def errors(bev: float) -> dict:
    """The breakdown at IoU 0.7: fixing mislocalized boxes gains 10 (BEV) and 30 (3D),
    background 5 and 1, the rest nothing."""

    def fixed(ap: float, mislocalized: float, background: float) -> dict:
        return {"mislocalized": ap + mislocalized, "background": ap + background,
                "duplicate": ap, "missed": ap}  # fmt: skip

    return {"false_positives": {"0.7": {
        "bev": {"ap": bev, "ap_fixed": fixed(bev, 10, 5)},
        "3d": {"ap": bev - 20, "ap_fixed": fixed(bev - 20, 30, 1)},
    }}}  # fmt: skip


def write(path: Path, document: dict) -> None:
    path.mkdir(parents=True, exist_ok=True)
    (path / "metrics.json").write_text(json.dumps(document))


def make_runs(root: Path) -> tuple[list[Path], Path]:
    data = root / "real-data"
    with FrameSetWriter(data / "drive_labels", "kitti") as writer:
        writer.append("d-0", np.zeros((3, 4), np.float32))
    write_boxes(data / "drive_labels", BoxTable.from_arrays(["d-0"], [[10, 0, 0, 4, 2, 1.5, 0]]))
    runs = []
    for name, (control, x2) in BEV.items():
        run = root / f"real-{name}"
        write(run / "baselines/source_x2_budget/eval_ptsn", metrics(control))
        write(run / "iter2/eval", metrics(x2) | {"errors": errors(x2)})
        write(run / "objects_other/x2", metrics(x2 - 10))
        write(run / "objects_other/control", metrics(control - 10))
        bootstrap = {
            "bev moderate": {"delta": x2 - control, "delta_std": 3.0,
                             "delta_interval_95": [1.0, 20.0], "share_not_above_reference": 0.01},
            "3d moderate": {"delta": x2 - control, "delta_std": 4.0,
                            "delta_interval_95": [-1.0, 21.0], "share_not_above_reference": 0.04},
        }  # fmt: skip
        (run / "compare_real").mkdir(parents=True)
        (run / "compare_real" / "drive-x2.json").write_text(
            json.dumps({"bootstrap": {"rows": {"control": {}, "x2": bootstrap}}})
        )
        runs.append(run)
    return runs, data


def test_means_pairs_and_bootstraps(tmp_path):
    runs, data = make_runs(tmp_path)
    out = tmp_path / "report" / "real-kitti.md"
    result = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "real_kitti_table.py"), *map(str, runs),
         "--data", str(data), "--sets", "drive", "objects_other", "--out", str(out)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    text = out.read_text()
    assert text.strip() == result.stdout.strip()
    lines = text.splitlines()
    x2 = [line for line in lines if line.startswith("| DALI x2 |")]
    # on the drive: BEV 50, 60 -> 55.0 ± 7.1; 3D 30, 40; per seed shown; then on the object set
    assert x2[0].startswith("| DALI x2 | 55.0 ± 7.1 | 35.0 ± 7.1 | 75.0 ± 7.1 | 65.0 ± 7.1 |")
    assert "50.0 / 30.0 · 60.0 / 40.0" in x2[0]
    assert any(line.startswith("| DALI x2 | 45.0 ± 7.1 |") for line in x2[2:])
    # minus the control, seed by seed: 10 and 16 -> +13.0 ± 4.2 on every metric
    assert x2[1].startswith("| DALI x2 | +13.0 ± 4.2 | +13.0 ± 4.2 |") and "+10.0 · +16.0" in x2[1]
    # rows never evaluated stay empty, not zero
    assert any(line.startswith("| DALI x1 | - | - |") for line in lines)
    boot = [line for line in lines if line.startswith("| drive | x2 − control |")]
    assert [line.split(" | ")[2] for line in boot] == ["real-s0", "real-s1"]
    assert "+10.0 ± 3.0 | [+1.0, +20.0] | 0.01" in boot[0]


def test_dali_against_its_control_and_where_ap_is_lost(tmp_path):
    runs, data = make_runs(tmp_path)
    result = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "real_kitti_table.py"), *map(str, runs),
         "--data", str(data), "--sets", "drive"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    lines = result.stdout.splitlines()
    pairs = [line for line in lines if line.startswith("| DALI x2 − control")]
    # x2 − control: +10 and +16 in both BEV and 3D; seeds listed in order
    assert pairs == [
        "| DALI x2 − control (source, x2 budget, PTSN) | +13.0 ± 4.2 | +13.0 ± 4.2 "
        "| +10.0 / +10.0 · +16.0 / +16.0 |"
    ]
    # pairs whose rows were never evaluated stay empty
    assert any(line.startswith("| DALI x2 + ST − control + ST | - | - |") for line in lines)
    losses = [line for line in lines if line.startswith("| DALI x2 | ") and "fixed" not in line]
    loss = next(line for line in losses if "mislocalized (" in line)
    # x2's AP 50 / 30 and 60 / 40 -> means 55.0 / 35.0; mislocalized the largest, +30 in 3D
    assert loss.startswith("| DALI x2 | 55.0 / 35.0 | +10.0 / +30.0 | +5.0 / +1.0 | +0.0 / +0.0 |")
    assert loss.endswith("| mislocalized (+30.0) |")
    # a row without a breakdown gets no line in that table: the control is in the AP table only
    assert sum(line.startswith("| control (source") for line in lines) == 1


def test_a_set_too_small_for_r40_gets_its_ceiling_and_r400(tmp_path):
    """10 counted cars cap AP_R40 at 22.5: the table says so and rescores the saved predictions
    under R400, where finding every car is 100 and finding half of them 50."""
    runs, data = make_runs(tmp_path)
    cars, kitti = row_of_cars(10), kitti_columns(10)
    frames = ["o-0"] * 10
    (data / "objects_few").mkdir()
    write_boxes(data / "objects_few", BoxTable.from_arrays(frames, cars, label="Car", **kitti))
    for run in runs:
        for row, found in (("x2", 10), ("control", 5)):
            directory = run / "objects_few" / row
            write(directory, metrics(50.0) | {"Car": metrics(50.0)["Car"] | {
                "counts": {"moderate": {"gt": 10}}}})  # fmt: skip
            found_cars = BoxTable.from_arrays(
                frames[:found], cars[:found], score=np.linspace(0.9, 0.5, found), label="Car")  # fmt: skip
            write_boxes(directory, found_cars).rename(directory / "predictions.parquet")
    result = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "real_kitti_table.py"), *map(str, runs),
         "--data", str(data), "--sets", "drive", "objects_few"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    lines = result.stdout.splitlines()
    assert any(line.startswith("Only 10 moderate cars count here") and "at 22.5" in line
               for line in lines)  # fmt: skip
    assert "| DALI x2 | 100.0 ± 0.0 / 100.0 ± 0.0 | 100.0 / 100.0 · 100.0 / 100.0 |" in lines
    assert "| control (source, x2 budget, PTSN) | 50.0 ± 0.0 / 50.0 ± 0.0 |" in "\n".join(lines)
    pair = "| DALI x2 − control (source, x2 budget, PTSN) | +50.0 ± 0.0 / +50.0 ± 0.0 |"
    assert any(line.startswith(pair) for line in lines)
    # the drive (one car in the fake truth, but no counts recorded) gets no such section
    assert sum(line.startswith("Only ") for line in lines) == 1


def test_the_recipe_row_and_the_pseudo_labels_of_a_target_with_and_without_the_drive(tmp_path):
    """The shipped recipe (control + tracked ST ×2) is a row of its own, paired with the control;
    pseudo labels are measured on the labelled drive only where the target holds its frames (a
    holdout run's target does not: no empty precision table)."""
    runs, data = make_runs(tmp_path)
    for run, bev in zip(runs, (70.0, 74.0), strict=True):
        write(run / "baselines/source_x2_budget_tst2/eval", metrics(bev))
        tracked = run / "baselines/source_x2_budget/tracked"
        tracked.mkdir(parents=True)
        write_boxes(tracked, BoxTable.from_arrays(["d-0"], [[10, 0, 0, 4, 2, 1.5, 0]], score=[0.9]))
        (tracked / "manifest.json").write_text("{}")

    def table(target_frame: str) -> list[str]:
        shutil.rmtree(data / "target", ignore_errors=True)
        with FrameSetWriter(data / "target", "kitti") as writer:
            writer.append(target_frame, np.zeros((3, 4), np.float32))
        result = subprocess.run(
            [sys.executable, str(ROOT / "bench" / "real_kitti_table.py"), *map(str, runs),
             "--data", str(data), "--sets", "drive"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        return result.stdout.splitlines()

    lines = table("d-0")
    assert any(line.startswith("| control + tracked ST ×2 | 72.0 ± 2.8 | 52.0 ± 2.8 |")
               for line in lines)  # fmt: skip
    # minus the control (40 and 44): +30 on both seeds
    assert any(line.startswith("| control + tracked ST ×2 | +30.0 ± 0.0 |") for line in lines)
    measured = [line for line in lines if "| baselines/source_x2_budget/tracked |" in line]
    assert len(measured) == 2 and all(line.split(" | ")[2:4] == ["1", "1.0"] for line in measured)
    lines = table("other-0")
    assert not any("| baselines/source_x2_budget/tracked |" in line for line in lines)
    assert any(line.startswith("None: the target") for line in lines)
