"""The product speaks of the product: code, help text, comments, tests, the Makefile, the
benchmarks, their results and the documents say what dali does and why, never when or in which
round of its development something was written, nor where on some machine it ran. A figure's
date of measurement belongs beside the figure (docs/RESULTS.md, docs/experiments.md, docs/results/,
bench/results/); how the project got there lives in git history."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("dali_cli", "stages", "tests", "bench", "docs", "Makefile", "README.md")
SUFFIXES = {".py", ".md", ".sh", ".toml", ".txt", ".json", ""}

HISTORY = re.compile(
    r"\b[Ss]essions? \d+"  # a session number or range
    r"|\b[Ss]ession-\d+"  # a session number as an adjective
    r"|\b[Ii]ssues? #?\d+"  # an issue number, with or without #, with or without an item
    r"|\.\./shared/"  # a path outside the repository
    r"|\bhistory\.md\b"  # the work log that git history replaced
    r"|(?<![\w.~}])/wo"
    r"rk/"  # an absolute path of the machine that ran something
    r"|(?<![\w.~}])/tmp/[a-z]"
    # a work log's phrases: which run or sitting did what, what has been fixed since
    r"|\b[Aa] later[ ]run\b|\bnow[ ]fixed\b|\bnot yet[ ]remeasured\b|\b[Tt]his[ ]session\b"
    r"|\bleft on the[ ]lease\b|\bwork[ ]period\b|\bwithin the[ ]lease\b|\bhelpers'[ ]jobs\b"
    r"|\b(?:[Ee]arlier|[Ll]ater) the[ ]same day\b|\bas first[ ]written\b"
)
# a calendar date (not part of a longer token such as a nuScenes scene name)
DATE = re.compile(r"(?<![-\w])20\d\d-[01]\d-[0-3]\d(?![-\w])")
# where a date may stand: beside a measured figure
DATED_DOCUMENTS = ("docs/RESULTS.md", "docs/experiments.md", "docs/results/", "bench/results/")
# what continues a comment or a quote on the next line, stripped before joining two lines
CONTINUATION = re.compile(r"^\s*(?:#+|//|\*|>|-)?\s*")


def scanned_files() -> list[Path]:
    files = []
    for name in SCANNED:
        path = ROOT / name
        candidates = [path] if path.is_file() else sorted(path.rglob("*"))
        for file in candidates:
            if not file.is_file() or file.suffix not in SUFFIXES:
                continue
            if "__pycache__" in file.parts or "fixtures" in file.parts:
                continue
            files.append(file)
    return files


def history_lines(path: Path, root: Path = ROOT) -> list[str]:
    """'path:line: text' of every line of `path` that cites development history or a machine
    path, including a citation broken across the line's end and the next line's start (comment
    and quote markers of the next line skipped); a date outside DATED_DOCUMENTS counts too."""
    relative = path.relative_to(root).as_posix()
    dates_allowed = relative.startswith(DATED_DOCUMENTS)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    found = []
    for number, line in enumerate(lines, 1):
        head = line.rstrip()
        following = CONTINUATION.sub("", lines[number]) if number < len(lines) else ""
        joined = f"{head} {following}"
        patterns = (HISTORY,) if dates_allowed else (HISTORY, DATE)
        if any(m.start() < len(head) for p in patterns for m in p.finditer(joined)):
            found.append(f"{relative}:{number}: {line.strip()}")
    return found


def test_no_development_history_in_the_product():
    files = scanned_files()
    assert len(files) > 100, "the scan found too few files: is ROOT right?"
    hits = [hit for path in files for hit in history_lines(path)]
    assert not hits, "development history in the product:\n" + "\n".join(hits)


def test_the_pattern_catches_what_it_must(tmp_path):
    # spelt in pieces so that this file does not match its own scan
    cited = ["see sess" "ion 12", "(sess" "ions 15-17)", "the sess" "ion-12 ablation",
             "iss" "ue 18's target", "Iss" "ue 22.1: a bug", "iss" "ue #7", "../sha" "red/M.md",
             "see results/hist" "ory.md", "--out /wo" "rk/runs/x", "RUN=/t" "mp/rx/mk",
             "ran in a la" "ter run", "two were defects, now fi" "xed", "no time left on the le" "ase",
             "in this sess" "ion", "did not finish within the le" "ase", "other help" "ers' jobs",
             "earlier the sa" "me day", "Later the sa" "me day, at a lower load",
             "streaming as first wr" "itten was slower"]  # fmt: skip
    clean = ["a session of training", "the issue is the size bias", "shared/ memory",
             "runs/work/x", "$TMPDIR/tmp/x", "a history of the run"]  # fmt: skip
    assert all(HISTORY.search(text) for text in cited)
    assert not any(HISTORY.search(text) for text in clean)
    assert DATE.search("measured on " + "2026-" + "11-28") and not DATE.search("n015-2018-07-24-11")
    session = "sess" + "ion"
    sample = tmp_path / "sample.py"
    sample.write_text(f"x = 1\n# measured in {session} 3\ny = 2\n", encoding="utf-8")
    assert history_lines(sample, tmp_path) == [f"sample.py:2: # measured in {session} 3"]


def test_a_citation_broken_across_two_lines_is_caught(tmp_path):
    session, day = "sess" + "ion", "2026-" + "11-24"
    sample = tmp_path / "sample.md"
    sample.write_text(f"as measured in {session}\n14, then\nagain\n", encoding="utf-8")
    assert history_lines(sample, tmp_path) == [f"sample.md:1: as measured in {session}"]
    code = tmp_path / "code.py"
    code.write_text(f"# the rows of\n# {session}\n# 9 and a date {day}\n", encoding="utf-8")
    assert [hit.split(":")[1] for hit in history_lines(code, tmp_path)] == ["2", "3"]
    results = tmp_path / "docs" / "RESULTS.md"
    results.parent.mkdir()
    results.write_text(f"x2 85.5 (measured {day})\n", encoding="utf-8")
    assert history_lines(results, tmp_path) == []
