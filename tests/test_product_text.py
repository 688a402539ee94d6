"""The product speaks of the product: code, help text, comments, tests, the Makefile, the
benchmarks and the documents say what dali does and why, never when or in which round of its
development something was written. docs/results/ is exempt: it is the archived measurement log
(history.md) and the raw material it cites."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("dali_cli", "stages", "tests", "bench", "docs", "Makefile", "README.md")
ARCHIVE = ROOT / "docs" / "results"
SUFFIXES = {".py", ".md", ".sh", ".toml", ".txt", ""}

HISTORY = re.compile(
    r"\b[Ss]essions? \d+"  # a session number or range
    r"|\b[Ss]ession-\d+"  # a session number as an adjective
    r"|\b[Ii]ssues? #?\d+"  # an issue number, with or without #, with or without an item
    r"|\.\./shared/"  # a path outside the repository
)

# options measured to gain nothing and leaving the product (docs/RESULTS.md, "Measured and
# removed"): their own text goes with them, so a hit next to one of their names is not counted
LEAVING = re.compile(
    r"(?<![\w-])-*(tta|fit[-_]ground|ground_fit|ignore[-_]min|ignore[-_]label|ignore regions"
    r"|continue[-_]schedule|schedule[-_]epochs|occlusion|size[-_]factor[-_]score[-_]min"
    r"|confident_e_pred|refine_passes|flip_test|--compile|compile_net)(?![\w-])"
)
WINDOW = 8  # lines above a hit that may name the leaving option it belongs to


def scanned_files() -> list[Path]:
    files = []
    for name in SCANNED:
        path = ROOT / name
        candidates = [path] if path.is_file() else sorted(path.rglob("*"))
        for file in candidates:
            if not file.is_file() or file.suffix not in SUFFIXES or ARCHIVE in file.parents:
                continue
            if "__pycache__" in file.parts:
                continue
            files.append(file)
    return files


def history_lines(path: Path, root: Path = ROOT) -> list[str]:
    """'path:line: text' of every line of `path` that cites development history."""
    if LEAVING.fullmatch(path.stem):  # a leaving option's own module
        return []
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    found = []
    for number, line in enumerate(lines, 1):
        if not HISTORY.search(line):
            continue
        if any(LEAVING.search(above) for above in lines[max(0, number - 1 - WINDOW) : number]):
            continue
        found.append(f"{path.relative_to(root)}:{number}: {line.strip()}")
    return found


def test_no_development_history_in_the_product():
    files = scanned_files()
    assert len(files) > 100, "the scan found too few files: is ROOT right?"
    hits = [hit for path in files for hit in history_lines(path)]
    assert not hits, "development history in the product:\n" + "\n".join(hits)


def test_the_pattern_catches_what_it_must(tmp_path):
    # spelt in two pieces so that this file does not match its own scan
    cited = ["see sess" "ion 12", "(sess" "ions 15-17)", "the sess" "ion-12 ablation",
             "iss" "ue 18's target", "Iss" "ue 22.1: a bug", "iss" "ue #7", "../sha" "red/M.md"]  # fmt: skip
    clean = ["a session of training", "the issue is the size bias", "shared/ memory"]
    assert all(HISTORY.search(text) for text in cited)
    assert not any(HISTORY.search(text) for text in clean)
    session = "sess" + "ion"
    sample = tmp_path / "sample.py"
    sample.write_text(
        f"x = 1\n# measured in {session} 3\n" + "y = 2\n" * WINDOW
        + f"# --tta: off, level in {session} 4\n",
        encoding="utf-8",
    )  # fmt: skip
    assert history_lines(sample, tmp_path) == [f"sample.py:2: # measured in {session} 3"]
