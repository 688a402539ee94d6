"""One PTSN scale contract: scale.json is read by one reader with one set of rules,
and ŝ is used exactly as the sweep wrote it."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.store.artifacts import ArtifactError
from dali_cli.store.manifest import read_manifest
from dali_cli.store.scale_file import read_scale, write_scale


@pytest.mark.parametrize("bad", [float("inf"), float("nan"), 0.0, -1.0, True, "1.1", None])
def test_read_scale_refuses_what_is_not_a_positive_finite_number(tmp_path, bad):
    (tmp_path / "scale.json").write_text(json.dumps({"scale": bad}))
    with pytest.raises(ArtifactError, match="scale.json: field 'scale'"):
        read_scale(tmp_path)


def test_scale_round_trips_exactly_from_a_folder_or_the_file(tmp_path):
    found = 1.1994930481237717  # a secant step's value: more digits than any rounding keeps
    write_scale(tmp_path, {"scale": found, "E_est": [3.89, 1.62, 1.53]})
    assert read_scale(tmp_path).scale == found
    assert read_scale(tmp_path / "scale.json").scale == found


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


def test_scale_result_is_typed_and_pseudo_label_scales_about_its_pivot(tmp_path):
    """One scale contract: E_est, E_pred and the pivot (mount height) come typed from scale.json,
    and pseudo-label scales about the sweep's pivot, not a height it resolves another way."""
    import numpy as np

    from dali_cli.store.artifacts import write_frameset
    from stages.pseudo_label import pseudo_label

    document = {"scale": 1.25, "E_est": [3.9, 1.6, 1.5], "E_pred_at_scale": [3.8, 1.7, None],
                "mount_height_m": 1.9}  # fmt: skip
    (tmp_path / "ptsn").mkdir()
    write_scale(tmp_path / "ptsn", document)
    result = read_scale(tmp_path / "ptsn")
    assert result.scale == 1.25 and result.e_est == (3.9, 1.6, 1.5)
    assert result.e_pred == (3.8, 1.7, None) and result.pivot_m == 1.9
    assert result.record["mount_height_m"] == 1.9
    target = tmp_path / "target"
    target.mkdir()
    write_frameset(target, [("000", np.zeros((5, 4), np.float32))], sensor="kitti")
    (tmp_path / "model").mkdir()
    seen = []

    class Recorder:
        def predict(self, points_list, scale=1.0, mount_height_m=None):
            seen.append((scale, mount_height_m))
            return [(np.zeros((0, 7)), np.zeros(0, np.float32)) for _ in points_list]

    pseudo_label(
        tmp_path / "model", target, tmp_path / "pseudo", scale_from=tmp_path / "ptsn",
        progress=False, detector_loader=lambda _: Recorder(),
    )  # fmt: skip
    assert seen == [(1.25, 1.9)]  # the kitti profile's 1.73 m would scale about another point
    # ŝ is stored once in the output: its scale.json, the sweep's record exactly (no per-box
    # column, no copy in summary.json or the manifest's record), and self-train reads it there
    from stages.self_train import pseudo_label_scale

    stored = read_scale(tmp_path / "pseudo")
    assert stored.scale == 1.25 and stored.e_est == (3.9, 1.6, 1.5) and stored.pivot_m == 1.9
    assert stored.record["scale_source"] == str(tmp_path / "ptsn")
    assert "scale" not in json.loads((tmp_path / "pseudo" / "summary.json").read_text())
    assert "scale" not in read_manifest(tmp_path / "pseudo")["pseudo_label"]
    assert pseudo_label_scale(tmp_path / "pseudo") == 1.25


def test_self_train_reads_the_scale_of_earlier_pseudo_label_outputs(tmp_path):
    """Outputs of earlier versions carry ŝ as a per-box 'scale' column and no scale.json."""
    import numpy as np

    from dali_cli.runtime.errors import StageError
    from dali_cli.store.artifacts import BoxTable, write_boxes
    from stages.self_train import pseudo_label_scale

    boxes = np.tile([[5.0, 0.0, -1.0, 3.9, 1.6, 1.5, 0.0]], (3, 1))
    table = BoxTable.from_arrays(np.array(["000", "000", "001"]), boxes)
    (tmp_path / "old").mkdir()
    write_boxes(tmp_path / "old", table.with_columns(scale=np.full(3, 1.0 + 1e-12)))
    assert pseudo_label_scale(tmp_path / "old") == 1.0 + 1e-12
    (tmp_path / "mixed").mkdir()
    write_boxes(tmp_path / "mixed", table.with_columns(scale=np.array([1.0, 1.1, 1.0])))
    with pytest.raises(StageError, match="one positive 'scale'"):
        pseudo_label_scale(tmp_path / "mixed")
    (tmp_path / "none").mkdir()
    write_boxes(tmp_path / "none", table)
    with pytest.raises(StageError, match="no scale.json"):
        pseudo_label_scale(tmp_path / "none")
