"""`--no-progress` (dali_cli.commands.common.no_progress_option) on every command that draws a
progress bar: every tqdm bar of the package can be turned off, the commands whose code reaches
one (found by walking the source) have the option, and with it the bar is gone from the output."""

from __future__ import annotations

import ast
import copy
import functools
import re
from pathlib import Path

import numpy as np
import pytest
from cli_commands import cli_commands, option_words
from click.testing import CliRunner

from dali_cli.cli import main

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dali_cli", "stages")
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
# commands known to draw a bar: the source walk below must find at least these
DRAW_BARS = {
    "synth", "library build", "eval", "compare", "import kitti", "import kitti-raw",
    "import nuscenes", "import openpcdet", "import waymo", "export kitti", "pretrain",
    "ptsn-sweep", "pseudo-label", "ppcg-rc", "ppcg-cf", "retrain", "self-train",
}  # fmt: skip
# what a tqdm bar leaves in the output: a carriage return, "42%|" or a rate such as "3.1frame/s"
BAR = re.compile(r"\r|\d%\||[\d.?]+(?:it|frame)/s")


# ---------------------------------------------------------------------------------------------
# The source walk: which functions draw a bar, and which commands reach one


@functools.cache
def modules() -> dict[str, ast.Module]:
    """Every module of dali_cli/ and stages/ by its dotted name, parsed."""
    found = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = ast.parse(path.read_text(encoding="utf-8"), str(path))
    return found


def is_tqdm_call(node: ast.AST) -> bool:
    return isinstance(node, ast.Call) and (
        (isinstance(node.func, ast.Name) and node.func.id == "tqdm")
        or (isinstance(node.func, ast.Attribute) and node.func.attr == "tqdm")
    )


def units(tree: ast.Module) -> dict[str, ast.AST]:
    """The module's top-level functions and its classes' methods ("Class.method")."""
    found = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            found[node.name] = node
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                    found[f"{node.name}.{item.name}"] = item
    return found


@functools.cache
def imports(module: str) -> dict[str, set[tuple[str, str | None]]]:
    """Local name -> (module, name) it was imported as, from every import of the module (those
    inside functions too); name None: the local name may be the module itself (`from package
    import name` gives both: a package may re-export a function named as one of its modules)."""
    found: dict[str, set[tuple[str, str | None]]] = {}
    for node in ast.walk(modules()[module]):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                entries = found.setdefault(alias.asname or alias.name, set())
                entries.add((node.module, alias.name))
                if f"{node.module}.{alias.name}" in modules():
                    entries.add((f"{node.module}.{alias.name}", None))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.asname:
                    found.setdefault(alias.asname, set()).add((alias.name, None))
    return found


def resolve(module: str, name: str, seen: frozenset = frozenset()) -> set[tuple[str, str]]:
    """The functions and methods (module, unit) that `name` in `module` stands for: a function,
    every method of a class, or what an import (re-exports followed) names."""
    if module not in modules() or (module, name) in seen:
        return set()
    own = units(modules()[module])
    if name in own:
        return {(module, name)}
    methods = {(module, unit) for unit in own if unit.startswith(f"{name}.")}
    if methods:
        return methods
    found = set()
    for target, attr in imports(module).get(name, ()):
        if attr is not None:
            found |= resolve(target, attr, seen | {(module, name)})
    return found


def module_alias(module: str, name: str) -> str | None:
    """The module of ours that the local name `name` of `module` stands for, if any."""
    targets = [t for t, attr in imports(module).get(name, ()) if attr is None and t in modules()]
    return targets[0] if targets else None


def references(module: str, unit: str) -> set[tuple[str, str]]:
    """The functions and methods one function (nested functions and lambdas included) names."""
    node = units(modules()[module])[unit]
    cls = unit.split(".")[0] if "." in unit else None
    found = set()
    for child in ast.walk(node):
        if isinstance(child, ast.Name):
            found |= resolve(module, child.id)
        elif isinstance(child, ast.Attribute) and isinstance(child.value, ast.Name):
            if cls is not None and child.value.id == "self":
                found |= resolve(module, f"{cls}.{child.attr}") & {(module, f"{cls}.{child.attr}")}
            elif (target := module_alias(module, child.value.id)) is not None:
                found |= resolve(target, child.attr)
    return found


@functools.cache
def bar_functions() -> frozenset[tuple[str, str]]:
    """Every function or method that draws a bar, or names one that does (transitively)."""
    graph = {
        (module, unit): references(module, unit)
        for module, tree in modules().items()
        for unit in units(tree)
    }
    reached = {
        (module, unit)
        for module, tree in modules().items()
        for unit, node in units(tree).items()
        if any(is_tqdm_call(child) for child in ast.walk(node))
    }
    while True:
        more = {key for key, named in graph.items() if key not in reached and named & reached}
        if not more:
            return frozenset(reached)
        reached |= more


def commands_that_draw_bars() -> set[str]:
    return {
        name
        for name, command in cli_commands().items()
        if (command.callback.__module__, command.callback.__name__) in bar_functions()
    }


def test_every_bar_can_be_turned_off():
    calls = [
        (module, node)
        for module, tree in modules().items()
        for node in ast.walk(tree)
        if is_tqdm_call(node)
    ]
    assert len(calls) >= 10, "the tqdm calls were not found"
    for module, call in calls:
        disable = [k.value for k in call.keywords if k.arg == "disable"]
        assert disable, f"{module}, line {call.lineno}: tqdm( without disable="
        assert not isinstance(disable[0], ast.Constant), f"{module}, line {call.lineno}: constant"


def test_every_command_that_draws_a_bar_has_no_progress():
    drawing = commands_that_draw_bars()
    assert drawing >= DRAW_BARS, f"the source walk lost {sorted(DRAW_BARS - drawing)}"
    commands = cli_commands()
    lacking = [
        name for name in sorted(drawing) if "--no-progress" not in option_words(commands[name])
    ]
    assert not lacking, f"commands that draw a progress bar without --no-progress: {lacking}"


def test_the_walk_spares_commands_without_a_bar():
    drawing = commands_that_draw_bars()
    assert not drawing & {"sensors", "library show", "view", "report", "compare-domains"}


def test_a_new_bar_is_caught(monkeypatch):
    """A bar added to the body of a stage without one (size-norm's `build`) makes its command
    one that draws a bar."""
    tree = copy.deepcopy(modules()["stages.size_norm"])
    units(tree)["build"].body[:0] = ast.parse("from tqdm import tqdm\ntqdm([], disable=True)").body
    monkeypatch.setitem(modules(), "stages.size_norm", tree)
    bar_functions.cache_clear()
    try:
        assert "size-norm" in commands_that_draw_bars()
    finally:
        monkeypatch.undo()
        bar_functions.cache_clear()


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
    if not needed.is_file():
        pytest.skip(f"fixture {needed} not found")
    run_both(lambda out: [*args, "--out", out], tmp_path)


def test_export_kitti(tmp_path):
    if not (KITTI / "training" / "velodyne" / "000008.bin").is_file():
        pytest.skip("KITTI fixture not found under tests/fixtures/real")
    code, output = invoke("import", "kitti", KITTI, "--out", tmp_path / "set", "--no-progress")
    assert code == 0, output
    run_both(
        lambda out: ["export", "kitti", tmp_path / "set", "--calib-root", KITTI, "--out", out],
        tmp_path,
    )
