"""Shared by the table scripts (short_pretrain_table.py, budget_table.py): one
row's figures from its metrics files, as markdown cells."""

import json
from pathlib import Path


def metrics(path: Path) -> dict | None:
    """A metrics.json, None when the row has not finished."""
    return json.loads(path.read_text()) if path.is_file() else None


def row_cells(eval_dir: Path, val800_dir: Path) -> list[str] | None:
    """Cells AP_3D@0.7 on the 200 frames (eval_dir/metrics.json), KITTI moderate AP_3D@0.7
    (eval_dir/metrics_kitti.json), AP_3D@0.7, AP_BEV@0.7 and AP_3D@0.7 at 50-80 m on the 800
    frames (val800_dir/metrics.json) and the mean predicted l, w, h (m) there; a figure whose
    file is missing is an empty cell; None when neither the 200 nor the 800 has finished."""
    small_metrics = metrics(eval_dir / "metrics.json")
    big_metrics = metrics(val800_dir / "metrics.json")
    if small_metrics is None and big_metrics is None:
        return None
    small = small_metrics["Car"] if small_metrics else None
    big = big_metrics["Car"] if big_metrics else None
    kitti_metrics = metrics(eval_dir / "metrics_kitti.json")
    kitti = kitti_metrics["Car"]["3d"]["moderate"] if kitti_metrics else None
    sizes = big_metrics["sizes"]["pred"] if big_metrics else None
    return [
        f"{small['3d']['all']:.2f}" if small else "",
        f"{kitti:.2f}" if kitti is not None else "",
        f"{big['3d']['all']:.2f}" if big else "",
        f"{big['bev']['all']:.2f}" if big else "",
        f"{big['3d']['50-80']:.2f}" if big else "",
        ", ".join(f"{v:.2f}" for v in sizes) if sizes else "",
    ]
