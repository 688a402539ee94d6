"""The ownership rule (docs/data-safety.md): a stage replaces only its own stage's artifact,
never writes inside another artifact, never deletes a file it did not write; locks follow no
link; special files are refused where a file is read; a diverging training stops."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from test_data_safety import build_boxes, make_target, quiet, snapshot

from dali_cli.detector.train import NonFiniteLossError, check_finite_loss
from dali_cli.importers.common import read_float_records
from dali_cli.store.atomic_dir import OutputLock
from dali_cli.store.manifest import content_hash, run_stage
from dali_cli.store.output_paths import (
    PREDICTIONS_MARK,
    OutputPathError,
    check_metrics_output,
    is_eval_predictions,
)
from dali_cli.store.regular_files import SpecialFileError


def stage(name: str, out: Path, value: float = 1.0, force: bool = False, dry_run: bool = False):
    return run_stage(
        name, out, {}, {"v": value}, build_boxes(value), force=force, dry_run=dry_run, echo=quiet
    )


def test_a_stage_replaces_only_its_own_stages_artifact_even_with_force(tmp_path):
    out = tmp_path / "a"
    stage("library", out)
    before = snapshot(out)
    for force in (False, True):
        with pytest.raises(OutputPathError, match="artifact of stage 'library'"):
            stage("synth", out, 2.0, force=force)
    assert snapshot(out) == before
    assert stage("library", out, 2.0).status == "ran"  # its own: replaced as before
    assert stage("library", out, 2.0).status == "skipped"


def test_a_stage_never_writes_an_artifact_inside_another(tmp_path):
    outer = tmp_path / "outer"
    stage("pretrain", outer)
    hashed = content_hash(outer)
    for name in ("pretrain", "synth"):
        with pytest.raises(OutputPathError, match="inside the dali artifact"):
            stage(name, outer / "data")
        with pytest.raises(OutputPathError, match="inside the dali artifact"):
            stage(name, outer / "deep" / "er")
    assert content_hash(outer) == hashed and sorted(p.name for p in outer.iterdir()) == [
        "boxes.parquet", "manifest.json", "payload.bin"
    ]  # fmt: skip


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("where", ["NOTES.txt", "sub/notes.md"])
def test_a_user_file_inside_an_artifact_stops_the_rerun_naming_it(tmp_path, force, where):
    out = tmp_path / "a"
    stage("synth", out)
    note = out / where
    note.parent.mkdir(exist_ok=True)
    note.write_text("mine")
    for dry_run in (True, False):
        with pytest.raises(OutputPathError, match=where.replace(".", r"\.")):
            stage("synth", out, 2.0, force=force, dry_run=dry_run)
    assert note.read_text() == "mine"
    note.unlink()
    assert stage("synth", out, 2.0, force=force).status == "ran"


def test_an_edited_file_of_the_stage_is_rebuilt_as_before(tmp_path):
    out = tmp_path / "a"
    stage("synth", out)
    (out / "payload.bin").write_bytes(b"edited")
    outcome = stage("synth", out)
    assert outcome.status == "ran" and "changed since" in outcome.reason
    assert (out / "payload.bin").read_bytes() != b"edited"


def test_a_lock_that_is_a_hard_link_is_refused_and_its_target_untouched(tmp_path):
    victim = tmp_path / "f"
    victim.write_text("2024\n")
    os.link(victim, tmp_path / ".a7.lock")
    with pytest.raises(OutputPathError, match="one link"):
        with OutputLock(tmp_path / "a7"):
            pass
    assert victim.read_text() == "2024\n"


def test_a_fifo_is_refused_where_a_file_is_read_and_never_opened(tmp_path):
    target = make_target(tmp_path / "t")
    fifo = target / "frames.zarr" / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(SpecialFileError, match="FIFO"):
        content_hash(target)  # every stage hashes its inputs before reading them
    scan = tmp_path / "000001.bin"
    os.mkfifo(scan)
    with pytest.raises(SpecialFileError, match="000001.bin"):
        read_float_records(scan, 4)


def test_eval_never_replaces_predictions_it_did_not_write(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    table = pa.table({"frame_id": ["a"], "score": [0.5]})
    pq.write_table(table, mine / "predictions.parquet")
    metrics = mine / "metrics.json"
    # a dali metrics file of an evaluation of those very predictions (--pred), written after them
    metrics.write_text('{"Car": {"bev": {}, "source": {"pred": "x"}}, "sizes": {}}')
    assert not is_eval_predictions(mine / "predictions.parquet", metrics)
    with pytest.raises(OutputPathError, match="predictions.parquet"):
        check_metrics_output(metrics, {}, beside=("predictions.parquet",))
    # marked as dali eval's, but the metrics beside it evaluated them (--pred): a user's copy of
    # another evaluation's predictions, which a later `eval --model --out` must not replace
    marked = table.replace_schema_metadata(dict([PREDICTIONS_MARK]))
    pq.write_table(marked, mine / "predictions.parquet")
    assert not is_eval_predictions(mine / "predictions.parquet", metrics)
    with pytest.raises(OutputPathError, match="predictions.parquet"):
        check_metrics_output(metrics, {}, beside=("predictions.parquet",))
    # beside the metrics of a model's evaluation, the marked file is that evaluation's
    metrics.write_text('{"Car": {"bev": {}, "source": {"model": "m"}}, "sizes": {}}')
    assert is_eval_predictions(mine / "predictions.parquet", metrics)
    check_metrics_output(metrics, {}, beside=("predictions.parquet",))


def test_a_non_finite_loss_stops_training_naming_the_step():
    terms = {"heatmap": torch.tensor(1.0), "box": torch.tensor(float("nan"))}
    check_finite_loss(torch.tensor(2.5), terms, 0)  # finite: nothing happens
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(NonFiniteLossError, match="training step 8"):
            check_finite_loss(torch.tensor(bad), terms, 7)
