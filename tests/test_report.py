"""`dali report`: rows come only from artifacts present; the gap-closed figure is computed right."""

from __future__ import annotations

import json

from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.reporting.report import build_report, collect_rows, gap_closed


def write_metrics(path, bev, ap3d, iou=0.7, bucket="all", **extra):
    path.parent.mkdir(parents=True, exist_ok=True)
    block = {
        "iou": iou,
        "recall_positions": 40,
        "bev": {bucket: bev},
        "3d": {bucket: ap3d},
        "counts": {},
    }
    path.write_text(json.dumps({"Car": block, **extra}))


def test_rows_gap_and_missing(tmp_path):
    write_metrics(tmp_path / "iter0/eval/metrics.json", 60.0, 20.0)
    write_metrics(tmp_path / "iter2/eval/metrics.json", 80.0, 50.0, scale=1.02)
    write_metrics(tmp_path / "baselines/oracle/eval/metrics.json", 90.0, 70.0, bucket="moderate")
    rows = {row.name: row for row in collect_rows(tmp_path)}
    assert rows["Source only"].ap["0.7"] == {"bev": 60.0, "3d": 20.0}
    assert rows["x2"].scale == 1.02
    assert rows["Oracle"].ap["0.7"]["3d"] == 70.0
    assert rows["SN"].ap == {}
    # (50 - 20) / (70 - 20)
    assert abs(gap_closed(list(rows.values())) - 0.6) < 1e-12
    text, document = build_report(tmp_path)
    assert "| SN |" not in text and "SN" in text.split("Not run in this RUN")[1]  # left out, named
    assert "closed (AP_3D@0.7): 60%" in text
    assert document["gap_closed_3d_0.7"] == gap_closed(list(rows.values()))


def test_second_iou_block_is_read(tmp_path):
    path = tmp_path / "iter1/eval/metrics.json"
    write_metrics(path, 70.0, 40.0)
    document = json.loads(path.read_text())
    document["Car@0.5"] = {"iou": 0.5, "bev": {"all": 95.0}, "3d": {"all": 90.0}}
    path.write_text(json.dumps(document))
    row = {r.name: r for r in collect_rows(tmp_path)}["PTSN + RC&CF (x1)"]
    assert row.ap == {"0.7": {"bev": 70.0, "3d": 40.0}, "0.5": {"bev": 95.0, "3d": 90.0}}


def test_report_command_writes_files(tmp_path):
    empty = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert empty.exit_code == 1 and "no run artifacts" in empty.output
    assert not (tmp_path / "report").exists()
    write_metrics(tmp_path / "iter0/eval/metrics.json", 60.0, 20.0)
    result = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "report/report.md").read_text().startswith("# dali report")
    assert (
        json.loads((tmp_path / "report/report.json").read_text())["target"][0]["ap"]["0.7"]["bev"]
        == 60.0
    )


def test_distance_bands_table(tmp_path):
    path = tmp_path / "iter1/eval/metrics.json"
    path.parent.mkdir(parents=True)
    block = {
        "iou": 0.7,
        "recall_positions": 40,
        "bev": {"all": 50.0, "0-30": 80.0, "30-50": 40.0, "50-80": 10.0},
        "3d": {"all": 30.0, "0-30": 60.0, "30-50": 20.0, "50-80": None},
        "counts": {"0-30": {"gt": 12}, "30-50": {"gt": 7}, "50-80": {"gt": 3}},
    }
    path.write_text(json.dumps({"Car": block}))
    text, document = build_report(tmp_path)
    assert "0-30 m (12 cars)" in text and "50-80 m (3 cars)" in text
    assert "| PTSN + RC&CF (x1) | 80.00 / 60.00 | 40.00 / 20.00 | 10.00 / — |" in text
    rows = {row["name"]: row for row in document["target"]}
    assert rows["PTSN + RC&CF (x1)"]["bands"]["30-50"] == {"bev": 40.0, "3d": 20.0, "gt": 7}
    assert rows["Source only"]["bands"] == {}


