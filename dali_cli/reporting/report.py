"""The results table of a run: AP per method row, sizes, cross-domain AP and time per stage.

Reads only artifacts a run directory already holds (metrics.json files written by `dali eval`,
manifests, PTSN outputs); rows whose artifacts are missing are shown as "—", never invented.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dali_cli.store.regular_files import read_json_file

# x2's retraining frames in one retraining on iteration 1's PPCG (`make x1-long`)
X1_LONG = "x1 long (x2's frames, one retraining)"
# (row name, metrics.json relative to the run, how the model was evaluated)
ROWS: tuple[tuple[str, str], ...] = (
    ("Source only", "iter0/eval/metrics.json"),
    ("SN", "baselines/sn/eval/metrics.json"),
    ("ROS", "baselines/ros/eval/metrics.json"),
    ("PTSN only", "iter0/eval_ptsn/metrics.json"),
    ("PTSN + RC", "baselines/rc_only/eval_ptsn/metrics.json"),
    ("PTSN + CF", "baselines/cf_only/eval_ptsn/metrics.json"),
    ("PTSN + RC&CF (x1)", "iter1/eval/metrics.json"),
    ("x2", "iter2/eval/metrics.json"),
    ("x2 + ST", "iter2_st/eval/metrics.json"),
    (X1_LONG, "x1_long/eval/metrics.json"),
    ("Oracle", "baselines/oracle/eval/metrics.json"),
)
# the same training frames as DALI's models saw: does the gain come from more training?
SOURCE_X1_BUDGET = "Source only, x1's budget + PTSN"
SOURCE_X2_BUDGET = "Source only, x2's budget + PTSN"
ORACLE_X2_BUDGET = "Oracle, x2's budget"
# the same controls with their predictions resized per dimension at test time, label-free
# (`dali eval --size-correction per-dim`): the cheap alternative at its strongest
SIZED = " + size correction"
SOURCE_X1_BUDGET_SIZED = SOURCE_X1_BUDGET + SIZED
SOURCE_X2_BUDGET_SIZED = SOURCE_X2_BUDGET + SIZED
CONTROL_ROWS: tuple[tuple[str, str], ...] = (
    (SOURCE_X1_BUDGET, "baselines/source_x1_budget/eval_ptsn/metrics.json"),
    (SOURCE_X1_BUDGET_SIZED, "baselines/source_x1_budget/eval_ptsn_sized/metrics.json"),
    (SOURCE_X2_BUDGET, "baselines/source_x2_budget/eval_ptsn/metrics.json"),
    (SOURCE_X2_BUDGET_SIZED, "baselines/source_x2_budget/eval_ptsn_sized/metrics.json"),
    (ORACLE_X2_BUDGET, "baselines/oracle_x2_budget/eval/metrics.json"),
)
KITTI_NAME = "metrics_kitti.json"  # beside each metrics.json: the same predictions, KITTI protocol
DIFFICULTIES = ("easy", "moderate", "hard")
SOURCE_ROWS: tuple[tuple[str, str], ...] = (
    ("Source only", "iter0/eval_source/metrics.json"),
    ("DALI x2", "iter2/eval_source/metrics.json"),
    ("DALI x2, source sized as it was trained (size-norm)", "iter2/eval_source_sized/metrics.json"),
)
STAGE_DIRS = ("model", "ptsn", "pseudo", "rc", "cf")
IOUS = (0.7, 0.5)


@dataclass
class Row:
    name: str
    path: str
    ap: dict  # {"0.7": {"bev": x, "3d": y}, "0.5": {...}} in percent, missing → absent
    sizes: dict  # {"pred": [l, w, h], "gt": [l, w, h]} when recorded
    scale: float | None
    bands: dict  # {"0-30": {"bev", "3d", "gt"}, ...} at IoU 0.7 with the range protocol, else {}
    kitti: dict = field(default_factory=dict)  # {"0.7": {"bev": {"easy", "moderate", "hard"}, ...}}
    # {"0.7": [p_1, ..., p_40]}: AP_3D's interpolated precision at the recall positions k/40 of
    # the summary bucket (0 above the maximum recall), R40 blocks with curves only
    precision_3d: dict = field(default_factory=dict)
    # metrics.json's error breakdown (dali_cli.evaluation.errors); None when the file predates it
    errors: dict | None = None


def _summary_key(block: dict) -> str | None:
    """The headline bucket of one AP block: 'moderate' with KITTI difficulties, else 'all'."""
    for key in ("moderate", "all"):
        if key in block:
            return key
    return next(iter(block), None)


BANDS = ("0-30", "30-50", "50-80")


def read_bands(document: dict) -> dict:
    """AP_BEV / AP_3D and ground-truth count per distance band of the IoU 0.7 block, if any."""
    block = document.get("Car")
    if not isinstance(block, dict):
        return {}
    bands = {}
    for band in BANDS:
        if band in block.get("bev", {}):
            bands[band] = {
                "bev": block["bev"][band],
                "3d": block["3d"].get(band),
                "gt": block.get("counts", {}).get(band, {}).get("gt"),
            }
    return bands


def read_precision_3d(document: dict) -> dict:
    """{iou: (40,) list} AP_3D's interpolated precision at the recall positions 1/40 .. 40/40 of
    each R40 block's summary bucket (its "curves"; {} for R11 or without curves)."""
    precision = {}
    for key, block in document.items():
        if not (key.startswith("Car") and isinstance(block, dict)) or "iou" not in block:
            continue
        if block.get("recall_positions") != 40:
            continue
        curves = block.get("curves", {}).get("3d", {})
        bucket = _summary_key(curves) if isinstance(curves, dict) else None
        values = curves.get(bucket, {}).get("precision") if bucket is not None else None
        if isinstance(values, list) and len(values) == 41:
            precision[f"{float(block['iou']):.1f}"] = [float(v) for v in values[1:]]
    return precision


