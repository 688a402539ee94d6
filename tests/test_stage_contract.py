"""The stage contract: stages and the core modules are plain Python (no click), stages do not
import each other, and their plain errors reach the user through one mapping in dali_cli.cli."""

from __future__ import annotations

import ast
import pickle
from pathlib import Path

import pytest
from click.testing import CliRunner

from dali_cli.artifacts import ArtifactError
from dali_cli.cli import main
from dali_cli.errors import ParameterError, StageError

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
        ["ptsn-sweep", "--model", str(tmp_path / "model"), "--target", str(tmp_path / "target"),
         "--frames", "2", "--frame-fraction", "0.5", "--out", str(tmp_path / "o")],
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "--frames / --frame-fraction" in result.output
    assert "frame_fraction" not in result.output
    # any other StageError: exit 1 with its message (the missing frames.zarr is named)
    result = runner.invoke(
        main,
        ["pseudo-label", "--model", str(tmp_path / "model"), "--target", str(tmp_path / "target"),
         "--scale", "1.0", "--out", str(tmp_path / "o")],
    )  # fmt: skip
    assert result.exit_code == 1 and "frames.zarr" in result.output, result.output
    assert not (tmp_path / "o").exists()