def test_ptsn_no_detections_fallback_is_marked(tmp_path):
    # a sweep that fell back to s = 1 has no E_pred: the row says so instead of failing
    write_metrics(tmp_path / "iter0/eval/metrics.json", 10.0, 1.0)
    ptsn_dir = tmp_path / "iter1/ptsn"
    ptsn_dir.mkdir(parents=True)
    document = {
        "scale": 1.0,
        "E_est": [3.89, 1.62, 1.53],
        "E_pred": [None, None, None],
        "fallback": "no-detections",
        "passes": 10,
    }
    (ptsn_dir / "scale.json").write_text(json.dumps(document))
    text, _ = build_report(tmp_path)
    assert "| iter1 | 1.000 (no detections: s = 1) | 3.89/1.62/1.53 | — | 10 |" in text


def write_kitti(path, moderate_3d, iou=0.7):
    """A metrics_kitti.json beside `path` (KITTI difficulties of the same predictions)."""
    block = {
        "iou": iou,
        "bev": {"easy": 99.0, "moderate": moderate_3d + 10, "hard": 80.0},
        "3d": {"easy": moderate_3d + 5, "moderate": moderate_3d, "hard": moderate_3d - 5},
    }
    path.with_name("metrics_kitti.json").write_text(json.dumps({"Car": block}))


def test_equal_budget_gap_and_kitti_rows(tmp_path):
    write_metrics(tmp_path / "iter2/eval/metrics.json", 80.0, 50.0)
    write_kitti(tmp_path / "iter2/eval/metrics.json", 61.0)
    write_metrics(tmp_path / "baselines/source_x2_budget/eval_ptsn/metrics.json", 82.0, 40.0)
    write_metrics(tmp_path / "baselines/oracle_x2_budget/eval/metrics.json", 90.0, 80.0)
    text, document = build_report(tmp_path)
    assert abs(document["gap_closed_equal_budget_3d_0.7"] - (50 - 40) / (80 - 40)) < 1e-12
    assert abs(document["gap_closed_equal_budget_bev_0.7"] - (80 - 82) / (90 - 82)) < 1e-12
    assert "| x2 | 66.00 | 61.00 | 56.00 | 71.00 |" in text  # KITTI easy / moderate / hard


def test_x1_long_row_gap_and_pairing_with_the_x2_budget_controls(tmp_path):
    """`make x1-long`'s row (x2's frames in one retraining) is read, its equal-budget gap closed
    is computed against the x2-budget control and oracle, and it is paired with that control;
    the control size-corrected at test time (eval_ptsn_sized) is a control row of its own, paired
    apart from the plain one and the base of its own gap closed."""
    from dali_cli.reporting.report import SOURCE_X2_BUDGET_SIZED, X1_LONG

    values = {"s0": (50.0, 56.0, 40.0, 55.0), "s1": (52.0, 55.0, 47.0, 54.5)}
    for seed, (x2, long, control, sized) in values.items():
        run = tmp_path / f"experiment-{seed}"
        write_metrics(run / "iter2/eval/metrics.json", 80.0, x2)
        write_metrics(run / "x1_long/eval/metrics.json", 81.0, long)
        write_metrics(run / "baselines/source_x2_budget/eval_ptsn/metrics.json", 79.0, control)
        write_metrics(run / "baselines/source_x2_budget/eval_ptsn_sized/metrics.json", 79.5, sized)
        write_metrics(run / "baselines/oracle_x2_budget/eval/metrics.json", 90.0, 80.0)
    text, document = build_report(tmp_path / "experiment-s0")
    assert abs(document["gap_closed_equal_budget_3d_0.7"] - (50 - 40) / (80 - 40)) < 1e-12
    assert abs(document["gap_closed_equal_budget_x1_long_3d_0.7"] - (56 - 40) / (80 - 40)) < 1e-12
    assert abs(document["gap_closed_sized_control_3d_0.7"] - (50 - 55) / (80 - 55)) < 1e-12
    assert f"closed by {X1_LONG} (AP_3D@0.7): 40%" in text
    assert f"| {SOURCE_X2_BUDGET_SIZED} |" in text
    result = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    paired = json.loads((tmp_path / "r/report.json").read_text())["paired"]
    by_control = {p["control"]: p["metrics"]["AP_3D@0.7"] for p in paired if p["row"] == X1_LONG}
    assert [p["difference"] for p in by_control.pop(SOURCE_X2_BUDGET_SIZED)["per_run"]] == [
        1.0,
        0.5,
    ]
    [plain] = by_control.values()
    assert [p["difference"] for p in plain["per_run"]] == [16.0, 8.0]