def read_metrics(path: Path, document: dict | None = None) -> tuple[dict, dict, float | None]:
    """AP per IoU ({iou: {"bev", "3d"}}), sizes and scale from one metrics.json (or its parsed
    `document`)."""
    document = read_json_file(path, "metrics file") if document is None else document
    blocks = [
        value
        for key, value in document.items()
        if key.startswith("Car") and isinstance(value, dict)
    ]
    ap = {}
    for block in blocks:
        iou = block.get("iou")
        if iou is None:
            continue
        entry = {}
        for metric in ("bev", "3d", "aph"):  # APH: metrics.json of dali eval with heading metrics
            values = block.get(metric, {})
            key = _summary_key(values)
            if key is not None and values[key] is not None:
                entry[metric] = float(values[key])
        ap[f"{float(iou):.1f}"] = entry
    sizes = document.get("sizes", {})
    scale = document.get("scale")
    return ap, sizes, scale


def read_kitti(path: Path) -> dict:
    """AP per IoU, metric and KITTI difficulty from a metrics_kitti.json ({} when absent)."""
    if not path.is_file():
        return {}
    kitti = {}
    for key, block in read_json_file(path, "metrics file").items():
        if not (key.startswith("Car") and isinstance(block, dict) and "iou" in block):
            continue
        kitti[f"{float(block['iou']):.1f}"] = {
            metric: {d: block.get(metric, {}).get(d) for d in DIFFICULTIES}
            for metric in ("bev", "3d")
        }
    return kitti


