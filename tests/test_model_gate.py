"""The gate `make models` runs before it replaces a shipped model (bench/model_gate.py): refused
where AP_3D@0.7 falls beyond the paired bootstrap's noise on any set, and shown on the card."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def load(name: str):
    """bench/<name>.py as a module (bench's scripts import their siblings by name)."""
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gate_module = load("model_gate")
card_module = load("model_card")


def bootstrap(delta: float, interval: tuple[float, float], frames: int = 50) -> dict:
    """`dali compare`'s bootstrap block: the shipped model the reference, one candidate row."""
    cell = lambda ap: {"ap": ap, "std": 1.0}  # noqa: E731
    return {
        "reference": "shipped", "frames": frames, "samples": 1000, "seed": 0,
        "rows": {
            "shipped": {"3d moderate": cell(60.0), "bev moderate": cell(80.0)},
            "candidate": {
                "3d moderate": {**cell(60.0 + delta), "delta": delta,
                                "delta_interval_95": list(interval)},
                "bev moderate": {**cell(80.0), "delta": 0.0, "delta_interval_95": [-1.0, 1.0]},
            },
        },
    }  # fmt: skip


def test_a_fall_whose_interval_lies_below_zero_is_refused():
    line = gate_module.set_verdict(bootstrap(-11.6, (-19.4, -4.5)))
    assert line["falls"] and line["3d moderate"]["candidate"] == pytest.approx(48.4)
    verdict = gate_module.gate({"drive": line})
    assert verdict["refused"] and verdict["falls_on"] == ["drive"]


def test_a_fall_within_the_noise_or_a_gain_passes():
    within = gate_module.set_verdict(bootstrap(-2.8, (-8.2, 0.9)))
    gain = gate_module.set_verdict(bootstrap(3.0, (0.5, 6.0)))
    assert not within["falls"] and not gain["falls"]
    assert not gate_module.gate({"drive": within, "objects": gain})["refused"]


def test_one_set_falling_refuses_the_model_whatever_the_others():
    sets = {
        "drive": gate_module.set_verdict(bootstrap(5.0, (1.0, 9.0))),
        "objects_other": gate_module.set_verdict(bootstrap(-9.3, (-22.0, -0.4), frames=24)),
    }
    assert gate_module.gate(sets)["falls_on"] == ["objects_other"]


def test_the_card_shows_the_comparison_and_its_verdict():
    verdict = gate_module.gate({"drive": gate_module.set_verdict(bootstrap(-11.6, (-19.4, -4.5)))})
    text = "\n".join(card_module.gate_lines(json.loads(json.dumps(verdict))))
    assert "## Against the model it replaces" in text and "refused" in text
    assert "| drive | 50 | 60.0 | 48.4 | -11.6 [-19.4, -4.5] |" in text
    assert card_module.gate_lines(None) == []


def test_the_gate_refuses_a_directory_that_is_not_a_model(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        gate_module.main(["--shipped", str(tmp_path), "--candidate", str(tmp_path),
                          "--set", f"drive={tmp_path}", "--work", str(tmp_path / "w"),
                          "--out", str(tmp_path / "gate.json")])  # fmt: skip
    assert stop.value.code == 2 and "is not a model" in capsys.readouterr().err
    assert not (tmp_path / "gate.json").exists()


def test_the_gate_evaluates_again_where_an_earlier_run_left_predictions(tmp_path, monkeypatch):
    """A second round replaces the model in place: predictions left in the work directory by an
    earlier gate must not stand in for the new model's (dali eval decides, by its manifest)."""
    work = tmp_path / "work"
    for row in ("shipped", "candidate"):
        (work / "drive" / row).mkdir(parents=True)
        (work / "drive" / row / "predictions.parquet").write_bytes(b"stale")
    calls = []

    def fake_dali(*args, log):
        calls.append(args[0])
        if args[0] == "compare":
            out = Path(args[args.index("--out") + 1])
            out.write_text(json.dumps({"bootstrap": bootstrap(1.0, (-2.0, 4.0))}))

    monkeypatch.setattr(gate_module, "dali", fake_dali)
    models = {
        "shipped": (tmp_path / "a", tmp_path / "a"),
        "candidate": (tmp_path / "b", tmp_path / "b"),
    }
    gate_module.compare_on("drive", str(tmp_path), str(tmp_path), models, work)
    assert calls == ["eval", "eval", "compare"]