def test_report_aggregates_seeds_into_mean_and_std(tmp_path):
    import statistics

    values = {"s0": (80.0, 50.0, 61.0), "s1": (84.0, 57.5, 66.0), "s2": (79.0, 49.0, 60.5)}
    for seed, (bev, ap3d, moderate) in values.items():
        run = tmp_path / "runs" / f"experiment-{seed}"
        path = run / "iter2/eval/metrics.json"
        write_metrics(path, bev, ap3d, sizes={"pred": [3.9, 1.6 + bev / 1000, 1.5], "gt": None})
        write_kitti(path, moderate)
        write_metrics(run / "iter0/eval/metrics.json", 10.0, 1.0)
    write_metrics(tmp_path / "runs/experiment-s1/baselines/oracle/eval/metrics.json", 90.0, 70.0)
    result = CliRunner().invoke(main, ["report", str(tmp_path / "runs")])
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "runs/report/report.json").read_text())
    assert len(document["runs"]) == 3
    rows = {row["name"]: row["columns"] for row in document["target"]}
    for column, index in (("BEV@0.7", 0), ("3D@0.7", 1), ("KITTI 3D@0.7 moderate", 2)):
        numbers = [v[index] for v in values.values()]
        assert abs(rows["x2"][column]["mean"] - statistics.mean(numbers)) < 1e-9
        assert abs(rows["x2"][column]["std"] - statistics.stdev(numbers)) < 1e-9
        assert rows["x2"][column]["n"] == 3
    widths = [1.6 + v[0] / 1000 for v in values.values()]
    assert abs(rows["x2"]["pred w"]["mean"] - statistics.mean(widths)) < 1e-9
    assert rows["Source only"]["3D@0.7"]["std"] == 0.0
    assert rows["Oracle"]["3D@0.7"]["n"] == 1 and rows["Oracle"]["3D@0.7"]["std"] is None
    assert rows["SN"]["3D@0.7"]["n"] == 0
    expected = (
        f"{statistics.mean([50.0, 57.5, 49.0]):.2f} ± {statistics.stdev([50.0, 57.5, 49.0]):.2f}"
    )
    assert expected in result.output and "| x2 | 3 |" in result.output
    # the same runs named one by one give the same table
    named = [str(tmp_path / "runs" / f"experiment-{seed}") for seed in values]
    again = CliRunner().invoke(main, ["report", *named, "--out", str(tmp_path / "named")])
    assert again.exit_code == 0, again.output
    assert json.loads((tmp_path / "named/report.json").read_text())["target"] == document["target"]


def test_report_pairs_each_dali_row_with_its_control_per_seed(tmp_path):
    """x2 - equal-budget control per seed, its mean ± sample std and the target's verdict; a seed
    without the control enters neither the differences nor n."""
    import statistics

    x2 = {"s0": 70.0, "s1": 66.0, "s2": 75.0, "s3": 60.0}
    control = {"s0": 65.0, "s1": 62.5, "s2": 70.0}  # s3 has no control
    for seed, value in x2.items():
        run = tmp_path / f"experiment-{seed}"
        write_metrics(run / "iter2/eval/metrics.json", 80.0, value)
        if seed in control:
            path = run / "baselines/source_x2_budget/eval_ptsn/metrics.json"
            write_metrics(path, 79.0, control[seed])
    result = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    paired = json.loads((tmp_path / "r/report.json").read_text())["paired"]
    [pair] = [p for p in paired if p["row"] == "x2"]
    ap3d = pair["metrics"]["AP_3D@0.7"]
    differences = [x2[s] - control[s] for s in control]
    assert [p["difference"] for p in ap3d["per_run"]] == differences
    assert ap3d["n"] == 3 and abs(ap3d["mean"] - statistics.mean(differences)) < 1e-9
    assert abs(ap3d["std"] - statistics.stdev(differences)) < 1e-9
    # mean 4.5 >= 3 and > 2 x 0.87: met; BEV +1.0 every seed: below the margin
    assert ap3d["verdict"] == "met"
    assert pair["metrics"]["AP_BEV@0.7"]["verdict"] == "not met"
    assert "| x2 - Source only, x2's budget + PTSN | AP_3D@0.7 | 3 | +5.00 / +3.50 / +5.00" in (
        result.output
    )