def collect_rows(run: Path, rows=ROWS) -> list[Row]:
    collected = []
    for name, relative in rows:
        path = run / relative
        errors = None
        if path.is_file():
            document = read_json_file(path, "metrics file")
            ap, sizes, scale = read_metrics(path, document)
            bands, precision = read_bands(document), read_precision_3d(document)
            errors = document.get("errors") if isinstance(document.get("errors"), dict) else None
        else:
            ap, sizes, scale, bands, precision = {}, {}, None, {}, {}
        kitti = read_kitti(path.with_name(KITTI_NAME))
        collected.append(Row(name, relative, ap, sizes, scale, bands, kitti, precision, errors))
    return collected


def stage_timings(run: Path) -> dict[str, dict[str, float]]:
    """Wall seconds per stage directory per iteration, from the manifests."""
    timings: dict[str, dict[str, float]] = {}
    for iteration in sorted(run.glob("iter*")):
        for stage in STAGE_DIRS:
            manifest = iteration / stage / "manifest.json"
            if manifest.is_file():
                document = read_json_file(manifest, "manifest")
                seconds = document.get("timings", {}).get("wall_seconds")
                if seconds is not None:
                    timings.setdefault(iteration.name, {})[stage] = float(seconds)
    return timings


def ptsn_scales(run: Path) -> dict[str, dict]:
    """ŝ and the size numbers of every PTSN sweep in the run: each scale.json's record, read
    through the one scale contract (dali_cli.store.scale_file.read_scale); an unreadable one is
    reported and left out."""
    from dali_cli.runtime import console
    from dali_cli.store.artifacts import ArtifactError
    from dali_cli.store.scale_file import read_scale

    scales = {}
    for path in sorted(run.glob("iter*/ptsn/scale.json")):
        try:
            scales[path.parent.parent.name] = read_scale(path).record
        except ArtifactError as error:
            console.warn(f"report: {error}: left out")
    return scales


def _triple(value) -> str:
    if isinstance(value, list | tuple):  # None entries: undefined (a PTSN no-detections fallback)
        return "—" if None in value else "/".join(f"{x:.2f}" for x in value)
    return "—" if value is None else str(value)


