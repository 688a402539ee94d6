"""`dali view`: the PNG is written, has the asked size, shows points and each source's boxes."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from dali_cli.cli import main
from dali_cli.reporting.view import BOX_COLOURS
from dali_cli.store.artifacts import BoxTable, write_boxes, write_frameset


def read_png(path):
    import matplotlib.image

    return matplotlib.image.imread(str(path))  # (H, W, 4) float in [0, 1]


def colour_pixels(image: np.ndarray, hex_colour: str, tolerance: float = 0.06) -> int:
    rgb = np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255
    return int((np.abs(image[:, :, :3] - rgb).max(axis=2) < tolerance).sum())


def make_frames(tmp_path):
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-30, 30, (4000, 2)), np.full(4000, -1.7), rng.uniform(0, 1, 4000)]
    car = np.c_[rng.uniform(8, 12, (500, 1)), rng.uniform(-1, 1, (500, 1)), rng.uniform(-1.7, -0.2, (500, 1)),
                np.full((500, 1), 0.4)]  # fmt: skip
    data = tmp_path / "data"
    data.mkdir()
    write_frameset(data, [("a", np.r_[ground, car]), ("b", ground[:10])], sensor="kitti")
    labels = BoxTable.from_arrays(
        ["a", "b"], [[10, 0, -0.95, 4, 2, 1.5, 0.0], [5, 5, -1, 4, 2, 1.5, 1.0]]
    )
    write_boxes(data, labels)
    predictions = tmp_path / "pred"
    predictions.mkdir()
    write_boxes(
        predictions,
        BoxTable.from_arrays(["a"], [[10.3, 0.2, -0.9, 4.2, 1.9, 1.5, 0.1]], score=[0.8]),
    )
    return data, predictions


def test_view_writes_png_with_both_box_sets(tmp_path):
    data, predictions = make_frames(tmp_path)
    out = tmp_path / "pictures" / "a.png"
    result = CliRunner().invoke(
        main, ["view", str(data), "--frame", "a", "--boxes", f"pred={predictions}", "--width-px", "800",
               "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    image = read_png(out)
    assert image.shape[1] == 800 and image.shape[0] > 300
    assert image[:, :, :3].std() > 0.05  # not blank
    assert colour_pixels(image, BOX_COLOURS[0]) > 50  # labels
    assert colour_pixels(image, BOX_COLOURS[1]) > 50  # predictions
    assert list(out.parent.iterdir()) == [out]  # no temporary file left


def test_view_side_view_is_taller_and_frame_index_works(tmp_path):
    data, _ = make_frames(tmp_path)
    plain, side = tmp_path / "plain.png", tmp_path / "side.png"
    runner = CliRunner()
    assert (
        runner.invoke(
            main, ["view", str(data), "--frame", "a", "--range-m", "20", "--out", str(plain)]
        ).exit_code
        == 0
    )
    result = runner.invoke(
        main, ["view", str(data), "--frame", "0", "--side", "--range-m", "20", "--out", str(side)]
    )
    assert result.exit_code == 0, result.output
    assert read_png(side).shape[0] > read_png(plain).shape[0] * 1.1
    # no own boxes: the label colour disappears
    bare = tmp_path / "bare.png"
    assert (
        runner.invoke(
            main, ["view", str(data), "--frame", "a", "--no-own-boxes", "--out", str(bare)]
        ).exit_code
        == 0
    )
    assert colour_pixels(read_png(bare), BOX_COLOURS[0]) < 5


def test_view_unknown_frame_is_an_error(tmp_path):
    data, _ = make_frames(tmp_path)
    out = tmp_path / "x.png"
    result = CliRunner().invoke(main, ["view", str(data), "--frame", "zzz", "--out", str(out)])
    assert result.exit_code == 1 and "zzz" in result.output and not out.exists()