def test_paired_verdict_needs_two_seeds_and_a_clear_margin():
    from dali_cli.reporting.paired import verdict

    assert verdict({"n": 1, "mean": 9.0, "std": None}) == "undecided"
    assert verdict({"n": 3, "mean": 3.5, "std": 2.0}) == "not met"  # inside 2 std
    assert verdict({"n": 3, "mean": 2.5, "std": 0.1}) == "not met"  # below the margin
    assert verdict({"n": 3, "mean": 3.0, "std": 1.4}) == "met"


def test_bench_paired_rows_differences_by_seed(tmp_path):
    """bench/paired_rows.py: a row's per-seed AP minus the base row's of the same seed; a seed
    missing the row is left out of the differences."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "paired_rows.py"
    spec = importlib.util.spec_from_file_location("paired_rows", path)
    paired_rows = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(paired_rows)
    base, row = {0: 50.0, 1: 60.0, 2: 55.0}, {0: 54.0, 1: 61.0}
    for seed, value in base.items():
        write_metrics(tmp_path / f"b{seed}/metrics.json", 70.0, value)
    for seed, value in row.items():
        write_metrics(tmp_path / f"r{seed}/metrics.json", 71.0, value)
    text = paired_rows.paired_table(
        ("base", str(tmp_path / "b{seed}")), [("new", str(tmp_path / "r{seed}"))], [0, 1, 2]
    )
    line = next(x for x in text.splitlines() if x.startswith("| new | AP_3D@0.7"))
    assert "| 54.0 / 61.0 |" in line and "| +4.0 / +1.0 | +2.5 ± 2.1 (n = 2) |" in line


def test_far_band_is_aggregated_and_paired(tmp_path):
    """The 50-80 m band (where PPCG should help most) gets its mean ± std over runs and its
    paired difference against the control; a row without bands (KITTI protocol) stays out."""
    from dali_cli.reporting.aggregate import aggregate_runs

    def write_banded(path, all_3d, far_3d):
        path.parent.mkdir(parents=True, exist_ok=True)
        block = {"iou": 0.7, "bev": {"all": 90.0, "50-80": 80.0},
                 "3d": {"all": all_3d, "50-80": far_3d}, "counts": {"50-80": {"gt": 40}}}  # fmt: skip
        path.write_text(json.dumps({"Car": block}))

    far = {"x2": (60.0, 66.0), "control": (55.0, 57.0)}
    runs = []
    for seed in range(2):
        run = tmp_path / f"experiment-s{seed}"
        write_banded(run / "iter2/eval/metrics.json", 80.0, far["x2"][seed])
        write_banded(
            run / "baselines/source_x2_budget/eval_ptsn/metrics.json", 79.0, far["control"][seed]
        )
        write_metrics(run / "iter0/eval/metrics.json", 50.0, 30.0)  # no bands
        runs.append(run)
    text, document = aggregate_runs(runs)
    [x2] = [row for row in document["target"] if row["name"] == "x2"]
    assert x2["columns"]["3D@0.7 50-80 m"]["mean"] == 63.0
    [source] = [row for row in document["target"] if row["name"] == "Source only"]
    assert source["columns"]["3D@0.7 50-80 m"]["n"] == 0
    assert "### By distance (AP_3D@0.7, front region)" in text
    [pair] = [p for p in document["paired"] if p["row"] == "x2"]
    assert [p["difference"] for p in pair["metrics"]["AP_3D@0.7 50-80 m"]["per_run"]] == [5.0, 9.0]


def test_paired_split_takes_out_the_recall_positions_only_one_row_reaches(tmp_path):
    """x2 reaches one recall position more than its control (its maximum recall crossed a k/40
    boundary) and is 0.01 better at 10 shared positions: AP_3D differs by that position's whole
    precision / 40 plus 0.25, the shared-positions figure by 0.25 only."""
    control = [0.0] + [0.9] * 30 + [0.0] * 10  # 41 points as dali eval writes them
    x2 = [0.0] + [0.91] * 10 + [0.9] * 20 + [0.8] + [0.0] * 9
    for seed in (0, 1):
        run = tmp_path / f"experiment-s{seed}"
        for relative, curve in (
            ("iter2/eval", x2),
            ("baselines/source_x2_budget/eval_ptsn", control),
        ):
            path = run / relative / "metrics.json"
            path.parent.mkdir(parents=True)
            block = {"iou": 0.7, "recall_positions": 40, "bev": {"all": 80.0},
                     "3d": {"all": sum(curve[1:]) / 40 * 100}, "counts": {},
                     "curves": {"3d": {"all": {"precision": curve, "recall": [0.0] * 41}}}}  # fmt: skip
            path.write_text(json.dumps({"Car": block}))
    result = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    paired = json.loads((tmp_path / "r/report.json").read_text())["paired"]
    [pair] = [p for p in paired if p["row"] == "x2"]
    ap = pair["metrics"]["AP_3D@0.7"]
    shared = pair["metrics"]["AP_3D@0.7 at the recall positions both reach"]
    assert abs(ap["mean"] - (0.8 / 40 * 100 + 0.25)) < 1e-9
    assert abs(shared["mean"] - 0.25) < 1e-9 and shared["verdict"] == "diagnostic"
    assert [(p["positions"], p["positions_control"]) for p in shared["per_run"]] == [(31, 30)] * 2
    assert "+0.25 (31 vs 30)" in result.output


def test_report_aggregates_the_runs_compare_files(tmp_path):
    """RUN/compare_r400.json (`make compare`): each row's difference to the reference per run,
    with the frames' bootstrap std, and its mean ± std over the runs; a run without the file
    is left out of n."""
    import statistics

    deltas = {"s0": (-0.5, 1.3), "s1": (0.9, 1.2), "s2": None}
    for seed, values in deltas.items():
        run = tmp_path / f"experiment-{seed}"
        write_metrics(run / "iter2/eval/metrics.json", 80.0, 70.0)
        if values is None:
            continue
        rows = {"control": {"3d all": {"ap": 80.0, "std": 1.1}}}
        for name, delta in zip(("x2", "x1-long"), values, strict=True):
            rows[name] = {"3d all": {"ap": 80.0 + delta, "std": 1.0, "delta": delta,
                                     "delta_std": 0.8, "share_not_above_reference": 0.1}}  # fmt: skip
        summary = {"reference": "control", "frames": 200, "samples": 400, "seed": 0, "rows": rows}
        (run / "compare_r400.json").write_text(json.dumps({"bootstrap": summary}))
    result = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    compared = json.loads((tmp_path / "r/report.json").read_text())["compare"]["compare_r400.json"]
    x2, x1_long = compared
    assert x2["row"] == "x2" and x2["n"] == 2 and abs(x2["mean"] - 0.2) < 1e-9
    assert abs(x1_long["std"] - statistics.stdev([1.3, 1.2])) < 1e-9
    assert [p["delta_std"] for p in x2["per_run"]] == [0.8, 0.8]
    assert "| x1-long | 2 | +1.30 ± 0.80 / +1.20 ± 0.80 | +1.25 ± 0.07 |" in result.output
    assert "compare_r40.json" not in json.loads((tmp_path / "r/report.json").read_text())["compare"]