def _cell(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def _sizes_cell(sizes: dict, key: str) -> str:
    values = sizes.get(key)
    if not values:
        return "—"
    return "/".join(f"{v:.2f}" for v in values)


def markdown_table(rows: list[Row]) -> str:
    header = (
        "| method | BEV@0.7 | 3D@0.7 | APH@0.7 | BEV@0.5 | 3D@0.5 | scale | pred l/w/h | gt l/w/h |"
    )
    lines = [header, "|" + "---|" * 9]
    for row in rows:
        cells = [row.name]
        for iou in ("0.7", "0.5"):
            entry = row.ap.get(iou, {})
            cells += [_cell(entry.get("bev")), _cell(entry.get("3d"))]
            if iou == "0.7":
                cells.append(_cell(entry.get("aph")))
        cells.append("—" if row.scale is None else f"{row.scale:.3f}")
        cells += [_sizes_cell(row.sizes, "pred"), _sizes_cell(row.sizes, "gt")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def bands_table(rows: list[Row]) -> str | None:
    """AP_BEV / AP_3D @0.7 per distance band for the rows evaluated with range bands."""
    shown = [row for row in rows if row.bands]
    if not shown:
        return None
    counts = next(row.bands for row in shown)
    header = "| method | " + " | ".join(
        f"{band} m ({counts.get(band, {}).get('gt', '?')} cars)" for band in BANDS
    )
    lines = [header + " |", "|---|" + "---|" * len(BANDS)]
    for row in shown:
        cells = []
        for band in BANDS:
            entry = row.bands.get(band, {})
            cells.append(f"{_cell(entry.get('bev'))} / {_cell(entry.get('3d'))}")
        lines.append(f"| {row.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def gap_closed(
    rows: list[Row], metric: str = "3d", iou: str = "0.7", oracle_row: str = "Oracle"
) -> float | None:
    """Share of the source-only → oracle gap closed by the last DALI iteration present."""
    by_name = {row.name: row.ap.get(iou, {}).get(metric) for row in rows}
    source, oracle = by_name.get("Source only"), by_name.get(oracle_row)
    final = by_name.get("x2") if by_name.get("x2") is not None else by_name.get("PTSN + RC&CF (x1)")
    if source is None or oracle is None or final is None or np.isclose(oracle, source):
        return None
    return float((final - source) / (oracle - source))


def gap_closed_equal_budget(
    rows: list[Row], metric: str = "3d", iou: str = "0.7", final: str = "x2",
    control_row: str = SOURCE_X2_BUDGET,
) -> float | None:  # fmt: skip
    """Share of the gap from the equal-budget control (source only with x2's training frames +
    test-time PTSN; `control_row`, e.g. the size-corrected one) to the equal-budget oracle that
    `final` closes (the benchmark's measure of adaptation)."""
    by_name = {row.name: row.ap.get(iou, {}).get(metric) for row in rows}
    control, oracle = by_name.get(control_row), by_name.get(ORACLE_X2_BUDGET)
    value = by_name.get(final)
    if control is None or oracle is None or value is None or np.isclose(oracle, control):
        return None
    return float((value - control) / (oracle - control))


def kitti_table(rows: list[Row]) -> str | None:
    """AP_3D / AP_BEV @0.7 per KITTI difficulty for the rows with a metrics_kitti.json."""
    shown = [row for row in rows if row.kitti.get("0.7")]
    if not shown:
        return None
    lines = [
        "| method | 3D@0.7 easy | 3D@0.7 moderate | 3D@0.7 hard | BEV@0.7 moderate |",
        "|---|---|---|---|---|",
    ]
    for row in shown:
        block = row.kitti["0.7"]
        cells = [_cell(block["3d"].get(d)) for d in DIFFICULTIES]
        lines.append(
            f"| {row.name} | " + " | ".join(cells) + f" | {_cell(block['bev'].get('moderate'))} |"
        )
    return "\n".join(lines)


def build_report(run: Path) -> tuple[str, dict]:
    """Markdown text and a JSON-ready dict describing the run."""
    rows = collect_rows(run)
    source_rows = collect_rows(run, SOURCE_ROWS)
    timings = stage_timings(run)
    scales = ptsn_scales(run)
    controls = collect_rows(run, CONTROL_ROWS)
    parts = [
        f"# dali report: {run}",
        "",
        "## Target validation (Car AP, R40)",
        "",
        markdown_table([row for row in rows if row.ap] or rows),
        *gap_lines(rows),
        *controls_section(rows, controls),
    ]
    by_band = bands_table(rows + controls)
    if by_band is not None:
        parts += ["", "### By distance (AP_BEV / AP_3D @0.7)", "", by_band]
    by_difficulty = kitti_table(rows + controls)
    if by_difficulty is not None:
        parts += ["", "### KITTI difficulties (AP_R40)", "", by_difficulty]
    if any(row.ap for row in source_rows):
        shown = [row for row in source_rows if row.ap]
        parts += ["", "## Source validation (cross-domain check)", "", markdown_table(shown)]
    parts += breakdown_section(rows + controls)
    parts += ptsn_section(scales) + timings_section(timings)
    missing = [row.name for row in rows if not row.ap]
    if missing:
        parts += ["", f"Not run in this RUN (left out of the tables): {', '.join(missing)}."]
    document = {
        "run": str(run),
        "target": [row.__dict__ for row in rows],
        "source": [row.__dict__ for row in source_rows],
        "gap_closed_3d_0.7": gap_closed(rows),
        "gap_closed_bev_0.7": gap_closed(rows, "bev", "0.7"),
        "controls": [row.__dict__ for row in controls],
        "gap_closed_equal_budget_3d_0.7": gap_closed_equal_budget(rows + controls),
        "gap_closed_equal_budget_bev_0.7": gap_closed_equal_budget(rows + controls, "bev"),
        "gap_closed_equal_budget_x1_long_3d_0.7": gap_closed_equal_budget(
            rows + controls, final=X1_LONG
        ),
        "gap_closed_sized_control_3d_0.7": gap_closed_equal_budget(
            rows + controls, control_row=SOURCE_X2_BUDGET_SIZED
        ),
        "gap_closed_sized_control_x1_long_3d_0.7": gap_closed_equal_budget(
            rows + controls, final=X1_LONG, control_row=SOURCE_X2_BUDGET_SIZED
        ),
        "ptsn": scales,
        "timings": timings,
    }
    return "\n".join(parts) + "\n", document


def gap_lines(rows: list) -> list[str]:
    """The share of the source-only-to-oracle gap closed, AP_3D and AP_BEV at IoU 0.7."""
    parts = []
    for metric in ("3d", "bev"):
        share = gap_closed(rows, metric, "0.7")
        if share is not None:
            note = (
                " (above 100%: the oracle saw fewer training frames than x2)" if share > 1 else ""
            )
            parts += [
                "",
                f"Gap from source only to oracle closed (AP_{metric.upper()}@0.7): "
                f"{100 * share:.0f}%{note}",
            ]
    return parts


def controls_section(rows: list, controls: list) -> list[str]:
    """The equal-training-frames controls table and the gaps closed against them (none when
    no control was run)."""
    if not any(row.ap for row in controls):
        return []
    parts = [
        "",
        "### Controls: equal training frames",
        "",
        markdown_table(
            [row for row in rows if row.name in ("PTSN only", "PTSN + RC&CF (x1)", "x2", X1_LONG)]
            + controls
        ),
    ]
    for metric, iou in (("3d", "0.7"), ("bev", "0.7")):
        closed_long = gap_closed(rows + controls, metric, iou, oracle_row=ORACLE_X2_BUDGET)
        if closed_long is not None:
            parts.append(
                f"\nGap closed against the oracle with x2's budget "
                f"(AP_{metric.upper()}@{iou}): {100 * closed_long:.0f}%"
            )
        for final in ("x2", X1_LONG):
            for control, what in ((SOURCE_X2_BUDGET, "source + PTSN"),
                                  (SOURCE_X2_BUDGET_SIZED, "source + PTSN + size correction")):  # fmt: skip
                equal = gap_closed_equal_budget(rows + controls, metric, iou, final, control)
                if equal is not None:
                    parts.append(
                        f"\nGap from {what} to the oracle, both with x2's budget, closed by "
                        f"{final} (AP_{metric.upper()}@{iou}): {100 * equal:.0f}%"
                    )
    return parts


def _signed(value: float) -> str:
    """`value` with its sign and 2 decimals; a value that rounds to 0 is +0.00, never -0.00."""
    return f"{round(value, 2) + 0.0:+.2f}"


NO_BREAKDOWN = "no breakdown: rerun dali eval --force"
BREAKDOWN_IOU = "0.7"  # the threshold whose losses the report names


def breakdown_section(rows: list[Row]) -> list[str]:
    """Box errors of the matches and the false positives with the AP each fix gains, for the
    rows whose metrics.json holds the error breakdown; rows evaluated before it existed are
    named with NO_BREAKDOWN."""
    from dali_cli.evaluation.errors import FIXES, KINDS, QUANTITIES, largest_loss

    shown = [row for row in rows if row.errors]
    stale = [row.name for row in rows if row.ap and not row.errors]
    if not shown:
        return (
            _section("## Error breakdown", f"{NO_BREAKDOWN} ({', '.join(stale)})") if stale else []
        )
    first = shown[0].errors
    matches = first["true_positives"]
    parts = _section(
        "## Error breakdown",
        f"Box errors of the matches ({matches['overlap'].upper()} IoU > {matches['iou']:g}, "
        f"{first['protocol']} {first['group']}, prediction − truth; radial > 0: too far from the "
        "sensor; yaw_axis: the heading axis, modulo 180°; turned > 90°: boxes facing backwards): "
        "median [16 %, 84 %]",
        "",
        "| method | matches | " + " | ".join(QUANTITIES) + " |",
        "|---|---|" + "---|" * len(QUANTITIES),
    )
    for row in shown:
        block = row.errors["true_positives"]["all"]
        cells = [
            "—" if block.get(q, {}).get("median") is None
            else f"{_signed(block[q]['median'])} [{_signed(block[q]['p16'])}, "
                 f"{_signed(block[q]['p84'])}]"
            for q in QUANTITIES
        ]  # fmt: skip
        count = f"{block['count']} ({block['flipped']} turned > 90°)"
        parts.append(f"| {row.name} | {count} | " + " | ".join(cells) + " |")
    parts += [
        "",
        f"False positives at IoU {BREAKDOWN_IOU} (3D; every prediction kept) and AP_3D with each "
        "kind fixed alone (TIDE's dAP: mislocalized boxes snapped to their car, duplicates or "
        "background boxes removed, missed cars removed from the truth):",
        "",
        "| method | AP_3D | TP | FP | " + " | ".join(KINDS) + " | missed | "
        + " | ".join(f"+{name}" for name in FIXES) + " | largest loss |",
        "|---|---|---|---|" + "---|" * (len(KINDS) + 2 + len(FIXES)),
    ]  # fmt: skip
    for row in shown:
        block = row.errors["false_positives"].get(BREAKDOWN_IOU, {}).get("3d")
        if block is None:
            continue
        counts = block["counts"][row.errors["group"]]
        gains = [
            "—" if block["ap_fixed"][name] is None or block["ap"] is None
            else _signed(block["ap_fixed"][name] - block["ap"])
            for name in FIXES
        ]  # fmt: skip
        loss = largest_loss(block)
        cells = [_cell(block["ap"]), counts["tp"], counts["fp"], *(counts[k] for k in KINDS),
                 counts["missed"], *gains,
                 "—" if loss is None else f"{loss[0]} ({_signed(loss[1])})"]  # fmt: skip
        parts.append(f"| {row.name} | " + " | ".join(map(str, cells)) + " |")
    if stale:
        parts += ["", f"{NO_BREAKDOWN} ({', '.join(stale)})"]
    return parts


def _section(title: str, *lines: str) -> list[str]:
    """A markdown section: a blank line, the title, a blank line, then `lines`."""
    return ["", title, "", *lines]


def ptsn_section(scales: dict) -> list[str]:
    """The PTSN table: ŝ, E_est and E_pred(ŝ) of each sweep (none without sweeps)."""
    if not scales:
        return []
    parts = _section(
        "## PTSN", "| sweep | ŝ | E_est l/w/h | E_pred(ŝ) l/w/h | passes |", "|---|---|---|---|---|"
    )
    for name, info in scales.items():
        est = info.get("expected_lwh") or info.get("E_est")
        pred = info.get("pred_lwh_at_scale") or info.get("E_pred")
        fallback = " (no detections: s = 1)" if info.get("fallback") == "no-detections" else ""
        parts.append(
            f"| {name} | {info.get('scale', float('nan')):.3f}{fallback} | {_triple(est)} | "
            f"{_triple(pred)} | "
            f"{info.get('passes', '—')} |"
        )
    return parts


def timings_section(timings: dict) -> list[str]:
    """Seconds per stage and iteration (none without timings)."""
    if not timings:
        return []
    parts = _section(
        "## Time per stage (s)",
        "| iteration | " + " | ".join(STAGE_DIRS) + " |",
        "|---|" + "---|" * len(STAGE_DIRS),
    )
    for iteration, stages in timings.items():
        parts.append(
            f"| {iteration} | " + " | ".join(_cell(stages.get(s)) for s in STAGE_DIRS) + " |"
        )
    return parts
