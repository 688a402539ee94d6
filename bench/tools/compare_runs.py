"""Compare two pipeline runs artifact by artifact: are the outputs byte-identical?

    python bench/tools/compare_runs.py RUN_A RUN_B

Every file under RUN_A and RUN_B (same relative paths) is compared byte for byte, except where
a field records time, the machine or the run's own path rather than the result:

- manifest.json: compared as JSON without `created`, `timings`, `runtime`, `executor` (workers'
  timings), the input/output paths and content hashes (a model directory's hash covers its
  model.json's timings; every file is compared itself), and any string holding the run
  directory (RUN_A / RUN_B replaced by one placeholder);
- model.json: as JSON without train.seconds, train.frames_per_s, train.runtime and paths;
- Parquet files that are not byte-identical: compared column by column (NaN equal to NaN),
  without the timing columns frames_per_s, elapsed_s, data_wait_share (train_log) and seconds
  (sweep.parquet), which one side may lack;
- model.pt: the saved tensors (state dict) exactly, plus the non-tensor metadata as above
  (torch's zip container records file names that differ run to run, not the weights).

Files under `.dali-cache/` (training caches derived from the artifacts, e.g. the gt database)
are not compared. Other files must be byte-identical; where a JSON file is not, the line says
which fields differ. Prints one line per difference (and per file only one side has) and a
summary; exits 1 when anything differs, so it is usable as a check that a refactor leaves a
run's artifacts unchanged.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

# fields that record time or the machine: timings, runtime, per-frame seconds, and the output's
# byte count (its JSON files hold the timings)
TIMING_KEYS = {
    "created", "timings", "runtime", "executor", "seconds", "frames_per_s", "detector_seconds",
    "per_frame_compute_seconds", "bytes",
}  # fmt: skip
TIMING_COLUMNS = {"frames_per_s", "elapsed_s", "seconds", "data_wait_share"}


def _strip(value, roots: tuple[str, ...]):
    """`value` without timing keys, paths and content hashes (a model directory's hash covers
    its model.json, timings included; the files themselves are compared one by one), with the
    run directories replaced by '<RUN>'."""
    if isinstance(value, dict):
        return {
            _strip(key, roots): _strip(item, roots)
            for key, item in value.items()
            if key not in TIMING_KEYS and key != "path" and not key.endswith("hash")
        }
    if isinstance(value, list):
        return [_strip(item, roots) for item in value]
    if isinstance(value, str):
        for root in roots:
            value = value.replace(root, "<RUN>")
        return value
    return value


def _json_differences(a: Path, b: Path, roots: tuple[str, ...]) -> list[str]:
    left = _strip(json.loads(a.read_text()), roots)
    right = _strip(json.loads(b.read_text()), roots)
    return [] if left == right else _first_differences(left, right, "")


def _first_differences(left, right, where: str, limit: int = 5) -> list[str]:
    """Up to `limit` paths (a.b[3]) where two JSON values differ."""
    if isinstance(left, dict) and isinstance(right, dict):
        found = []
        for key in sorted(set(left) | set(right)):
            if left.get(key, "<absent>") != right.get(key, "<absent>"):
                found += _first_differences(
                    left.get(key, "<absent>"), right.get(key, "<absent>"), f"{where}.{key}"
                )
            if len(found) >= limit:
                break
        return found[:limit]
    if isinstance(left, list) and isinstance(right, list) and len(left) == len(right):
        found = []
        for index, (x, y) in enumerate(zip(left, right, strict=True)):
            if x != y:
                found += _first_differences(x, y, f"{where}[{index}]")
            if len(found) >= limit:
                break
        return found[:limit]
    return [f"{where or '.'}: {str(left)[:80]} != {str(right)[:80]}"]


def _same_column(left, right) -> bool:
    """Equal values, NaN equal to NaN (a sweep without detections logs NaN sizes)."""
    import numpy as np

    if left.type != right.type:
        return False
    if left.type in ("float", "double", "halffloat"):
        return np.array_equal(
            left.to_numpy(zero_copy_only=False),
            right.to_numpy(zero_copy_only=False),
            equal_nan=True,
        )
    return left.equals(right)


def _model_differences(a: Path, b: Path, roots: tuple[str, ...]) -> list[str]:
    import torch

    left = torch.load(a, map_location="cpu", weights_only=False)
    right = torch.load(b, map_location="cpu", weights_only=False)
    return _object_differences(left, right, "", roots)


def _object_differences(left, right, where: str, roots: tuple[str, ...]) -> list[str]:
    import torch

    if isinstance(left, torch.Tensor) or isinstance(right, torch.Tensor):
        same = (
            isinstance(left, torch.Tensor)
            and isinstance(right, torch.Tensor)
            and left.dtype == right.dtype
            and left.shape == right.shape
            and torch.equal(left, right)
        )
        return [] if same else [f"{where}: tensors differ"]
    if isinstance(left, dict) and isinstance(right, dict):
        if set(left) != set(right):
            return [f"{where}: keys {sorted(set(left) ^ set(right))[:5]} on one side only"]
        found = []
        for key in left:
            if key in TIMING_KEYS:
                continue
            found += _object_differences(left[key], right[key], f"{where}.{key}", roots)
        return found
    if isinstance(left, list | tuple) and isinstance(right, list | tuple):
        if len(left) != len(right):
            return [f"{where}: lengths {len(left)} != {len(right)}"]
        found = []
        for index, (x, y) in enumerate(zip(left, right, strict=True)):
            found += _object_differences(x, y, f"{where}[{index}]", roots)
        return found
    return (
        [] if _strip(left, roots) == _strip(right, roots) else [f"{where}: {left!r} != {right!r}"]
    )


def _table_differences(a: Path, b: Path) -> list[str]:
    """Why two Parquet files differ: columns on one side only, columns with other values
    (timing columns such as a sweep's seconds and a train log's frames/s are not compared)."""
    import pyarrow.parquet as pq

    left, right = pq.read_table(a), pq.read_table(b)
    found = [
        f"column '{c}' only in the first"
        for c in left.column_names
        if c not in right.column_names and c not in TIMING_COLUMNS
    ]
    found += [
        f"column '{c}' only in the second"
        for c in right.column_names
        if c not in left.column_names and c not in TIMING_COLUMNS
    ]
    if left.num_rows != right.num_rows:
        return [*found, f"rows {left.num_rows} != {right.num_rows}"]
    found += [
        f"column '{c}' differs"
        for c in left.column_names
        if c in right.column_names
        and c not in TIMING_COLUMNS
        and not _same_column(left[c], right[c])
    ]
    return found


def compare_file(a: Path, b: Path, roots: tuple[str, ...]) -> list[str]:
    """The differences between two artifacts' files (empty: the same result)."""
    if a.name in ("manifest.json", "model.json"):
        return _json_differences(a, b, roots)
    if a.name == "model.pt":
        return _model_differences(a, b, roots)
    if a.read_bytes() == b.read_bytes():
        return []
    if a.suffix == ".parquet":
        return _table_differences(a, b)
    if a.suffix == ".json":
        return _json_differences(a, b, roots)
    return ["bytes differ"]


