"""Bad files a user's shell can hand dali, shared by the fuzz tests (tests/test_fuzz_reads.py)
and the hostile-input probe (bench/hostile_inputs.py): `make_bad` puts one kind at a path,
`box_table_with` writes a frame set's box table with columns set to hostile values."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

DEVICES = {"dev-zero": "/dev/zero", "dev-null": "/dev/null", "dev-urandom": "/dev/urandom"}
BAD_KINDS = ("fifo", "directory", "dangling", *DEVICES, "sparse-4g", "deep-json", "random")


def make_bad(path: Path, kind: str) -> None:
    """Put a bad file of `kind` (one of BAD_KINDS) at `path`, replacing what is there: a FIFO, a
    directory, a dangling link, a link to a device, a 4 GiB sparse file, JSON nested 200,000
    deep, or 4 KiB of random bytes."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):  # a file, a link, a FIFO
        path.unlink()
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "dangling":
        path.symlink_to(path.parent / "nothing-here")
    elif kind in DEVICES:
        path.symlink_to(DEVICES[kind])
    elif kind == "sparse-4g":
        with open(path, "wb") as handle:
            handle.truncate(4 << 30)
    elif kind == "deep-json":
        path.write_text("[" * 200_000 + "]" * 200_000)
    elif kind == "random":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    else:
        raise ValueError(f"unknown bad-file kind {kind!r}")


def box_table_with(frames: Path, path: Path, **columns) -> Path:
    """`frames`' box table with each named column set to one value for every row (a new float32
    column where there is none), written at `path`."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(frames / "boxes.parquet")
    for name, value in columns.items():
        index = table.schema.get_field_index(name)
        kind = table.schema.field(name).type if index >= 0 else pa.float32()
        column = pa.array([value] * table.num_rows, kind)
        table = (
            table.set_column(index, name, column)
            if index >= 0
            else table.append_column(name, column)
        )
    pq.write_table(table, path)
    return path
