"""Stage compare: AP of several prediction tables on the same frames, with a paired bootstrap
over the frames (dali_cli.evaluation.bootstrap): how far each row's AP, and its difference to the first
row, would move with another draw of evaluation frames. Reads tables and labels only; writes
one JSON file (atomically) or nothing. Not an artifact stage: the file is always recomputed."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from dali_cli.evaluation.evaluate import Protocol
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.artifacts import BoxTable

MARKER = "bootstrap"  # the block that marks a `dali compare` file (output_paths)


def parse_rows(specs: tuple[str, ...]) -> dict[str, Path]:
    """NAME=PATH (or PATH, named by itself) per --pred, in order; at least two, names unique.
    The name ends at the first "=" (a path may hold one, a name may not)."""
    rows: dict[str, Path] = {}
    for spec in specs:
        name, _, path = spec.partition("=") if "=" in spec else (spec, "", spec)
        if not name or not path:
            raise ParameterError("preds", f"'{spec}' is not NAME=PATH")
        if name in rows:
            raise ParameterError("preds", f"row name '{name}' given twice")
        if not Path(path).exists():
            raise ParameterError("preds", f"{path}: not found (row '{name}')" + _name_hint(spec))
        rows[name] = Path(path)
    if len(rows) < 2:
        raise ParameterError("preds", "give at least two --pred rows to compare")
    return rows


def _name_hint(spec: str) -> str:
    """When `spec` names an existing path after a later "=", the row's name held an "=": say so."""
    cuts = [i for i, char in enumerate(spec) if char == "="][1:]
    for cut in cuts:
        name, path = spec[:cut], spec[cut + 1 :]
        if Path(path).exists():
            return (
                f"; '{path}' exists: a row name cannot contain '=' (the name ends at the first"
                f" one), rename the row '{name}'"
            )
    return ""


def ap_metric(gt_path, settings: Protocol):
    """metric(pred, gt) -> {"3d <band>": AP, "bev <band>": AP} of `dali_cli.evaluation.evaluate.evaluate`
    with `settings`; an EvaluationError becomes a StageError naming the truth file."""
    from dali_cli.evaluation.evaluate import EvaluationError, evaluate

    def metric(pred: BoxTable, gt: BoxTable) -> dict[str, float | None]:
        try:
            block = evaluate(pred, gt, **asdict(settings))[settings.class_name]
        except EvaluationError as error:
            raise StageError(f"cannot evaluate against {gt_path}: {error}") from None
        kinds = ("3d", "bev", "aph")  # APH: AP_BEV with each true positive weighted by heading
        return {f"{kind} {band}": ap for kind in kinds for band, ap in block[kind].items()}

    return metric


def run_compare(
    *,
    preds: tuple[str, ...],
    gt_path: str | Path,
    settings: Protocol = Protocol(),
    samples: int = 1000,
    seed: int = 0,
    out: str | Path | None = None,
    progress: bool = True,
) -> dict:
    """The comparison document ({"bootstrap": BootstrapResult.summary(), "settings", "inputs"})
    of the --pred rows against `gt_path`; written to `out` (a .json file) when given. Checks the
    rows, the IoU and the output path before any evaluation."""
    from dali_cli.evaluation.bootstrap import paired_bootstrap
    from dali_cli.evaluation.evaluate import check_ious
    from dali_cli.importers.kitti_label import read_box_source

    rows = parse_rows(tuple(preds))
    check_ious((settings.iou,))
    if samples < 2:
        raise ParameterError("samples", f"must be at least 2, got {samples}")
    inputs = {"gt": gt_path, **{f"pred {name}": path for name, path in rows.items()}}
    target = None
    if out is not None:
        from dali_cli.store.output_paths import check_metrics_output

        if Path(out).suffix != ".json":
            raise ParameterError("out", f"{out}: give a .json file to write")
        target = check_metrics_output(out, inputs, marker=MARKER)
    tables = {name: read_box_source(path, "pred")[0] for name, path in rows.items()}
    gt, _ = read_box_source(gt_path, "gt")
    metric = ap_metric(gt_path, settings)
    bar = _progress_bar(progress, samples)
    try:
        result = paired_bootstrap(tables, gt, metric, samples=samples, seed=seed,
                                  progress=bar.update)  # fmt: skip
    finally:
        bar.close()
    document = {
        MARKER: result.summary(),
        "settings": asdict(settings),
        "inputs": {"gt": str(gt_path), "preds": {name: str(p) for name, p in rows.items()}},
    }
    if target is not None:
        from dali_cli.store.atomic_file import write_text_atomically

        write_text_atomically(target, json.dumps(document, indent=2) + "\n")
    return document


def _progress_bar(enabled: bool, total: int):
    import sys

    from tqdm import tqdm

    return tqdm(total=total, desc="bootstrap draws", unit="draw", file=sys.stderr,
                disable=not enabled, leave=False)  # fmt: skip


def format_comparison(document: dict, kinds: tuple[str, ...] = ("3d", "bev", "aph")) -> str:
    """The comparison as a text table: per metric, each row's AP ± its bootstrap std and, after
    the reference, Δ ± std [95 % interval] and the share of draws with Δ <= 0."""
    summary = document[MARKER]
    names = list(summary["rows"])
    metrics = [m for m in summary["rows"][names[0]] if m.split(" ")[0] in kinds]
    lines = [
        f"paired bootstrap: {summary['samples']} draws of {summary['frames']} frames "
        f"(seed {summary['seed']}); reference: {summary['reference']}"
    ]

    def number(value, width=6):
        return f"{value:{width}.2f}" if value is not None else " " * (width - 1) + "-"

    for metric in metrics:
        lines.append(f"{metric}:")
        for name in names:
            entry = summary["rows"][name][metric]
            line = f"  {name:<28} {number(entry['ap'])} ± {number(entry['std'], 4)}"
            if "delta" in entry:
                low, high = entry["delta_interval_95"]
                share = entry["share_not_above_reference"]
                line += f"   Δ {number(entry['delta'])} ± {number(entry['delta_std'], 4)}"
                line += f"  [{number(low)}, {number(high)}]  P(Δ<=0) "
                line += f"{share:.3f}" if share is not None else "-"
            lines.append(line)
    return "\n".join(lines)
