"""One PTSN scale contract (issue 23): scale.json is read by one reader with one set of rules,
and ŝ is used exactly as the sweep wrote it."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from dali_cli.artifacts import ArtifactError
from dali_cli.cli import main
from dali_cli.scale_file import read_scale, write_scale


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), 0.0, -1.0, True, "1.1", None])
def test_read_scale_refuses_what_is_not_a_positive_finite_number(tmp_path, bad):
    (tmp_path / "scale.json").write_text(json.dumps({"scale": bad}))
    with pytest.raises(ArtifactError, match="scale.json: field 'scale'"):
        read_scale(tmp_path)


def test_scale_round_trips_exactly_from_a_folder_or_the_file(tmp_path):
    found = 1.1994930481237717  # a secant step's value: more digits than any rounding keeps
    write_scale(tmp_path, {"scale": found, "E_est": [3.89, 1.62, 1.53]})
    assert read_scale(tmp_path)[0] == found
    assert read_scale(tmp_path / "scale.json")[0] == found


def test_eval_refuses_an_infinite_scale_it_used_to_accept(tmp_path):
    (tmp_path / "ptsn").mkdir()
    (tmp_path / "ptsn" / "scale.json").write_text('{"scale": Infinity}')
    (tmp_path / "model").mkdir()
    (tmp_path / "data").mkdir()
    result = CliRunner().invoke(
        main,
        ["eval", "--model", str(tmp_path / "model"), "--data", str(tmp_path / "data"),
         "--scale-from", str(tmp_path / "ptsn")],
    )  # fmt: skip
    assert result.exit_code == 1 and "scale.json: field 'scale'" in result.output
