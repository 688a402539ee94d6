"""What each step of a run's first DALI iteration kept, from the stages' manifests:

    python bench/tools/run_counts.py RUN

prints PTSN's scale ŝ (with the sweep's warnings, e.g. no detections), the pseudo boxes kept, the boxes
RC and CF replaced, and the frames the retraining saw (what `make tiny` ends with)."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def counts(run: Path, step: str) -> dict:
    """The `outputs.counts` of RUN/iter1/<step>/manifest.json ({} when the step has not run)."""
    path = run / "iter1" / step / "manifest.json"
    return json.loads(path.read_text())["outputs"]["counts"] if path.exists() else {}


def main(run: Path) -> None:
    scale = json.loads((run / "iter1" / "ptsn" / "scale.json").read_text())
    pseudo, rc, cf = counts(run, "pseudo"), counts(run, "rc"), counts(run, "cf")
    model = counts(run, "model")
    sweep = json.loads((run / "iter1" / "ptsn" / "manifest.json").read_text())
    warnings = "; ".join(sweep.get("notes", [])) or "no warning"
    print(f"ptsn-sweep: scale {scale['scale']:.3f} ({warnings})")
    print(f"pseudo-label: {pseudo.get('boxes')} boxes kept on {pseudo.get('frames')} frames")
    print(f"ppcg-rc: {rc.get('boxes_rc')} of {rc.get('boxes')} boxes replaced")
    print(f"ppcg-cf: {cf.get('boxes_cf')} of {cf.get('boxes')} boxes replaced")
    print(f"retrain: {model.get('frames_seen')} frames seen")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
