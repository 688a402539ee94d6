"""The on-disk data contract: FrameSets (Zarr v3 point clouds) and box tables (Parquet).

FrameSet: `<dir>/frames.zarr`, a Zarr v3 group with arrays
    points    float32 (N_total, 4)   x, y, z, intensity in the sensor frame (metres)
    offsets   int64   (F + 1,)       frame i is points[offsets[i]:offsets[i + 1]]
    frame_ids string  (F,)
and attrs `sensor`, `frame_convention` ("sensor"), `count`.

Box table: `<dir>/boxes.parquet`, one row per box, columns frame_id, x, y, z, l, w, h, yaw
(float64, geometric centre, yaw CCW from +x), score (float32), label (string), num_points (int32)
plus optional extra columns.

Every reader validates what it reads and raises ArtifactError naming the path and the problem:
frame ids (dali_cli.store.frame_ids), column types and integer ranges, NaN/inf, and every chunk of points
it reads (present, and its CRC-32C checksum when the writer recorded one). docs/input-validation.md
lists what is checked where.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from dali_cli.store import raw_chunks
from dali_cli.store.artifact_errors import ArtifactError, TableValueError, read_json  # noqa: F401
from dali_cli.store.box_tables import (  # noqa: F401  (box tables: store/box_tables.py, re-exported)
    _BASE_TYPES,
    BOX_FIELDS,
    BOXES_NAME,
    BoxTable,
    _check_frame_ids,
    _is_plain_type,
    _typed_column,
    _value_problem,
    check_frames_known,
    int32_column,
    read_boxes,
    write_boxes,
)
from dali_cli.store.frame_ids import FrameIdError, check_name, first_bad_name

FRAMES_NAME = "frames.zarr"
DEFAULT_CHUNK_POINTS = 2**21  # ~2 M points (32 MiB uncompressed) per chunk


# ---------------------------------------------------------------------------------------------
# FrameSet


# Group attribute set by writers that store every chunk, even one equal to the fill value (Zarr
# skips those by default, so in older artifacts an absent chunk of zeros is legitimate).
COMPLETE_CHUNKS_ATTR = "complete_chunks"
STORE_EVERY_CHUNK = {"write_empty_chunks": True}


def read_whole_array(
    array, where: str, error: type[ArtifactError] = ArtifactError, complete: bool = True
) -> np.ndarray:
    """All of a small Zarr array, verified: with `complete` (the writer stored every chunk) every
    chunk must be present (Zarr reads a missing chunk as its fill value: zeros, or "" for
    strings), and every chunk must decode. `where` names the array in the message; raises `error`
    (an ArtifactError) otherwise."""
    missing = array.nchunks - array.nchunks_initialized if complete else 0
    if missing:
        raise error(
            f"{where}: {missing} of {array.nchunks} chunks missing; the artifact is damaged, "
            "rebuild it with the stage that wrote it"
        )
    try:
        return np.asarray(array[:])
    except Exception as problem:  # codecs raise RuntimeError, ValueError, ...
        raise error(f"{where}: cannot be read ({problem})") from None


class ChunkCache:
    """Arrays one reader used last, least recently used first out, bounded by their number
    (`max_chunks`: a FrameSet reader's decoded point chunks, `(chunk, 4)` float32 each) and/or
    their total bytes (`max_bytes`; an array larger than that is returned but not kept): bounded
    memory for random access."""

    def __init__(self, max_chunks: int | None = 2, max_bytes: int | None = None):
        from collections import OrderedDict

        self.max_chunks = None if max_chunks is None else max(1, int(max_chunks))
        self.max_bytes = None if max_bytes is None else max(0, int(max_bytes))
        self.bytes = 0
        self._chunks: OrderedDict = OrderedDict()

    def get(self, chunk) -> np.ndarray | None:
        data = self._chunks.get(chunk)
        if data is not None:
            self._chunks.move_to_end(chunk)
        return data

    def put(self, chunk, data: np.ndarray) -> np.ndarray:
        if self.max_bytes is not None and data.nbytes > self.max_bytes:
            return data
        old = self._chunks.pop(chunk, None)
        self.bytes += data.nbytes - (0 if old is None else old.nbytes)
        self._chunks[chunk] = data
        while (self.max_chunks is not None and len(self._chunks) > self.max_chunks) or (
            self.max_bytes is not None and self.bytes > self.max_bytes
        ):
            self.bytes -= self._chunks.popitem(last=False)[1].nbytes
        return data


class FrameSet:
    """Read access to a FrameSet directory. Reading one frame reads only the chunks it spans."""

    def __init__(self, directory: str | Path):
        import zarr

        self.directory = Path(directory)
        self.path = self.directory / FRAMES_NAME
        if not self.path.is_dir():
            raise ArtifactError(f"{self.path}: frame set not found (expected a Zarr group)")
        from dali_cli.store.regular_files import UnreadableFileError, check_zarr_files

        try:
            check_zarr_files(self.path)  # before zarr opens a file: none may block or be huge
        except UnreadableFileError as error:
            raise ArtifactError(str(error)) from None
        try:
            group = zarr.open_group(str(self.path), mode="r")
        except Exception as error:  # zarr raises several types for a broken group
            raise ArtifactError(f"{self.path}: cannot open Zarr group ({error})") from None
        arrays = {name: self._array(group, name) for name in ("points", "offsets", "frame_ids")}
        self._points = arrays["points"]
        if self._points.dtype != np.float32 or self._points.ndim != 2 or self._points.shape[1] != 4:
            raise ArtifactError(
                f"{self.path}/points: expected float32 (N, 4), got {self._points.dtype} {self._points.shape}"
            )
        complete = bool(group.attrs.get(COMPLETE_CHUNKS_ATTR, False))
        offsets = self._small(arrays["offsets"], "offsets", complete)
        if offsets.dtype != np.int64 or offsets.ndim != 1 or offsets.size < 1:
            raise ArtifactError(
                f"{self.path}/offsets: expected int64 (F + 1,), got {offsets.dtype} {offsets.shape}"
            )
        if offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ArtifactError(f"{self.path}/offsets: not monotone non-decreasing from 0")
        if offsets[-1] != self._points.shape[0]:
            raise ArtifactError(
                f"{self.path}/offsets: last offset {offsets[-1]} != number of points {self._points.shape[0]}"
            )
        # frame ids are never "" (the fill value), so every chunk was always stored
        ids = self._small(arrays["frame_ids"], "frame_ids", complete=True)
        frame_ids = [str(f) for f in ids.tolist()]
        if len(frame_ids) != offsets.size - 1:
            raise ArtifactError(
                f"{self.path}/frame_ids: {len(frame_ids)} ids for {offsets.size - 1} frames"
            )
        bad = first_bad_name(frame_ids)
        if bad is not None:
            raise ArtifactError(f"{self.path}/frame_ids, frame {bad[0]}: frame id {bad[1]}")
        if len(set(frame_ids)) != len(frame_ids):
            raise ArtifactError(f"{self.path}/frame_ids: duplicate frame ids")
        self.offsets = offsets
        self.frame_ids: list[str] = frame_ids
        self.attrs = dict(group.attrs)
        self.sensor: str = str(self.attrs.get("sensor", ""))
        self._index = {fid: i for i, fid in enumerate(frame_ids)}
        self._chunk = int(self._points.chunks[0])
        self._chunks_present: set[int] = set()  # chunk files already seen on disk
        # uncompressed chunks (what PPCG writes) are read straight from their files
        self._raw = raw_chunks.is_raw_layout(self.path / "points")

    def _array(self, group, name: str):
        """Array `name` of the group; ArtifactError when absent or its metadata is unreadable."""
        try:
            if name not in group:
                raise ArtifactError(f"{self.path}: missing array '{name}'")
            return group[name]
        except ArtifactError:
            raise
        except Exception as error:  # broken zarr.json: JSON, key or value errors
            raise ArtifactError(f"{self.path}/{name}: cannot open array ({error})") from None

    def _small(self, array, name: str, complete: bool) -> np.ndarray:
        """All of a small array (offsets, frame ids), verified (see `read_whole_array`)."""
        return read_whole_array(array, f"{self.path}/{name}", complete=complete)

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def num_points(self) -> int:
        return int(self.offsets[-1])

    def index_of(self, frame_id: str) -> int:
        try:
            return self._index[str(frame_id)]
        except KeyError:
            raise ArtifactError(f"{self.path}: no frame '{frame_id}'") from None

    def frame(self, index_or_id: int | str, cache: ChunkCache | None = None) -> np.ndarray:
        """Points of one frame, `(n, 4)` float32. Raises ArtifactError on NaN/inf values.
        With a `cache`, the whole chunks the frame spans are read and kept there (a frame of
        a chunk read before costs no read); without one only the frame's points are asked for."""
        index = self.index_of(index_or_id) if isinstance(index_or_id, str) else int(index_or_id)
        start, stop = int(self.offsets[index]), int(self.offsets[index + 1])
        if cache is None or stop <= start:
            return self._checked(self._read_points(start, stop), index)
        first, last = start // self._chunk, (stop - 1) // self._chunk
        parts = []
        for chunk in range(first, last + 1):
            lo = chunk * self._chunk
            data = cache.get(chunk)
            if data is None:
                data = cache.put(
                    chunk, self._read_points(lo, min(lo + self._chunk, self.num_points))
                )
            parts.append(data[max(start, lo) - lo : min(stop, lo + self._chunk) - lo])
        return self._checked(parts[0] if len(parts) == 1 else np.concatenate(parts), index)

    def _read_points(self, start: int, stop: int) -> np.ndarray:
        """points[start:stop] `(stop - start, 4)` float32, verified: every chunk it spans must exist
        (Zarr would return zeros for a missing one) and decode (its CRC-32C checksum, when
        written, must match). Raises ArtifactError naming the chunk and the frames in it."""
        if stop <= start:
            return np.zeros((0, 4), np.float32)
        for chunk in range(start // self._chunk, (stop - 1) // self._chunk + 1):
            if chunk not in self._chunks_present:  # one stat per chunk per FrameSet
                path = self._chunk_file(chunk)
                if path is not None and not path.is_file():
                    raise ArtifactError(self._damaged(chunk, "is missing"))
                self._chunks_present.add(chunk)
        if self._raw:
            return self._read_raw(start, stop)
        try:
            return np.asarray(self._points[start:stop])
        except Exception as error:  # codecs raise RuntimeError, ValueError, ...: find the chunk
            first, last = start // self._chunk, (stop - 1) // self._chunk
            for chunk in range(first, last + 1):
                lo = chunk * self._chunk
                try:
                    self._points[lo : min(lo + self._chunk, self.num_points)]
                except Exception as chunk_error:
                    raise ArtifactError(
                        self._damaged(chunk, f"cannot be decoded ({chunk_error})")
                    ) from None
            raise ArtifactError(
                f"{self.path}/points: cannot read points {start}..{stop} ({error})"
            ) from None

    def _read_raw(self, start: int, stop: int) -> np.ndarray:
        """points[start:stop] of an uncompressed array, straight from its chunk files (see
        dali_cli.store.raw_chunks); a range within one chunk that covers at least half of it comes back
        as a view of the chunk's buffer, without a copy (a small range is copied so that the
        chunk's memory is not held for it)."""
        first, last = start // self._chunk, (stop - 1) // self._chunk
        out = None
        for chunk in range(first, last + 1):
            try:
                data = raw_chunks.read_chunk(
                    raw_chunks.chunk_path(self.path / "points", chunk), self._chunk
                )
            except FileNotFoundError:
                raise ArtifactError(self._damaged(chunk, "is missing")) from None
            except (raw_chunks.RawChunkError, OSError) as error:
                raise ArtifactError(self._damaged(chunk, f"cannot be decoded ({error})")) from None
            lo = chunk * self._chunk
            a, b = max(start, lo) - lo, min(stop, lo + self._chunk) - lo
            if first == last:
                return data[a:b] if 2 * (b - a) >= self._chunk else data[a:b].copy()
            if out is None:
                out = np.empty((stop - start, 4), np.float32)
            out[lo + a - start : lo + b - start] = data[a:b]
        return out

    def _chunk_file(self, chunk: int) -> Path | None:
        """Where chunk `chunk` of the points array lives; None when the layout is not known."""
        encode = getattr(self._points.metadata, "encode_chunk_key", None)
        return None if encode is None else self.path / "points" / encode((chunk, 0))

    def _damaged(self, chunk: int, problem: str) -> str:
        """Message for a damaged chunk: the artifact, the chunk file and the frames in it."""
        lo, hi = chunk * self._chunk, min((chunk + 1) * self._chunk, self.num_points)
        first = int(np.searchsorted(self.offsets[1:], lo, side="right"))  # offsets[i+1] > lo
        last = int(np.searchsorted(self.offsets[:-1], hi, side="left")) - 1  # offsets[i] < hi
        frames = (
            f"frame '{self.frame_ids[first]}' lies"
            if first == last
            else f"frames '{self.frame_ids[first]}' to '{self.frame_ids[last]}' "
            f"({last - first + 1}) lie"
        )
        key = self._chunk_file(chunk)
        where = key.relative_to(self.path) if key is not None else f"chunk {chunk}"
        return (
            f"{self.path}: points chunk {where} {problem}; {frames} in it. "
            "The frame set is damaged: rebuild it with the stage that wrote it."
        )

    def _checked(self, points: np.ndarray, index: int) -> np.ndarray:
        if not np.isfinite(points).all():
            bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            raise ArtifactError(
                f"{self.path}: frame '{self.frame_ids[index]}' point {bad} has NaN/inf values"
            )
        return points

    def iter_frames(self, indices: Sequence[int] | None = None) -> Iterator[tuple[str, np.ndarray]]:
        """Yield (frame_id, points) in order, reading contiguous runs of frames block-wise."""
        indices = range(len(self)) if indices is None else indices
        chunk = self._chunk
        block_points = -(-max(DEFAULT_CHUNK_POINTS, chunk) // chunk) * chunk
        buffer_start, buffer = 0, np.zeros((0, 4), np.float32)
        for index in indices:
            start, stop = int(self.offsets[index]), int(self.offsets[index + 1])
            buffer_end = buffer_start + len(buffer)
            points = None
            if start < buffer_start or stop > buffer_end:
                # read whole chunks, each once: a frame that runs past the buffer keeps the
                # buffer's tail and reads only the chunks after it
                keep_tail = buffer_start <= start < buffer_end
                read_start = buffer_end if keep_tail else (start // chunk) * chunk
                read_stop = max(-(-stop // chunk) * chunk, read_start + block_points)
                fresh = self._read_points(read_start, min(read_stop, self.num_points))
                if keep_tail:  # only the frame that straddles the two blocks is copied
                    points = np.concatenate(
                        [buffer[start - buffer_start :], fresh[: stop - read_start]]
                    )
                buffer, buffer_start = fresh, read_start
            if points is None:
                points = buffer[start - buffer_start : stop - buffer_start]
            yield self.frame_ids[index], self._checked(points, index)

    def load_all(self) -> tuple[np.ndarray, np.ndarray]:
        """All points `(N_total, 4)` float32 and offsets `(F + 1,)` int64, in memory."""
        points = self._read_points(0, self.num_points)
        if not np.isfinite(points).all():
            bad_point = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            frame = int(np.searchsorted(self.offsets, bad_point, side="right") - 1)
            self._checked(points[self.offsets[frame] : self.offsets[frame + 1]], frame)
        return points, self.offsets.copy()


class FrameSetWriter:
    """Append frames one by one; points are flushed in whole chunks so memory stays bounded.

    Use as a context manager: `with FrameSetWriter(dir, sensor="kitti") as w: w.append(id, pts)`.
    The directory should be a stage's temporary output directory (see manifest.run_stage).
    """

    def __init__(
        self,
        directory: str | Path,
        sensor: str,
        attrs: dict | None = None,
        chunk_points: int = DEFAULT_CHUNK_POINTS,
        compress: bool = True,
    ):
        import zarr
        from zarr.codecs import Crc32cCodec, ZstdCodec

        self.path = Path(directory) / FRAMES_NAME
        self._group = zarr.open_group(str(self.path), mode="w", zarr_format=3)
        # compress=False: raw float32 chunks (LiDAR coordinates shrink only ~8% with zstd, which
        # costs more CPU than the rest of a fast stage); readers need no change. Every chunk ends
        # with a CRC-32C of its stored bytes, checked by Zarr on read (a flipped bit or a truncated
        # chunk is an error, not silently wrong points); about 3 ms per 32 MiB chunk.
        compressors = (ZstdCodec(level=0), Crc32cCodec()) if compress else (Crc32cCodec(),)
        # point chunks are never all zeros: skip zarr's costly "is this chunk empty?" scan
        # (about 3/4 of the CPU time of writing uncompressed chunks)
        self._points = self._group.create_array(
            "points",
            shape=(0, 4),
            chunks=(chunk_points, 4),
            dtype="float32",
            config={"write_empty_chunks": True},
            compressors=compressors,
        )
        self._chunk = chunk_points
        # uncompressed: frames are copied into one chunk buffer and each full chunk is written
        # straight to its file (dali_cli.store.raw_chunks: the same bytes Zarr writes, a third of
        # the time); compressed chunks go through Zarr
        self._raw = not compress
        self._parts: list[np.ndarray] = []  # raw: the next chunk's rows, as views of the frames
        self._buffered = 0
        self._pending: list[np.ndarray] = []
        self._pending_count = 0
        self._written = 0
        self._offsets = [0]
        self._frame_ids: list[str] = []
        self._seen: set[str] = set()  # duplicate check in O(1) (a list scan is O(F) per frame)
        self._attrs = {"sensor": sensor, "frame_convention": "sensor", **(attrs or {})}
        self._closed = False

    def append(self, frame_id: str, points: np.ndarray) -> None:
        """Add one frame; `points` is `(n, 4)` (x, y, z, intensity), cast to float32.

        The writer keeps `points` (not a copy) until the chunk it falls in is written: do not
        change the array after appending it."""
        frame_id = check_name(
            str(frame_id), f"{self.path}, frame {len(self._frame_ids)}"
        )  # FrameIdError (a ValueError) for an id that cannot name a file
        points = np.asarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] != 4:
            raise ValueError(f"frame '{frame_id}': points must be (n, 4), got {points.shape}")
        if not np.isfinite(points).all():
            raise ValueError(f"frame '{frame_id}': points contain NaN/inf")
        if frame_id in self._seen:
            raise FrameIdError(
                f"{self.path}, frame {len(self._frame_ids)}: frame id '{frame_id}' appended twice"
            )
        self._frame_ids.append(frame_id)
        self._seen.add(frame_id)
        self._offsets.append(self._offsets[-1] + len(points))
        if self._raw:
            self._buffer_points(points)
            return
        if len(points):
            self._pending.append(points)
            self._pending_count += len(points)
        if self._pending_count >= self._chunk:
            self._flush(final=False)

    def _buffer_points(self, points: np.ndarray) -> None:
        """Queue `points` (views, no copy: like the Zarr path, the writer keeps the appended
        arrays until their chunk is written) and write every chunk that fills up."""
        done = 0
        while done < len(points):
            take = min(len(points) - done, self._chunk - self._buffered)
            self._parts.append(points[done : done + take])
            self._buffered += take
            done += take
            if self._buffered == self._chunk:
                self._write_buffer()

    def _write_buffer(self) -> None:
        """Write the queued points as the next chunk (a partial last chunk is padded with the
        fill value 0, as Zarr stores it)."""
        if not self._buffered:
            return
        chunk = self._written // self._chunk
        path = raw_chunks.chunk_path(self.path / "points", chunk)
        raw_chunks.write_chunk_parts(path, self._parts, self._chunk)
        self._written += self._buffered
        self._parts, self._buffered = [], 0

    def _flush(self, final: bool) -> None:
        if self._raw:
            if final:
                self._write_buffer()
                if self._written:
                    self._points.resize((self._written, 4))  # metadata only: shape grows
            return
        if not self._pending:
            return
        data = np.concatenate(self._pending)
        take = len(data) if final else (len(data) // self._chunk) * self._chunk
        if take:
            self._points.resize((self._written + take, 4))
            self._points[self._written : self._written + take] = data[:take]
            self._written += take
        rest = data[take:]
        self._pending = [rest] if len(rest) else []
        self._pending_count = len(rest)

    def close(self) -> None:
        if self._closed:
            return
        self._flush(final=True)
        self._group.create_array(
            "offsets", data=np.asarray(self._offsets, dtype=np.int64), config=STORE_EVERY_CHUNK
        )
        # dtype=str is Zarr's variable-length UTF-8 string type (stable in the v3 spec)
        ids = self._group.create_array(
            "frame_ids", shape=(len(self._frame_ids),), dtype=str, config=STORE_EVERY_CHUNK
        )
        if self._frame_ids:
            ids[:] = np.asarray(self._frame_ids, dtype=object)
        self._group.attrs.update(
            {**self._attrs, "count": len(self._frame_ids), COMPLETE_CHUNKS_ATTR: True}
        )
        self._closed = True

    def __enter__(self) -> FrameSetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    @property
    def count(self) -> int:
        return len(self._frame_ids)

    @property
    def num_points(self) -> int:
        return self._offsets[-1]


def write_frameset(
    directory: str | Path,
    frames: Iterable[tuple[str, np.ndarray]],
    sensor: str,
    attrs: dict | None = None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> int:
    """Write (frame_id, points) pairs as a FrameSet; returns the number of frames."""
    with FrameSetWriter(directory, sensor, attrs, chunk_points) as writer:
        for frame_id, points in frames:
            writer.append(frame_id, points)
    return writer.count