def compare_runs(run_a: Path, run_b: Path) -> tuple[int, list[str]]:
    """(files compared, one line per difference)."""
    roots = (str(run_a.resolve()), str(run_b.resolve()), str(run_a), str(run_b))
    files_a = {p.relative_to(run_a) for p in run_a.rglob("*") if p.is_file() and not cached(p)}
    files_b = {p.relative_to(run_b) for p in run_b.rglob("*") if p.is_file() and not cached(p)}
    lines = [f"only in {run_a}: {p}" for p in sorted(files_a - files_b)]
    lines += [f"only in {run_b}: {p}" for p in sorted(files_b - files_a)]
    for relative in sorted(files_a & files_b):
        for difference in compare_file(run_a / relative, run_b / relative, roots):
            lines.append(f"{relative}: {difference}")
    return len(files_a & files_b), lines


def cached(path: Path) -> bool:
    """A file of a training cache (`.dali-cache/`, e.g. the gt database): derived from the
    artifacts, not an output of its own."""
    return ".dali-cache" in path.parts


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[0], file=sys.stderr)
        print("usage: python bench/tools/compare_runs.py RUN_A RUN_B", file=sys.stderr)
        return 2
    run_a, run_b = Path(argv[0]), Path(argv[1])
    compared, lines = compare_runs(run_a, run_b)
    for line in lines:
        print(line)
    verdict = "identical" if not lines else f"{len(lines)} differences"
    print(f"{compared} files compared: {verdict} (timings, runtime and run paths ignored)")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
