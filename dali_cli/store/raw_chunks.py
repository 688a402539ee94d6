"""Direct file I/O of uncompressed Zarr v3 point chunks, without Zarr's asynchronous machinery.

The layout is the one `FrameSetWriter(compress=False)` asks Zarr for: codecs `bytes` (little
endian) then `crc32c`, the default chunk key encoding (`c/<row chunk>/0`), chunks of `(C, 4)`
float32. Such a chunk file is exactly `C * 16` bytes of little-endian float32 (the last chunk
padded with the fill value 0) followed by the CRC-32C of those bytes (4 bytes, little endian), so
it can be read into one buffer and checked in place, and written from the frame buffer with no
re-encoding. Reading this way costs a quarter of what Zarr's path costs for the same bytes
(bench/results/ppcg.json); the files are byte-for-byte those Zarr writes (tests/test_raw_chunks.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

_CHECKSUM_BYTES = 4


class RawChunkError(ValueError):
    """A chunk file that cannot be what the layout promises (size, checksum); says which."""


def is_raw_layout(array_dir: str | Path) -> bool:
    """Whether the Zarr v3 array at `array_dir` stores `(C, 4)` float32 chunks as raw bytes + CRC."""
    from dali_cli.runtime.errors import StageError
    from dali_cli.store.regular_files import read_json_file

    try:
        meta = read_json_file(Path(array_dir) / "zarr.json", "Zarr metadata")
        codecs = meta["codecs"]
        chunk_shape = meta["chunk_grid"]["configuration"]["chunk_shape"]
        encoding = meta["chunk_key_encoding"]
    except (OSError, ValueError, KeyError, TypeError, StageError):
        return False
    return (
        meta.get("zarr_format") == 3
        and meta.get("data_type") == "float32"
        and meta.get("fill_value") in (0, 0.0)
        and not meta.get("storage_transformers")
        and len(chunk_shape) == 2
        and chunk_shape[1] == 4
        and encoding.get("name") == "default"
        and encoding.get("configuration", {}).get("separator", "/") == "/"
        and len(codecs) == 2
        and codecs[0].get("name") == "bytes"
        and codecs[0].get("configuration", {}).get("endian") == "little"
        and codecs[1].get("name") == "crc32c"
    )


def chunk_path(array_dir: str | Path, chunk: int) -> Path:
    """File of row chunk `chunk` of a 2-D array with the default chunk key encoding."""
    return Path(array_dir) / "c" / str(int(chunk)) / "0"


def read_chunk(path: str | Path, chunk_points: int) -> np.ndarray:
    """Points `(chunk_points, 4)` float32 of one chunk file, checksum verified.

    Raises FileNotFoundError when absent and RawChunkError when the size or checksum is wrong.
    The array is a writable view of a buffer of its own (no other reader shares it).
    """
    import stat

    import google_crc32c

    expected = int(chunk_points) * 16 + _CHECKSUM_BYTES
    if not stat.S_ISREG(os.stat(path).st_mode):  # FileNotFoundError when absent
        raise RawChunkError("not a regular file (a FIFO or device would block the read)")
    buffer = np.empty(expected, np.uint8)
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    with os.fdopen(descriptor, "rb", buffering=0) as handle:
        size = os.fstat(handle.fileno()).st_size
        if not stat.S_ISREG(os.fstat(handle.fileno()).st_mode) or size != expected:
            raise RawChunkError(f"{size} bytes, expected {expected}")
        view, read = memoryview(buffer), 0
        while read < expected:  # readinto may return fewer bytes than asked
            count = handle.readinto(view[read:])
            if not count:
                raise RawChunkError(f"ended after {read} of {expected} bytes")
            read += count
    payload = buffer[:-_CHECKSUM_BYTES]
    stored = int.from_bytes(buffer[-_CHECKSUM_BYTES:].tobytes(), "little")
    if google_crc32c.value(payload) != stored:
        raise RawChunkError("checksum mismatch (the stored bytes changed after writing)")
    return payload.view("<f4").reshape(-1, 4)


def write_chunk(path: str | Path, points: np.ndarray) -> None:
    """Write one full chunk `(C, 4)` float32 (C-contiguous) and its CRC-32C to `path`."""
    write_chunk_parts(path, [points], len(points))


def write_chunk_parts(path: str | Path, parts: list[np.ndarray], chunk_points: int) -> None:
    """Write the rows of `parts` (each `(n_i, 4)` float32, sum n_i <= chunk_points) one after the
    other as one chunk of `chunk_points` rows, padded with the fill value 0, and its CRC-32C:
    the file `write_chunk` writes for their concatenation, without building it."""
    import google_crc32c

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    crc, rows = 0, 0
    with open(path, "wb") as handle:
        for part in parts:
            part = np.ascontiguousarray(part, dtype="<f4")
            payload = part.reshape(-1).view(np.uint8)  # google_crc32c takes arrays
            handle.write(payload)
            crc = google_crc32c.extend(crc, payload)
            rows += len(part)
        if rows > chunk_points:
            raise ValueError(f"{path}: {rows} rows for a chunk of {chunk_points}")
        if rows < chunk_points:
            padding = np.zeros((chunk_points - rows) * 16, np.uint8)
            handle.write(padding)
            crc = google_crc32c.extend(crc, padding)
        handle.write(int(crc).to_bytes(_CHECKSUM_BYTES, "little"))
