"""Diagnostic (issue 18): how much AP@0.7 the per-dimension size bias left after PTSN costs at
*test time*, for any evaluated model of a run, without labels in the correction.

For an eval directory E (metrics.json + predictions.parquet, made with `--scale-from P`), the
predictions are resized per dimension by factor_d = E_est_d / E_pred_d(ŝ), both read from P's
scale.json (the sweep's own label-free numbers on the unlabeled target training frames), bottom
face kept (dali_cli.size_correction.resize_keeping_bottom), and evaluated again with the same
protocol flags (`dali eval --pred`). Target labels are used only by the evaluation itself.

    .venv/bin/python bench/test_time_size_correction.py RUN/iter2/eval RUN/iter3/ptsn \
        --gt RUN/data/target_val

Prints AP_BEV / AP_3D @0.7 before and after, and the factors; writes nothing outside a temp dir,
unless `--out DIR` keeps the corrected predictions as an eval directory of their own
(DIR/predictions.parquet, metrics.json, metrics_kitti.json with the Makefile's KITTI flags,
size_correction.json), which `dali report`-style tools (bench/paired_rows.py) read as a row.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dali_cli.size_correction import resize_keeping_bottom

EVAL_FLAGS = ["--protocol", "range", "--front-only", "--iou", "0.7", "--iou", "0.5"]
KITTI_FLAGS = ["--protocol", "kitti", "--iou", "0.7", "--iou", "0.5", "--size-score-min", "0.3"]


def corrected_predictions(predictions: Path, scale_json: Path, out: Path) -> np.ndarray:
    scale = json.loads(scale_json.read_text())
    factors = np.asarray(scale["E_est"], float) / np.asarray(scale["E_pred_at_scale"], float)
    table = pq.read_table(predictions)
    boxes = np.stack([table.column(c).to_numpy() for c in ("x", "y", "z", "l", "w", "h", "yaw")], 1)
    resized = resize_keeping_bottom(boxes, factors)
    for i, name in enumerate(("x", "y", "z", "l", "w", "h", "yaw")):
        table = table.set_column(table.schema.get_field_index(name), name, pa.array(resized[:, i]))
    pq.write_table(table, out)
    return factors


def run_eval(dali: str, pred: Path, gt: Path, out: Path, flags: list[str]) -> None:
    command = [dali, "eval", "--pred", str(pred), "--gt", str(gt), *flags, "--out", str(out)]
    subprocess.run(command, check=True, capture_output=True)


def evaluate(dali: str, pred: Path, gt: Path, out: Path) -> dict:
    run_eval(dali, pred, gt, out, EVAL_FLAGS)
    metrics = json.loads(out.read_text())["Car"]
    return {"bev": metrics["bev"]["all"], "3d": metrics["3d"]["all"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("eval_dir", type=Path)
    parser.add_argument("ptsn_dir", type=Path)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--dali", default=str(Path(sys.executable).with_name("dali")))
    parser.add_argument("--out", type=Path, help="keep the corrected predictions and metrics here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        before = evaluate(args.dali, args.eval_dir / "predictions.parquet", args.gt, tmp / "a.json")
        factors = corrected_predictions(
            args.eval_dir / "predictions.parquet", args.ptsn_dir / "scale.json", tmp / "p.parquet"
        )
        after = evaluate(args.dali, tmp / "p.parquet", args.gt, tmp / "b.json")
        record = {"eval": str(args.eval_dir), "factors_lwh": factors.round(4).tolist(),
                  "before": before, "after": after}  # fmt: skip
        if args.out is not None:  # built beside, then renamed: never a half-written row
            work = tmp / "out"
            work.mkdir()
            (tmp / "p.parquet").rename(work / "predictions.parquet")
            (tmp / "b.json").rename(work / "metrics.json")
            run_eval(args.dali, work / "predictions.parquet", args.gt, work / "metrics_kitti.json",
                     KITTI_FLAGS)  # fmt: skip
            (work / "size_correction.json").write_text(json.dumps(record, indent=2) + "\n")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(args.out, ignore_errors=True)
            shutil.move(str(work), str(args.out))
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
