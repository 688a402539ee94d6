"""The benchmark scripts pass dali options that exist: a renamed option (`--quiet` became
`--no-progress`) breaks a benchmark only when someone runs it, often on a lent GPU machine, so
every `--option` word in bench/ must be an option of some dali command, of the script's own
argparse parser, or of the few other tools the scripts call (listed here)."""

from __future__ import annotations

import re
from pathlib import Path

from cli_commands import cli_commands, option_words

BENCH = Path(__file__).resolve().parents[1] / "bench"
OTHER_TOOLS = {
    # pip, torchrun, Ray, nvidia-smi, make, unshare
    "--mount-proc", "--no-index", "--no-deps", "--no-compile", "--no-cache-dir", "--upgrade", "--standalone",
    "--nproc-per-node", "--head", "--block", "--num-cpus", "--object-store-memory",
    "--include-dashboard", "--disable-usage-stats", "--query-gpu", "--no-print-directory",
}  # fmt: skip


def dali_options() -> set[str]:
    return set().union(*(option_words(command) for command in cli_commands().values()))


def unknown_options(text: str, known: set[str]) -> list[str]:
    own = set(re.findall(r'add_argument\(\s*"(--[a-z0-9-]+)"', text))
    words = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]+)", text))
    return sorted(words - known - own - OTHER_TOOLS - {"--help"})


def test_every_option_in_the_benchmarks_exists():
    known = dali_options()
    scripts = sorted(p for p in BENCH.rglob("*") if p.suffix in {".py", ".sh"})
    assert len(scripts) > 10
    unknown = {str(p.relative_to(BENCH)): unknown_options(p.read_text(), known) for p in scripts}
    assert not {name: words for name, words in unknown.items() if words}


def test_a_renamed_option_is_caught():
    text = 'subprocess.run([dali, "pretrain", "--quiet", "--out", out])'
    assert unknown_options(text, dali_options()) == ["--quiet"]
