"""Property fuzz over the whole command tree (docs/input-validation.md, "Parameter kinds").

1. Every numeric option of every command (found by walking the click tree, so a new option is
   covered the day it is added) is fed NaN, ±inf, 0, negative, 1e-300 and 1e308 (as one number,
   or in each place of an 'a,b,c' / 'LOW:HIGH' option). NaN, ±inf and 1e308 are nonsense for
   every option: they must be refused as a usage error naming the option. No value may end in
   a traceback or write anything.
2. The model card (model.json) and an input artifact's manifest.json, replaced by malformed
   JSON (garbage bytes, truncated text, JSON of the wrong shape, a valid document with one
   field replaced by an arbitrary JSON value): no traceback, a non-zero exit whenever the
   document is not what dali writes, and nothing written (the model's checkpoint is a
   placeholder, so no case runs a stage to its end; the manifest cases run with --dry-run).

The option values are parsed before any input is opened (click converts the options given on
the command line first), so part 1 runs no stage; part 2 uses tiny inputs.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import tempfile
from pathlib import Path

import click
import pytest
from cli_commands import cli_commands, option_words
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_malformed_inputs import TOY
from toy_scenes import write_toy_dataset

from dali_cli.cli import main
from dali_cli.detector.config import DetectorConfig
from dali_cli.sensors import get_profile

HOSTILE = {"nan": True, "inf": True, "-inf": True, "1e308": True, "0": False, "-1": False,
           "1e-300": False}  # fmt: skip
"""Each value, and whether it is nonsense for every numeric option (then it must be refused)."""

NUMERIC_TYPES = (click.types.IntParamType, click.types.FloatParamType)


def numeric_shape(option: click.Option) -> str | None:
    """How a number is spelt for `option`: '{}' (one number), '{},{},{}' (a tuple type), '{}:{}'
    (a LOW:HIGH text); None for options that take no number."""
    kind = option.type
    if isinstance(kind, NUMERIC_TYPES) or type(kind).__name__ in ("QuantityType", "CoreCount"):
        return "{}"
    if hasattr(kind, "count") and hasattr(kind, "each"):  # 'a,b,c' tuples
        return ",".join(["{}"] * kind.count)
    if "LOW:HIGH" in (kind.name or "") or "LOW:HIGH" in (option.help or ""):
        return "{}:{}"
    return None


def numeric_options() -> list[tuple[str, str, str]]:
    """(command, option word, spelling) of every numeric option of every command."""
    found = []
    for name, command in sorted(cli_commands().items()):
        for param in command.params:
            if isinstance(param, click.Option) and not param.is_flag:
                shape = numeric_shape(param)
                if shape is not None:
                    found.append((name, param.opts[0], shape))
    return found


OPTIONS = numeric_options()


def test_the_walk_finds_the_numeric_options_of_the_stages():
    """The walk is not vacuous: it finds options of every kind of spelling."""
    found = {(command, option) for command, option, _ in OPTIONS}
    for expected in (("pretrain", "--lr"), ("pretrain", "--target-size"), ("eval", "--scale"),
                     ("ppcg-cf", "--range-m"), ("ptsn-sweep", "--scales"),
                     ("synth", "--workers"), ("pretrain", "--loader-workers")):  # fmt: skip
        assert expected in found
    assert len({command for command, _, _ in OPTIONS}) >= 15


def tree_hashes(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.blake2b(p.read_bytes(), digest_size=8).hexdigest()
        if p.is_file()
        else "dir"
        for p in sorted(root.rglob("*"))
    }


def run_cli(args: list) -> tuple[int, str, BaseException | None]:
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.output, result.exception


def assert_clean_failure(args, code, output, exception) -> None:
    """Exit 1 or 2, a message, no traceback."""
    assert code in (1, 2), (args, code, output)
    assert isinstance(exception, SystemExit), f"traceback for {args}: {exception!r}\n{output}"
    assert "Traceback" not in output and output.strip(), (args, output)


def test_every_numeric_option_refuses_nonsense_without_a_traceback(tmp_path):
    """Every numeric option x every hostile value x every place of a multi-number option."""
    failures = []
    for command, option, shape in OPTIONS:
        slots = shape.count("{}")
        has_out = "--out" in option_words(cli_commands()[command])
        for value, nonsense in HOSTILE.items():
            for place in range(slots):
                fill = ["1"] * slots
                fill[place] = value  # one hostile number among plausible ones
                args = [*command.split(), option, shape.format(*fill)]
                args += ["--out", tmp_path / "out"] if has_out else []
                code, output, exception = run_cli(args)
                traceback = not (exception is None or isinstance(exception, SystemExit))
                refused = code == 2 and option in output
                if traceback or "Traceback" in output or code == 0 or (nonsense and not refused):
                    failures.append((args[:3], code, output.strip()[-160:], exception))
    assert not failures, failures[:5]
    assert list(tmp_path.iterdir()) == []  # nothing written


# ---------------------------------------------------------------------------------------------
# malformed model cards and manifests


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """A target frame set, a box artifact made from it (with a manifest) and a model directory
    (a valid model.json, a placeholder checkpoint: every case stops before loading it or fails
    on it cleanly)."""
    root = tmp_path_factory.mktemp("fuzz")
    write_toy_dataset(root / "target", get_profile("kitti"), seed=2, **TOY)
    shutil.copytree(root / "target", root / "boxes")
    (root / "boxes" / "manifest.json").write_text(json.dumps(VALID_MANIFEST))
    (root / "model").mkdir()
    (root / "model" / "model.json").write_text(json.dumps(VALID_CARD))
    (root / "model" / "model.pt").write_bytes(b"not a checkpoint")
    (root / "library").mkdir()
    return root


VALID_MANIFEST = {"stage": "pseudo_label", "dali_version": "0", "params": {},
                  "inputs": {"target": [{"path": "t", "hash": "0" * 32}]},
                  "outputs": {"files": 2, "counts": {}}}  # fmt: skip
VALID_CARD = {"detector": "pillar-centerpoint-iou-refine", "config": DetectorConfig().to_dict(),
              "card": {"stage": "pretrain", "source_sensor": "kitti", "size_norm": "none"}}  # fmt: skip

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=8,
)


def with_field(document: dict, path: list[str], value) -> dict:
    """A deep copy of `document` with the field at `path` replaced by `value`."""
    copy = json.loads(json.dumps(document))
    node = copy
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return copy


def malformed(valid: dict, fields: list[list[str]]):
    """Bytes of a malformed variant of `valid`, and whether it is plainly not what dali writes
    (not JSON, not an object): then the command must fail."""
    garbage = st.binary(max_size=40).map(lambda b: (b, True))
    truncated = st.integers(1, 30).map(lambda n: (json.dumps(valid).encode()[:n], True))
    shaped = json_values.filter(lambda v: not isinstance(v, dict)).map(
        lambda v: (json.dumps(v).encode(), True)
    )
    one_field = st.tuples(st.sampled_from(fields), json_values).map(
        lambda pair: (json.dumps(with_field(valid, *pair)).encode(), False)
    )
    return garbage | truncated | shaped | one_field


def card_fields() -> list[list[str]]:
    return (
        [["config", name] for name in VALID_CARD["config"]]
        + [["card", name] for name in VALID_CARD["card"]]
        + [["config"], ["card"]]
    )


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(document=malformed(VALID_CARD, card_fields()),
       command=st.sampled_from(["pseudo-label", "ptsn-sweep", "eval"]))  # fmt: skip
def test_a_malformed_model_card_fails_cleanly(inputs, tmp_path, document, command):
    content, nonsense = document
    tmp_path = Path(tempfile.mkdtemp(dir=tmp_path))  # one directory per example
    model = tmp_path / "model"
    shutil.copytree(inputs / "model", model)
    (model / "model.json").write_bytes(content)
    out = tmp_path / "out"
    args = {
        "pseudo-label": ["pseudo-label", "--model", model, "--data", inputs / "target",
                         "--scale", "1", "--out", out, "--no-progress"],
        "ptsn-sweep": ["ptsn-sweep", "--model", model, "--data", inputs / "target",
                       "--out", out, "--no-progress"],
        "eval": ["eval", "--model", model, "--data", inputs / "target", "--scale", "1",
                 "--out", tmp_path / "m.json", "--no-progress"],
    }[command]  # fmt: skip
    before = tree_hashes(inputs), tree_hashes(tmp_path)
    code, output, exception = run_cli(args)
    assert exception is None or isinstance(exception, SystemExit), (args, exception, output)
    assert "Traceback" not in output
    if nonsense:
        assert_clean_failure(args, code, output, exception)
        assert "model.json" in output, output
    assert code != 0, (args, output)  # the checkpoint is a placeholder: never a model to run
    assert (tree_hashes(inputs), tree_hashes(tmp_path)) == before  # nothing written


def manifest_fields() -> list[list[str]]:
    return [["inputs"], ["inputs", "target"], ["outputs"], ["stage"], ["params"]]


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(document=malformed(VALID_MANIFEST, manifest_fields()))
def test_a_malformed_input_manifest_fails_cleanly(inputs, tmp_path, document):
    content, nonsense = document
    tmp_path = Path(tempfile.mkdtemp(dir=tmp_path))  # one directory per example
    boxes = tmp_path / "boxes"
    shutil.copytree(inputs / "boxes", boxes)
    (boxes / "manifest.json").write_bytes(content)
    try:
        parsed = json.loads(content)
    except ValueError:
        parsed = None
    records = parsed.get("inputs") if isinstance(parsed, dict) else None
    wrong_records = isinstance(parsed, dict) and "inputs" in parsed and not (
        isinstance(records, dict)
        and all(isinstance(v, list) and all(isinstance(r, dict) and isinstance(r.get("path"), str)
                and isinstance(r.get("hash"), str) for r in v) for v in records.values())
    )  # fmt: skip
    args = ["ppcg-rc", "--data", inputs / "target", "--boxes", boxes, "--library",
            inputs / "library", "--out", tmp_path / "out", "--dry-run"]  # fmt: skip
    before = tree_hashes(inputs), tree_hashes(tmp_path)
    code, output, exception = run_cli(args)
    assert exception is None or isinstance(exception, SystemExit), (args, exception, output)
    assert "Traceback" not in output
    if nonsense or wrong_records:
        assert_clean_failure(args, code, output, exception)
        assert "manifest.json" in output, output
    assert (tree_hashes(inputs), tree_hashes(tmp_path)) == before


def test_hostile_values_are_what_the_kinds_refuse():
    """The fuzz's notion of nonsense agrees with the kinds: no kind accepts NaN, ±inf or 1e308."""
    from dali_cli import quantities

    kinds = [v for v in vars(quantities).values() if isinstance(v, quantities.Quantity)]
    assert len(kinds) >= 10
    for kind in kinds:
        for value in (math.nan, math.inf, -math.inf, 1e308, 10**400):
            assert kind.problem(value) is not None, (kind, value)
        assert kind.problem((kind.low + kind.high) / 2) is None, kind
