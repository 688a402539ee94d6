"""The stage contract: stages and the core modules are plain Python (no click), stages do not
import each other, and their plain errors reach the user through one mapping in dali_cli.cli."""

from __future__ import annotations

import ast
import pickle
from pathlib import Path

import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.runtime.errors import ParameterError, StageError
from dali_cli.store.artifacts import ArtifactError

ROOT = Path(__file__).resolve().parent.parent
# modules that stages and engines call: they must not depend on the command line
CLICK_FREE = [
    *sorted((ROOT / "stages").glob("*.py")),
    *[
        p
        for p in sorted((ROOT / "dali_cli").rglob("*.py"))
        if "commands" not in p.parts and p.name != "cli.py"
    ],
]


def imported_modules(path: Path) -> set[str]:
    """Every module `path` imports, at any depth (lazy imports inside functions included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


@pytest.mark.parametrize("path", CLICK_FREE, ids=lambda p: str(p.relative_to(ROOT)))
def test_stages_and_library_do_not_import_click(path):
    assert not {m for m in imported_modules(path) if m == "click" or m.startswith("click.")}


@pytest.mark.parametrize("path", sorted((ROOT / "stages").glob("*.py")), ids=lambda p: p.name)
def test_stages_do_not_import_each_other(path):
    assert not {m for m in imported_modules(path) if m.startswith("stages")}


# the stage module(s) a command module may call, when not named like it
COMMAND_STAGES = {"evaluate": ("eval",), "library": ("library_build",), "importers": ("import_",)}


def test_commands_call_their_own_stage_only():
    """A command parses and prints; it calls its own stage, never another stage's internals."""
    for path in sorted((ROOT / "dali_cli" / "commands").glob("*.py")):
        allowed = COMMAND_STAGES.get(path.stem, (path.stem,))
        for module in imported_modules(path):
            if module.startswith("stages."):
                assert module.split(".", 1)[1].startswith(allowed), (path.name, module)


def test_errors_survive_pickling_with_their_fields():
    """Worker processes and engines send errors back pickled: fields and type must survive."""
    error = pickle.loads(pickle.dumps(ParameterError(("frames", "frame_fraction"), "not both")))
    assert isinstance(error, ParameterError) and error.fields == ("frames", "frame_fraction")
    assert str(error) == "frames / frame_fraction: not both"
    error = pickle.loads(pickle.dumps(ArtifactError("x/boxes.parquet: row 3", path="x")))
    assert isinstance(error, StageError) and error.path == "x" and "row 3" in str(error)


def test_stage_error_mapping(tmp_path):
    runner = CliRunner()
    (tmp_path / "model").mkdir()
    (tmp_path / "target").mkdir()
    # a ParameterError raised by the stage: exit 2, rendered with the command's flags
    result = runner.invoke(
        main,
        ["ptsn-sweep", "--model", str(tmp_path / "model"), "--data", str(tmp_path / "target"),
         "--frames", "2", "--frame-fraction", "0.5", "--out", str(tmp_path / "o")],
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "--frames / --frame-fraction" in result.output
    assert "frame_fraction" not in result.output
    # any other StageError: exit 1 with its message (the missing frames.zarr is named)
    result = runner.invoke(
        main,
        ["pseudo-label", "--model", str(tmp_path / "model"), "--data", str(tmp_path / "target"),
         "--scale", "1.0", "--out", str(tmp_path / "o")],
    )  # fmt: skip
    assert result.exit_code == 1 and "frames.zarr" in result.output, result.output
    assert not (tmp_path / "o").exists()


# library modules whose ParameterErrors reach the user through these commands
SHARED_BODIES = {"dali_cli/ppcg/run.py": ("ppcg_rc", "ppcg_cf"), "dali_cli/merge.py": ("merge",)}


def parameter_fields(path: Path) -> set[str]:
    """The stage argument names every `ParameterError(fields, ...)` in `path` names."""
    fields = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ParameterError":
            first = node.args[0]
            items = first.elts if isinstance(first, ast.Tuple) else [first]
            fields |= {item.value for item in items if isinstance(item, ast.Constant)}
    return fields


def command_params(module: str) -> set[str]:
    """Parameter names of `dali_cli.commands.<module>`'s command and its subcommands."""
    import importlib

    import click

    pending, names = [importlib.import_module(f"dali_cli.commands.{module}").command], set()
    while pending:
        current = pending.pop()
        names |= {param.name for param in current.params}
        if isinstance(current, click.Group):
            pending.extend(current.commands.values())
    return names


def test_every_parameter_error_names_a_flag_of_its_command():
    """A ParameterError's fields are rendered as the command's flags (`range_m` -> --range-m):
    a field no option carries would reach the user as a bare argument name."""
    stage_commands = {"eval": "evaluate", "library_build": "library"}
    sources = {
        ROOT / "stages" / f"{stage}.py": (stage_commands.get(stage, stage),)
        for stage in (p.stem for p in (ROOT / "stages").glob("*.py"))
    }
    for stage in (
        "import_kitti",
        "import_kitti_raw",
        "import_kitti_odometry",
        "import_nuscenes",
        "import_openpcdet",
        "import_waymo",
    ):
        sources[ROOT / "stages" / f"{stage}.py"] = ("importers",)
    for relative, stages in SHARED_BODIES.items():
        sources[ROOT / relative] = stages
    for path, modules in sources.items():
        fields = parameter_fields(path)
        for module in modules:
            if module == "__init__":
                continue
            missing = fields - command_params(module)
            assert not missing, (path.name, module, missing)
