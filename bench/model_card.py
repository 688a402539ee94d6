"""A shipped model's directory (models/<name>/): the trained model's weights and config, its
test-time scale, card.json and README.md (the model card) saying what the model is, what made
it (every stage that led to it, from the manifests: command parameters, frames seen, wall time,
machine) and how well it does (its own evaluations; the recipe's mean ± std over seeds).

    .venv/bin/python bench/model_card.py --model RUN/<row>/model [--scale-from RUN/<ptsn>] \\
        --name kitti-hdl64e --title "..." --eval SET=EVAL_DIR ... \\
        [--recipe SET=EVAL_DIR,EVAL_DIR,...] [--fixture-eval EVAL_DIR] --out models/kitti-hdl64e

--eval: this model's evaluations (a `dali eval` output: metrics.json), one per set; --recipe: the
same recipe's evaluations over several seeds (this model's among them), per set; --fixture-eval:
an evaluation on the repository's own test frames, which the tests rerun (tests/test_models.py).
The card is written next to a copy of model.pt and model.json (and scale.json): the directory
is staged beside --out and renamed into place; an --out this script did not write (no card.json)
is refused, never replaced.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import sys
from pathlib import Path

import numpy as np
from real_kitti_table import r400_at_07, read_json, spread  # the benchmark table's

from dali_cli.evaluation.evaluate import ap_ceiling
from dali_cli.store.artifacts import read_boxes

CARD_NAME = "card.json"
EXACT = ("AP_BEV@0.7 R400", "AP_3D@0.7 R400")  # a small set's AP@0.7 under R400 (exact_recall)
COPIED = ("model.pt", "model.json")
# (metrics.json block, overlap kind, header)
# APH@0.7: AP_BEV with each true positive weighted by its heading (docs/evaluation.md)
METRICS = (("Car", "bev", "AP_BEV@0.7"), ("Car", "3d", "AP_3D@0.7"), ("Car", "aph", "APH@0.7"),
           ("Car@0.5", "bev", "AP_BEV@0.5"), ("Car@0.5", "3d", "AP_3D@0.5"))  # fmt: skip
COUNTS_SHOWN = (
    "frames",
    "frames_without_labels",
    "frames_seen",
    "steps",
    "boxes",
    "pseudo_boxes",
    "labels",
)
PARAMS_SHOWN = ("frames", "epochs", "minutes", "lr", "scale", "score_min", "seed", "cars",
                "sensor", "expected_size", "crop_fov", "track_score_min")  # fmt: skip


def headline(metrics: dict, block: str, kind: str) -> float | None:
    """KITTI moderate AP (or the range protocol's all-range AP) of one block, in %."""
    entry = metrics.get(block, {}).get(kind, {})
    value = entry.get("moderate", entry.get("all"))
    return None if value is None else round(float(value), 2)


def evaluation(directory: Path) -> dict:
    """The AP figures, frames and protocol of one `dali eval` output; where too few cars count
    for R40 to reach 100 (`ap_ceiling`), that ceiling and AP@0.7 under R400 too, recomputed
    from its saved predictions against the data it evaluated (its manifest's input)."""
    metrics = read_json(directory / "metrics.json")
    if metrics is None:
        raise SystemExit(
            f"model_card: {directory}/metrics.json not found (is it a dali eval output?)"
        )
    car = metrics.get("Car", {})
    counts = car.get("counts", {})
    counted = counts.get("moderate", counts.get("all", {})).get("gt")
    ceiling = ap_ceiling(counted, car.get("recall_positions", 40)) if counted else None
    entry = {
        "protocol": car.get("protocol"),
        "frames": car.get("frames"),
        "scale": metrics.get("scale"),
        "counted": counted,
        "ceiling": ceiling,
        **{header: headline(metrics, block, kind) for block, kind, header in METRICS},
    }
    entry.update(box_quality(metrics))
    if ceiling is not None and ceiling < 100.0:
        entry.update(exact_recall(directory, car["protocol"]))
    return entry


QUALITY = ("backwards", "|dl| m", "l spread")  # box_quality's keys, as the card shows them


def box_quality(metrics: dict) -> dict:
    """How the true positives face and fit (the headline group, moderate or all): how many face
    backwards (of those matched at IoU 0.7, BEV), their median |length error| (m) and their
    lengths' 5-95 % range over the labels' (the error breakdown's, BEV IoU > 0.5). Empty for an
    evaluation written before these existed."""
    car = metrics.get("Car", {})
    heading = car.get("heading", {})
    heading = heading.get("moderate", heading.get("all"))
    tps = (metrics.get("errors") or {}).get("true_positives", {})
    length = tps.get("all", {}).get("l_m", {})
    spread = tps.get("sizes", {}).get("l_m", {})
    quality = {}
    if heading and heading.get("tp"):
        quality["backwards"] = f"{heading['backwards']}/{heading['tp']}"
    if length.get("median_abs") is not None:
        quality["|dl| m"] = round(float(length["median_abs"]), 3)
    if spread.get("spread_ratio") is not None:
        quality["l spread"] = round(float(spread["spread_ratio"]), 2)
    return quality


def exact_recall(directory: Path, protocol: str) -> dict:
    """AP_BEV / AP_3D@0.7 under R400 of an evaluation's saved predictions (moderate, or all)."""
    manifest = read_json(directory / "manifest.json") or {}
    data = [record["path"] for record in manifest.get("inputs", {}).get("data", [])]
    predictions = directory / "predictions.parquet"
    if len(data) != 1 or not predictions.is_file():
        raise SystemExit(f"model_card: {directory} has no predictions.parquet and data input")
    values = r400_at_07(read_boxes(predictions), read_boxes(data[0]), protocol)
    return {key: round(float(v), 2) for key, v in zip(EXACT, values, strict=True)}


def prediction_digest(directory: Path) -> dict:
    """The boxes an evaluation scored: their count and the sum of their scores (a rerun that
    predicts anything else shows in these, even where AP does not move)."""
    import pyarrow.parquet as pq

    scores = pq.read_table(directory / "predictions.parquet", columns=["score"]).column(0)
    return {"boxes": len(scores), "score_sum": round(float(np.sum(scores.to_numpy())), 4)}


def provenance(model_dir: Path) -> list[dict]:
    """Every stage that led to `model_dir`, inputs first (depth-first over the manifests'
    inputs; each directory once): stage, directory name, shown params, counts, wall seconds,
    machine. An input that is a shipped model (no manifest, a card.json) brings its card's own
    provenance, so a model adapted from a shipped one shows the whole chain."""
    seen, order = set(), []

    def visit(directory: Path) -> None:
        if directory in seen:
            return
        seen.add(directory)
        manifest = read_json(directory / "manifest.json")
        if manifest is None:
            order.extend((read_json(directory / "card.json") or {}).get("provenance", []))
            return
        for records in manifest.get("inputs", {}).values():
            for record in records if isinstance(records, list) else [records]:
                path = record.get("path") if isinstance(record, dict) else record
                if path:
                    visit(Path(path))
        runtime = manifest.get("runtime") or {}
        order.append({
            "stage": manifest.get("stage"),
            "directory": "/".join(directory.parts[-3:]),
            "params": {k: v for k, v in manifest.get("params", {}).items() if k in PARAMS_SHOWN},
            "counts": {k: v for k, v in ((manifest.get("outputs") or {}).get("counts") or {}).items()
                       if k in COUNTS_SHOWN},
            "wall_seconds": (manifest.get("timings") or {}).get("wall_seconds"),
            "machine": " · ".join(str(runtime[k]) for k in ("cpu_model", "device", "threads")
                                  if k in runtime),
            "created": manifest.get("created"),
        })  # fmt: skip

    visit(model_dir)
    return order


def named_dirs(pairs: list[str], option: str) -> dict[str, list[Path]]:
    result = {}
    for pair in pairs:
        name, _, dirs = pair.partition("=")
        if not name or not dirs:
            raise SystemExit(f"model_card: {option} takes SET=DIR[,DIR...], got {pair!r}")
        result[name] = [Path(d) for d in dirs.split(",")]
    return result


def card_text(card: dict) -> str:
    """README.md of the model directory."""
    lines = [f"# {card['name']}: {card['title']}", "", card["summary"], ""]
    lines += ["## Use", "", "    " + card["use"], ""]
    headers = [header for _, _, header in METRICS]
    lines += ["## Accuracy", "",
              "Car, R40; KITTI moderate where the set has KITTI's columns (else all ranges), %.",
              "", "| set | frames | " + " | ".join(headers) + " |",
              "|---|---|" + "---|" * len(headers)]  # fmt: skip
    for name, entry in card["evaluations"].items():
        cells = ["-" if entry.get(h) is None else f"{entry[h]:.1f}" for h in headers]
        lines.append(f"| {name} | {entry['frames']} | " + " | ".join(cells) + " |")
    quality = [(name, entry) for name, entry in card["evaluations"].items()
               if any(key in entry for key in QUALITY)]  # fmt: skip
    if quality:
        lines += ["", "How the found cars' boxes face and fit: true positives facing backwards (at "
                  "IoU 0.7, BEV), their median |length error| (m) and their lengths' 5-95 % range "
                  "over their labels' (1: as varied as the cars; 0: one length for every car).",
                  "", "| set | " + " | ".join(QUALITY) + " |", "|---|" + "---|" * len(QUALITY)]  # fmt: skip
        for name, entry in quality:
            lines.append(
                f"| {name} | " + " | ".join(str(entry.get(k, "-")) for k in QUALITY) + " |"
            )
    if card["recipe"]:
        whose = card.get("recipe_note") or "this model is one of them"
        lines += ["", f"The recipe over {card['recipe_seeds']} seeds (mean ± std; {whose}):", "",
                  "| set | seeds | " + " | ".join(headers) + " |",
                  "|---|---|" + "---|" * len(headers)]  # fmt: skip
        for name, entries in card["recipe"].items():
            cells = [spread([e[h] for e in entries if e.get(h) is not None]) for h in headers]
            lines.append(f"| {name} | {len(entries)} | " + " | ".join(cells) + " |")
    lines += ceiling_lines(card)
    if card["fixture"]:
        entry = card["fixture"]
        lines += ["", f"On the repository's test frame (tests/fixtures/real/kitti, {entry['frames']} "
                  f"frame): AP_BEV / AP_3D@0.7 {entry['AP_BEV@0.7']} / {entry['AP_3D@0.7']}; "
                  "tests/test_models.py reruns it."]  # fmt: skip
    lines += gate_lines(card.get("against_replaced"))
    total = sum(step["wall_seconds"] or 0 for step in card["provenance"])
    lines += ["", "## How it was made", "",
              "Every stage that led to the weights, inputs first (from the manifests; `make models` "
              f"reruns them): {total / 3600:.1f} h of stage wall time on the machines named.", "",
              "| stage | output | parameters | counts | wall s | machine |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for step in card["provenance"]:
        params = ", ".join(f"{k}={v}" for k, v in step["params"].items())
        counts = ", ".join(f"{k}={v}" for k, v in step["counts"].items())
        wall = "-" if step["wall_seconds"] is None else f"{step['wall_seconds']:.0f}"
        lines.append(f"| {step['stage']} | {step['directory']} | {params} | {counts} | {wall} | "
                     f"{step['machine']} |")  # fmt: skip
    lines += ["", "## Limits", "", *[f"- {limit}" for limit in card["limits"]], ""]
    return "\n".join(lines)


def gate_lines(gate: dict | None) -> list[str]:
    """The comparison with the model this one replaced (bench/model_gate.py), paired over each
    set's frames: AP_3D@0.7 moderate of both, the difference and its 95 % interval."""
    if not gate:
        return []
    lines = ["", "## Against the model it replaces", ""]
    lines += [gate["note"], ""] if gate.get("note") else []
    lines += [f"{gate['metric']}, paired over each set's frames (bootstrap, 95 %); "
              f"{'refused' if gate['refused'] else 'passed'}: a rebuilt model is refused where "
              "the interval lies wholly below zero.", "",
              "| set | frames | replaced | this model | difference [95 %] |", "|---|---|---|---|---|"]  # fmt: skip
    for name, line in gate["sets"].items():
        cell = line["3d moderate"]
        low, high = cell["delta_interval_95"]
        lines.append(f"| {name} | {line['frames']} | {cell['shipped']:.1f} | {cell['candidate']:.1f}"
                     f" | {cell['delta']:+.1f} [{low:+.1f}, {high:+.1f}] |")  # fmt: skip
    return lines


def ceiling_lines(card: dict) -> list[str]:
    """A paragraph per set where too few cars count for R40 to reach 100: its ceiling and the
    model's (and the recipe's) AP@0.7 under R400."""
    lines = []
    for name, entry in card["evaluations"].items():
        if entry.get("ceiling") is None or entry["ceiling"] >= 100.0:
            continue
        text = (f"On {name} only {entry['counted']} moderate cars count, so KITTI's R40 caps AP "
                f"at {entry['ceiling']:.1f} (what a perfect detector scores there). Under R400 "
                f"(the precision at exact recalls, `dali eval --recall-positions 400`) this "
                f"model's AP_BEV / AP_3D@0.7 is {entry[EXACT[0]]:.1f} / {entry[EXACT[1]]:.1f}")  # fmt: skip
        entries = [e for e in card["recipe"].get(name, []) if EXACT[0] in e]
        if len(entries) > 1:
            cells = [spread([e[h] for e in entries]) for h in EXACT]
            text += f", the recipe's {cells[0]} / {cells[1]} over {len(entries)} seeds"
        lines += ["", text + "."]
    return lines


def publish(staging: Path, out: Path) -> None:
    """Rename `staging` into `out`; an `out` without card.json is someone else's: refused."""
    if out.exists():
        if not (out / CARD_NAME).is_file():
            shutil.rmtree(staging)
            raise SystemExit(f"model_card: {out} exists and was not written by model_card "
                             f"(no {CARD_NAME}): not replaced")  # fmt: skip
        old = out.with_name(f".{out.name}.old-{os.getpid()}-{secrets.token_hex(8)}")
        out.rename(old)
        staging.rename(out)
        shutil.rmtree(old)
    else:
        staging.rename(out)


def use_lines(model: Path, has_scale: bool, config: dict) -> str:
    """The card's "Use": detect on one's own scans (at the model's scale.json, in the front view
    it was adapted on, model.json's config front_deg: detect's default) and eval."""
    front = config.get("front_deg")
    seen = [*(["at the model's scale.json"] if has_scale else []),
            *([f"in the front {front:g}° it was adapted on; --front-deg 360: every point"]
              if front else [])]  # fmt: skip
    return (f"dali detect SCANS --model {model} --out OUT    # your own scans: .bin, .pcd, .npy, "
            "a KITTI drive" + (f" ({', '.join(seen)})" if seen else "") + "\n    "
            f"dali eval --model {model} --data DATA" + (
                f" --scale-from {model}" if has_scale else "") + " --out OUT"
            "    # AP on a labelled frame set")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--scale-from", type=Path, help="the ptsn-sweep whose scale.json it uses")
    parser.add_argument("--name", required=True)
    parser.add_argument("--title", required=True)
    parser.add_argument("--summary", required=True, help="what the model is, in a paragraph")
    parser.add_argument("--limit", action="append", default=[], help="a limit (repeatable)")
    parser.add_argument("--eval", action="append", default=[], metavar="SET=DIR")
    parser.add_argument("--recipe", action="append", default=[], metavar="SET=DIR,DIR,...")
    parser.add_argument("--recipe-note", help="how this model relates to the recipe's seeds "
                        "(default: it is one of them)")  # fmt: skip
    parser.add_argument("--fixture-eval", type=Path)
    parser.add_argument("--gate", type=Path, help="bench/model_gate.py's verdict against the "
                        "model this one replaces")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    for name in COPIED:
        if not (args.model / name).is_file():
            raise SystemExit(f"model_card: {args.model / name} not found (is it a dali model?)")
    scale_file = args.scale_from / "scale.json" if args.scale_from else None
    if scale_file is not None and not scale_file.is_file():
        raise SystemExit(f"model_card: {scale_file} not found (is it a ptsn-sweep output?)")
    evaluations = {
        name: evaluation(dirs[0]) for name, dirs in named_dirs(args.eval, "--eval").items()
    }
    recipe = {name: [evaluation(d) for d in dirs if (d / "metrics.json").is_file()]
              for name, dirs in named_dirs(args.recipe, "--recipe").items()}  # fmt: skip
    scale = read_json(scale_file)["scale"] if scale_file else 1.0
    use = use_lines(args.out, bool(scale_file), read_json(args.model / "model.json")["config"])
    card = {
        "name": args.name,
        "title": args.title,
        "summary": args.summary,
        "use": use,
        "scale": scale,
        "model_bytes": (args.model / "model.pt").stat().st_size,
        "evaluations": evaluations,
        "recipe": recipe,
        "recipe_seeds": max((len(v) for v in recipe.values()), default=0),
        "recipe_note": args.recipe_note,
        "fixture": (
            {**evaluation(args.fixture_eval), "predictions": prediction_digest(args.fixture_eval)}
            if args.fixture_eval
            else None
        ),
        "provenance": provenance(args.model.resolve()),
        "limits": args.limit,
        "against_replaced": read_json(args.gate) if args.gate else None,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    staging = args.out.with_name(f".{args.out.name}.tmp-{os.getpid()}-{secrets.token_hex(8)}")
    staging.mkdir()
    for name in COPIED:
        shutil.copy2(args.model / name, staging / name)
    if scale_file:
        shutil.copy2(scale_file, staging / "scale.json")
    (staging / CARD_NAME).write_text(json.dumps(card, indent=1) + "\n")
    (staging / "README.md").write_text(card_text(card))
    publish(staging, args.out)
    print(f"model_card: wrote {args.out} ({card['model_bytes'] / 1e6:.1f} MB weights)")


if __name__ == "__main__":
    sys.exit(main())
