"""`--no-progress` (dali_cli.commands.common.no_progress_option) on every command that draws a
progress bar: every tqdm bar of the package can be turned off, every command but the few that
draw none has the option, and with it the bar is gone from the output."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
from cli_commands import cli_commands, option_words
from click.testing import CliRunner

from dali_cli.cli import main

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"
KITTI = FIXTURES / "real" / "kitti"
DRIVE = FIXTURES / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
NUSCENES = FIXTURES / "real" / "nuscenes"
NUSCENES_SCAN = NUSCENES / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
# importer -> (a file it needs, its arguments but --out) of the small fixtures of tests/fixtures
FIXTURE_IMPORTS = {
    "kitti": (KITTI / "training" / "velodyne" / "000008.bin", ["import", "kitti", KITTI]),
    "kitti-raw": (DRIVE / "tracklet_labels.xml", ["import", "kitti-raw", DRIVE]),
    "nuscenes": (NUSCENES_SCAN, ["import", "nuscenes", NUSCENES_SCAN,
                                 "--boxes-csv", NUSCENES / "boxes_lidar.csv"]),
}  # fmt: skip
# the commands that draw no progress bar (they read a few files or print a table); every other
# command must accept --no-progress, so a new command either gets it or is added here knowingly
NO_BAR = {
    "compare-domains",
    "export model",
    "export openpcdet",
    "library show",
    "report",
    "sensors",
    "size-norm",
    "track-pseudo",
    "view",
}
# what a tqdm bar leaves in the output: a carriage return, "42%|" or a rate such as "3.1frame/s"
BAR = re.compile(r"\r|\d%\||[\d.?]+(?:it|frame)/s")


def tqdm_calls() -> list[tuple[Path, ast.Call]]:
    """Every tqdm(...) call in dali_cli/ and stages/, with its file."""
    calls = []
    for package in ("dali_cli", "stages"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
                func = getattr(node, "func", None)
                name = getattr(func, "id", None) or getattr(func, "attr", None)
                if isinstance(node, ast.Call) and name == "tqdm":
                    calls.append((path.relative_to(ROOT), node))
    return calls


def test_every_bar_can_be_turned_off():
    calls = tqdm_calls()
    assert len(calls) >= 10, "the tqdm calls were not found"
    for path, call in calls:
        disable = [k.value for k in call.keywords if k.arg == "disable"]
        assert disable, f"{path}, line {call.lineno}: tqdm( without disable="
        assert not isinstance(disable[0], ast.Constant), f"{path}, line {call.lineno}: constant"


def test_every_command_but_the_bar_free_ones_has_no_progress():
    commands = cli_commands()
    assert NO_BAR <= set(commands), f"not commands: {sorted(NO_BAR - set(commands))}"
    lacking = [
        name
        for name, command in sorted(commands.items())
        if name not in NO_BAR and "--no-progress" not in option_words(command)
    ]
    assert not lacking, (
        f"commands without --no-progress: {lacking} (if one draws no progress bar, add it to NO_BAR)"
    )


# ---------------------------------------------------------------------------------------------
# The commands run: the bar on stderr by default, none with --no-progress


def invoke(*args) -> tuple[int, str]:
    """Exit code and output (stdout and stderr: where tqdm draws) of `dali ARGS`."""
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.output


def run_both(make_args, tmp_path: Path) -> str:
    """Run a command (args from make_args(out)) with and without --no-progress: the bar only
    without; returns the output of the quiet run."""
    code, loud = invoke(*make_args(tmp_path / "loud"))
    assert code == 0, loud
    assert BAR.search(loud), f"no bar drawn without --no-progress: {loud!r}"
    code, quiet = invoke(*make_args(tmp_path / "quiet"), "--no-progress")
    assert code == 0, quiet
    assert not BAR.search(quiet), f"a bar drawn with --no-progress: {quiet!r}"
    return quiet


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "set"
    code, output = invoke("synth", "--sensor", "kitti", "--frames", 2, "--workers", 1,
                          "--out", out, "--no-progress")  # fmt: skip
    assert code == 0, output
    return out


def test_synth(tmp_path):
    quiet = run_both(
        lambda out: ["synth", "--sensor", "kitti", "--frames", 2, "--workers", 1, "--out", out],
        tmp_path,
    )
    assert "2 frames" in quiet


def test_library_build_point_models(tmp_path, synthetic):
    run_both(
        lambda out: ["library", "build", "--points", synthetic, "--min-points", 1, "--out", out],
        tmp_path,
    )


def test_import_openpcdet(tmp_path):
    root = tmp_path / "custom"
    (root / "points").mkdir(parents=True)
    (root / "labels").mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        points = np.c_[
            rng.uniform(-1, 1, (200, 3)) * [2, 1, 0.7] + [10, 0, -1], rng.uniform(size=200)
        ]
        np.save(root / "points" / f"{name}.npy", points.astype(np.float32))
        (root / "labels" / f"{name}.txt").write_text("10 0 -1 4 2 1.4 0.3 Vehicle\n")
    quiet = run_both(
        lambda out: ["import", "openpcdet", root, "--sensor", "kitti", "--out", out], tmp_path
    )
    assert "2 frames" in quiet


@pytest.mark.parametrize("name", sorted(FIXTURE_IMPORTS))
def test_import_fixture(tmp_path, name):
    needed, args = FIXTURE_IMPORTS[name]
    assert needed.is_file(), f"fixture {needed} missing"
    run_both(lambda out: [*args, "--out", out], tmp_path)


def test_export_kitti(tmp_path):
    code, output = invoke("import", "kitti", KITTI, "--out", tmp_path / "set", "--no-progress")
    assert code == 0, output
    run_both(
        lambda out: ["export", "kitti", tmp_path / "set", "--calib-root", KITTI, "--out", out],
        tmp_path,
    )
