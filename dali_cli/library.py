"""The 3D model library: car meshes (procedural or CAD) and point models, and its on-disk artifact.

Meshes are normalized to the unit box centered at the origin (l along +x, w along +y, up +z) and
keep their native l/w/h. Point models are labelled source instances with enough points, stored in
box-normalized coordinates (x/l, y/w, z/h in the box frame, so they lie in [-0.5, 0.5]^3) with
their viewing angle.

Library directory:
    library.zarr/meshes/{vertices (V,3) f32, faces (F,3) i32, vertex_offsets, face_offsets (M+1,) i64}
    library.zarr/points/{points (P,4) f32 x, y, z normalized + intensity, offsets (K+1,) i64}
    meshes.parquet        model_id, kind, source, native_l, native_w, native_h, num_vertices, num_faces
    point_models.parquet  model_id, frame_id, sensor, view_angle_rad, l, w, h, yaw, range_m, num_points
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dali_cli.geometry import point_box_indices, wrap_angle
from dali_cli.procedural import KINDS, generate_car_mesh
from dali_cli.store.artifacts import (
    COMPLETE_CHUNKS_ATTR,
    STORE_EVERY_CHUNK,
    ArtifactError,
    FrameSet,
    read_boxes,
    read_whole_array,
)

LIBRARY_ZARR = "library.zarr"
MESHES_INDEX = "meshes.parquet"
POINTS_INDEX = "point_models.parquet"
CAD_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
_AXES = {"x": 0, "y": 1, "z": 2}


class LibraryError(ArtifactError):
    """A bad model file or library artifact; the message names the file and the problem."""


# ---------------------------------------------------------------------------------------------
# Mesh models


@dataclass
class CarModel:
    """A car mesh normalized to the unit box.

    vertices: `(V, 3)` float32 in [-0.5, 0.5]^3 (l along +x, w along +y, up +z, centered);
    faces: `(F, 3)` int32; native_lwh: `(3,)` float64 size in metres (or the CAD file's units).
    """

    model_id: str
    vertices: np.ndarray
    faces: np.ndarray
    native_lwh: np.ndarray
    kind: str = ""
    source: str = ""

    @property
    def num_triangles(self) -> int:
        return len(self.faces)

    def bvh(self):
        """The model's Embree BVH (built once per process, cached by content)."""
        from dali_cli.raycast import get_bvh

        return get_bvh(self.vertices, self.faces)


def normalize_mesh(
    vertices: np.ndarray, faces: np.ndarray, name: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Center a mesh and scale it to the unit box: (vertices (V,3) f32, faces (F,3) i32, native_lwh (3,)).

    Drops unreferenced vertices and degenerate (zero-area) faces; raises LibraryError naming
    `name` when nothing usable is left or an extent is zero.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise LibraryError(f"{name}: mesh has no vertices")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise LibraryError(f"{name}: mesh has no triangle faces")
    if not np.isfinite(vertices).all():
        raise LibraryError(f"{name}: mesh has NaN/inf vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise LibraryError(f"{name}: face indices out of range")
    corners = vertices[faces]  # (F, 3, 3)
    area = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    faces = faces[area > 1e-12 * max(1.0, float(np.ptp(vertices, axis=0).max()) ** 2)]
    if len(faces) == 0:
        raise LibraryError(f"{name}: every face is degenerate (zero area)")
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    vertices = vertices[used]
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    extent = high - low
    if np.any(extent <= 1e-9 * max(1.0, extent.max())):
        raise LibraryError(
            f"{name}: mesh is flat (extents {extent.round(6).tolist()}); not a 3D model"
        )
    unit = (vertices - 0.5 * (low + high)) / extent
    return unit.astype(np.float32), faces.astype(np.int32), extent.astype(np.float64)


def procedural_car(
    seed: int | Sequence[int], kind: str | None = None, lod: int = 8000, model_id: str | None = None
) -> CarModel:
    """A procedural car (see dali_cli.procedural) as a CarModel; deterministic per (seed, kind, lod)."""
    vertices, faces, shape = generate_car_mesh(seed, kind=kind, lod=lod)
    seed_text = "-".join(str(s) for s in np.atleast_1d(seed).tolist())
    name = model_id or f"proc-{seed_text}-{shape.kind}"
    unit, faces, native = normalize_mesh(vertices, faces, name)
    return CarModel(name, unit, faces, native, kind=shape.kind, source="procedural")


def procedural_library(
    count: int, seed: int, lod: int = 8000, kinds: Sequence[str] | None = None
) -> list[CarModel]:
    """`count` procedural cars; model i uses seed (seed, i), kinds cycle through `kinds` if given."""
    if kinds is not None:
        unknown = sorted(set(kinds) - set(KINDS))
        if unknown:
            raise ValueError(f"unknown car kind '{unknown[0]}' (known: {', '.join(KINDS)})")
    models = []
    for index in range(int(count)):
        kind = None if not kinds else kinds[index % len(kinds)]
        models.append(
            procedural_car(
                [int(seed), index], kind=kind, lod=lod, model_id=f"proc-s{seed}-{index:05d}"
            )
        )
    return models


def axis_rotation(up: str = "z", forward: str = "x") -> np.ndarray:
    """`(3, 3)` rotation taking a file's axes (`up`, `forward` like "y", "-z") to x forward, z up."""

    def vector(name: str, what: str) -> np.ndarray:
        text = name.strip().lower()
        sign = -1.0 if text.startswith("-") else 1.0
        axis = text.lstrip("+-")
        if axis not in _AXES:
            raise LibraryError(f"--{what}: expected one of x, y, z, -x, -y, -z, got '{name}'")
        result = np.zeros(3)
        result[_AXES[axis]] = sign
        return result

    up_vector, forward_vector = vector(up, "up"), vector(forward, "forward")
    if abs(float(up_vector @ forward_vector)) > 0.5:
        raise LibraryError(f"--up {up} and --forward {forward} must be different axes")
    left = np.cross(up_vector, forward_vector)
    return np.stack([forward_vector, left, up_vector])  # rows: new x, y, z in file coordinates


def proportions_problem(native_lwh: np.ndarray, up: str = "z", forward: str = "x") -> str | None:
    """Why a car model read with axes `up`, `forward` looks mis-oriented, or None when it is fine.

    native_lwh: `(3,)` l, w, h extents (file units) after the axis mapping. Cars are longer than
    wide and wider than high (l > w > h); otherwise the message gives the extents and the
    `--forward`/`--up` that would make them so: the file's longest axis forward, its shortest up.
    Extents cannot tell front from back or up from down, so an axis that keeps its role keeps the
    sign the user gave, and a new one is positive.
    """
    lwh = np.asarray(native_lwh, np.float64)
    if lwh[0] > lwh[1] > lwh[2]:
        return None
    rotation = axis_rotation(up, forward)  # rows: x (forward), y (left), z (up) in file axes
    file_axis = np.argmax(np.abs(rotation), axis=1)  # (3,) file axis of l, w, h
    file_extent = np.zeros(3)
    file_extent[file_axis] = lwh
    names = "xyz"
    given = {"forward": forward.strip().lower(), "up": up.strip().lower()}

    def flag(role: str, axis: int) -> str:
        keeps_role = given[role].lstrip("+-") == names[axis]
        return given[role].lstrip("+") if keeps_role else names[axis]

    order = np.argsort(-file_extent, kind="stable")  # file axes, longest first
    if not file_extent[order[0]] > file_extent[order[1]] > file_extent[order[2]]:
        suggestion = "no axis mapping does, two extents are equal, so"
    else:
        suggestion = f"--forward {flag('forward', order[0])} --up {flag('up', order[2])} would"
    return (
        f"extents l {lwh[0]:.3g}, w {lwh[1]:.3g}, h {lwh[2]:.3g} with --forward {forward} "
        f"--up {up} contradict a car (longer than wide, wider than high); {suggestion} "
        "give l > w > h (check the signs: extents cannot tell front from back or up from down)"
    )


def load_cad_file(path: str | Path, up: str = "z", forward: str = "x") -> CarModel:
    """Load one OBJ/PLY/STL/GLB/GLTF/OFF mesh (materials and textures ignored) as a CarModel."""
    import trimesh

    path = Path(path)
    rotation = axis_rotation(up, forward)
    try:
        kwargs = {"skip_materials": True} if path.suffix.lower() == ".obj" else {}
        loaded = trimesh.load(str(path), force="mesh", process=False, **kwargs)
    except Exception as error:  # trimesh raises many types for broken files
        raise LibraryError(f"{path}: cannot load mesh ({type(error).__name__}: {error})") from None
    vertices = getattr(loaded, "vertices", None)
    faces = getattr(loaded, "faces", None)
    if vertices is None or faces is None or len(vertices) == 0 or len(faces) == 0:
        raise LibraryError(f"{path}: no triangle geometry in the file (empty mesh)")
    vertices = np.asarray(vertices, np.float64) @ rotation.T
    unit, faces, native = normalize_mesh(vertices, np.asarray(faces), str(path))
    return CarModel(path.stem, unit, faces, native, kind="cad", source=str(path.name))


def load_cad_directory(
    directory: str | Path,
    up: str = "z",
    forward: str = "x",
    length_range: tuple[float, float] | None = None,
    skip_bad: bool = False,
    keep_odd_proportions: bool = False,
) -> tuple[list[CarModel], list[str]]:
    """Every CAD file under `directory` (recursively), sorted by path.

    length_range: keep models whose native length lies in [lo, hi] (file units; the paper kept
    2-8 m). skip_bad: skip unreadable/degenerate files instead of raising. A model that is not
    longer than wide and wider than high (`proportions_problem`: probably other axes) is bad too,
    unless keep_odd_proportions. Returns (models, skipped messages). Model ids are the paths
    relative to `directory` without suffix.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise LibraryError(f"{directory}: CAD directory not found")
    files = sorted(
        p for p in directory.rglob("*") if p.is_file() and p.suffix.lower() in CAD_SUFFIXES
    )
    if not files:
        raise LibraryError(f"{directory}: no mesh files ({', '.join(CAD_SUFFIXES)})")
    models, skipped = [], []
    for file in files:
        try:
            model = load_cad_file(file, up=up, forward=forward)
            problem = proportions_problem(model.native_lwh, up, forward)
            if problem and not keep_odd_proportions:
                raise LibraryError(
                    f"{file}: {problem}; --skip-bad skips such files, --force keeps them"
                )
        except LibraryError as error:
            if not skip_bad:
                raise
            skipped.append(error.message)
            continue
        model.model_id = file.relative_to(directory).with_suffix("").as_posix()
        if (
            length_range is not None
            and not length_range[0] <= model.native_lwh[0] <= length_range[1]
        ):
            skipped.append(f"{file}: length {model.native_lwh[0]:.2f} outside {length_range}")
            continue
        models.append(model)
    if not models:
        raise LibraryError(f"{directory}: no usable models ({len(skipped)} skipped: {skipped[:3]})")
    return models, skipped


# ---------------------------------------------------------------------------------------------
# Point models


@dataclass
class PointModels:
    """Point models of labelled instances, stored column-wise.

    points: `(P, 4)` float32 x, y, z in box-normalized coordinates ([-0.5, 0.5] in the box frame:
    x along l, y along w, z up) and intensity; offsets: `(K + 1,)` int64, model k is
    points[offsets[k]:offsets[k+1]]. view_angle_rad: `(K,)` azimuth of the sensor as seen from
    the box, in the box frame (atan2 of the box-frame sensor position), in [-pi, pi).
    lwh: `(K, 3)` the instance's box size; yaw, range_m: `(K,)`; model_id, frame_id, sensor:
    `(K,)` str.
    """

    points: np.ndarray
    offsets: np.ndarray
    view_angle_rad: np.ndarray
    lwh: np.ndarray
    yaw: np.ndarray
    range_m: np.ndarray
    model_id: np.ndarray
    frame_id: np.ndarray
    sensor: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def num_points(self) -> np.ndarray:
        return np.diff(self.offsets).astype(np.int32)

    def model_points(self, index: int) -> np.ndarray:
        """`(M, 4)` float32 normalized points (+ intensity) of model `index`."""
        return self.points[self.offsets[index] : self.offsets[index + 1]]

    @classmethod
    def empty(cls) -> PointModels:
        return cls(
            points=np.zeros((0, 4), np.float32),
            offsets=np.zeros(1, np.int64),
            view_angle_rad=np.zeros(0),
            lwh=np.zeros((0, 3)),
            yaw=np.zeros(0),
            range_m=np.zeros(0),
            model_id=np.zeros(0, dtype=object),
            frame_id=np.zeros(0, dtype=object),
            sensor=np.zeros(0, dtype=object),
        )

    @staticmethod
    def concat(parts: Sequence[PointModels]) -> PointModels:
        parts = [p for p in parts if len(p)]
        if not parts:
            return PointModels.empty()
        sizes = np.concatenate([np.diff(p.offsets) for p in parts])
        return PointModels(
            points=np.concatenate([p.points for p in parts]).astype(np.float32),
            offsets=np.r_[0, np.cumsum(sizes)].astype(np.int64),
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in (
                    "view_angle_rad",
                    "lwh",
                    "yaw",
                    "range_m",
                    "model_id",
                    "frame_id",
                    "sensor",
                )
            },
        )


def _to_box_frame(xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Points `(M, 3)` into the frames of per-point boxes `(M, 7)` → `(M, 3)` (metres, unscaled)."""
    offset = np.asarray(xyz, np.float64) - boxes[:, :3]
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    return np.stack(
        [
            cos * offset[:, 0] + sin * offset[:, 1],
            -sin * offset[:, 0] + cos * offset[:, 1],
            offset[:, 2],
        ],
        axis=1,
    )


def point_models_from_frame(
    points: np.ndarray,
    boxes: np.ndarray,
    frame_id: str,
    sensor: str = "",
    min_points: int = 300,
    origin: np.ndarray | None = None,
) -> PointModels:
    """Point models of one labelled frame: boxes `(N, 7)` holding >= `min_points` of `points` `(n, 4)`.

    Coordinates are box-normalized (local / (l, w, h)); the viewing angle is the azimuth of the
    sensor `origin` (default 0) seen from the box, in the box frame.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    points = np.asarray(points, np.float32)
    if len(boxes) == 0 or len(points) == 0:
        return PointModels.empty()
    owner = point_box_indices(points, boxes)
    counts = np.bincount(owner[owner >= 0], minlength=len(boxes))
    keep = np.flatnonzero(counts >= int(min_points))
    if len(keep) == 0:
        return PointModels.empty()
    selected = np.flatnonzero(np.isin(owner, keep))
    selected = selected[np.argsort(owner[selected], kind="stable")]  # grouped by box, kept order
    box_of_point = boxes[owner[selected]]  # (P, 7)
    local = _to_box_frame(points[selected, :3], box_of_point) / box_of_point[:, 3:6]
    normalized = np.concatenate([local, points[selected, 3:4]], axis=1).astype(np.float32)
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    kept = boxes[keep]
    sensor_local = _to_box_frame(np.broadcast_to(origin, (len(kept), 3)), kept)
    return PointModels(
        points=normalized,
        offsets=np.r_[0, np.cumsum(counts[keep])].astype(np.int64),
        view_angle_rad=wrap_angle(np.arctan2(sensor_local[:, 1], sensor_local[:, 0])),
        lwh=kept[:, 3:6].copy(),
        yaw=kept[:, 6].copy(),
        range_m=np.linalg.norm(kept[:, :2] - origin[:2], axis=1),
        model_id=np.array([f"{frame_id}#{k}" for k in keep], dtype=object),
        frame_id=np.full(len(keep), str(frame_id), dtype=object),
        sensor=np.full(len(keep), str(sensor), dtype=object),
    )


def point_models_from_frameset(
    data_dir: str | Path, min_points: int = 300, label: str | None = "Car", progress: bool = True
) -> PointModels:
    """Point models of every labelled instance of a FrameSet + boxes.parquet directory."""
    from tqdm import tqdm

    frames = FrameSet(data_dir)
    table = read_boxes(data_dir)
    if label is not None and len(table):
        table = table.select(np.asarray(table["label"]).astype(str) == label)
    by_frame = table.rows_by_frame()
    indices = [i for i, fid in enumerate(frames.frame_ids) if fid in by_frame]
    parts = []
    for frame_id, points in tqdm(
        frames.iter_frames(indices), total=len(indices), desc="point models", disable=not progress
    ):
        rows = by_frame[frame_id]
        parts.append(
            point_models_from_frame(points, table.boxes[rows], frame_id, frames.sensor, min_points)
        )
    return PointModels.concat(parts)


# ---------------------------------------------------------------------------------------------
# The artifact


@dataclass
class ModelLibrary:
    """Meshes and point models read from a library directory."""

    meshes: list[CarModel] = field(default_factory=list)
    point_models: PointModels = field(default_factory=PointModels.empty)

    @property
    def mesh_lwh(self) -> np.ndarray:
        """`(M, 3)` native l, w, h of the meshes."""
        return np.array([m.native_lwh for m in self.meshes], np.float64).reshape(-1, 3)

    @property
    def mesh_ids(self) -> list[str]:
        return [m.model_id for m in self.meshes]


def write_library(
    directory: str | Path,
    meshes: Sequence[CarModel],
    point_models: PointModels | None = None,
) -> dict:
    """Write a library artifact into `directory` (a stage's temp dir); returns counts."""
    directory = Path(directory)
    point_models = point_models if point_models is not None else PointModels.empty()
    ids = [m.model_id for m in meshes]
    if len(set(ids)) != len(ids):
        duplicate = next(i for i in ids if ids.count(i) > 1)
        raise LibraryError(f"{directory}: duplicate mesh model id '{duplicate}'")
    _write_library_arrays(directory / LIBRARY_ZARR, meshes, point_models)
    vertex_counts = [len(m.vertices) for m in meshes]
    face_counts = [len(m.faces) for m in meshes]
    _write_mesh_index(directory / MESHES_INDEX, meshes, ids, vertex_counts, face_counts)
    _write_point_index(directory / POINTS_INDEX, point_models)
    return {
        "meshes": len(meshes),
        "mesh_triangles": int(sum(face_counts)),
        "point_models": len(point_models),
        "model_points": int(point_models.offsets[-1]),
    }


def _write_library_arrays(path: Path, meshes: Sequence[CarModel], point_models: PointModels):
    """library.zarr: meshes (vertices, faces, offsets) and point models (points, offsets)."""
    import zarr

    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    group = root.create_group("meshes")
    vertex_counts = [len(m.vertices) for m in meshes]
    face_counts = [len(m.faces) for m in meshes]
    vertices = (
        np.concatenate([m.vertices for m in meshes]) if meshes else np.zeros((0, 3), np.float32)
    )
    faces = np.concatenate([m.faces for m in meshes]) if meshes else np.zeros((0, 3), np.int32)
    group.create_array(
        "vertices", data=np.ascontiguousarray(vertices, np.float32), config=STORE_EVERY_CHUNK
    )
    group.create_array(
        "faces", data=np.ascontiguousarray(faces, np.int32), config=STORE_EVERY_CHUNK
    )
    group.create_array(
        "vertex_offsets",
        data=np.r_[0, np.cumsum(vertex_counts)].astype(np.int64),
        config=STORE_EVERY_CHUNK,
    )
    group.create_array(
        "face_offsets",
        data=np.r_[0, np.cumsum(face_counts)].astype(np.int64),
        config=STORE_EVERY_CHUNK,
    )
    points_group = root.create_group("points")
    points_group.create_array(
        "points",
        data=np.ascontiguousarray(point_models.points, np.float32).reshape(-1, 4),
        config=STORE_EVERY_CHUNK,
    )
    points_group.create_array(
        "offsets", data=np.asarray(point_models.offsets, np.int64), config=STORE_EVERY_CHUNK
    )
    root.attrs.update(
        {
            "meshes": len(meshes),
            "point_models": len(point_models),
            "frame": "unit box",
            COMPLETE_CHUNKS_ATTR: True,
        }
    )


def _write_mesh_index(path: Path, meshes, ids, vertex_counts, face_counts) -> None:
    """meshes.parquet: one row per mesh (id, kind, source, native size, vertex/face counts)."""
    lwh = np.array([m.native_lwh for m in meshes], np.float64).reshape(-1, 3)
    pq.write_table(
        pa.table(
            {
                "model_id": pa.array(ids, pa.string()),
                "kind": pa.array([m.kind for m in meshes], pa.string()),
                "source": pa.array([m.source for m in meshes], pa.string()),
                "native_l": lwh[:, 0],
                "native_w": lwh[:, 1],
                "native_h": lwh[:, 2],
                "num_vertices": pa.array(vertex_counts, pa.int64()),
                "num_faces": pa.array(face_counts, pa.int64()),
            }
        ),
        path,
    )


def _write_point_index(path: Path, pm: PointModels) -> None:
    """point_models.parquet: one row per point model (ids, view angle, size, yaw, range, points)."""
    lwh = np.asarray(pm.lwh, np.float64).reshape(-1, 3)
    pq.write_table(
        pa.table(
            {
                "model_id": pa.array(pm.model_id.tolist(), pa.string()),
                "frame_id": pa.array(pm.frame_id.tolist(), pa.string()),
                "sensor": pa.array(pm.sensor.tolist(), pa.string()),
                "view_angle_rad": np.asarray(pm.view_angle_rad, np.float64),
                "l": lwh[:, 0],
                "w": lwh[:, 1],
                "h": lwh[:, 2],
                "yaw": np.asarray(pm.yaw, np.float64),
                "range_m": np.asarray(pm.range_m, np.float64),
                "num_points": pa.array(pm.num_points, pa.int32()),
            }
        ),
        path,
    )


def read_library(directory: str | Path) -> ModelLibrary:
    """Read and validate a library directory written by `write_library`."""
    import zarr

    directory = Path(directory)
    store = directory / LIBRARY_ZARR
    for required in (store, directory / MESHES_INDEX, directory / POINTS_INDEX):
        if not required.exists():
            raise LibraryError(
                f"{required}: missing (not a model library; build one with `dali library build`)"
            )
    try:
        root = zarr.open_group(str(store), mode="r")

        complete = bool(root.attrs.get(COMPLETE_CHUNKS_ATTR, False))

        def whole(name: str) -> np.ndarray:
            return read_whole_array(root[name], f"{store}/{name}", LibraryError, complete)

        vertices = np.asarray(whole("meshes/vertices"), np.float32)
        faces = np.asarray(whole("meshes/faces"), np.int32)
        vertex_offsets = np.asarray(whole("meshes/vertex_offsets"), np.int64)
        face_offsets = np.asarray(whole("meshes/face_offsets"), np.int64)
        points = np.asarray(whole("points/points"), np.float32).reshape(-1, 4)
        point_offsets = np.asarray(whole("points/offsets"), np.int64)
        mesh_index = pq.read_table(directory / MESHES_INDEX).to_pydict()
        point_index = pq.read_table(directory / POINTS_INDEX).to_pydict()
    except LibraryError:
        raise
    except Exception as error:
        raise LibraryError(
            f"{directory}: cannot read library ({type(error).__name__}: {error})"
        ) from None
    count = len(mesh_index["model_id"])
    if len(vertex_offsets) != count + 1 or len(face_offsets) != count + 1:
        raise LibraryError(f"{store}/meshes: offsets do not match {count} models in {MESHES_INDEX}")
    if vertex_offsets[-1] != len(vertices) or face_offsets[-1] != len(faces):
        raise LibraryError(f"{store}/meshes: offsets do not match the vertex/face arrays")
    meshes = []
    for k in range(count):
        model_vertices = vertices[vertex_offsets[k] : vertex_offsets[k + 1]]
        model_faces = faces[face_offsets[k] : face_offsets[k + 1]]
        if len(model_faces) and (model_faces.min() < 0 or model_faces.max() >= len(model_vertices)):
            raise LibraryError(
                f"{store}/meshes: model '{mesh_index['model_id'][k]}' has bad face indices"
            )
        meshes.append(
            CarModel(
                model_id=mesh_index["model_id"][k],
                vertices=model_vertices,
                faces=model_faces,
                native_lwh=np.array([mesh_index[f"native_{a}"][k] for a in "lwh"], np.float64),
                kind=mesh_index["kind"][k],
                source=mesh_index["source"][k],
            )
        )
    models = len(point_index["model_id"])
    if len(point_offsets) != models + 1 or point_offsets[-1] != len(points):
        raise LibraryError(
            f"{store}/points: offsets do not match {models} point models in {POINTS_INDEX}"
        )
    point_models = PointModels(
        points=points,
        offsets=point_offsets,
        view_angle_rad=np.asarray(point_index["view_angle_rad"], np.float64),
        lwh=np.stack([np.asarray(point_index[a], np.float64) for a in "lwh"], axis=1).reshape(
            -1, 3
        ),
        yaw=np.asarray(point_index["yaw"], np.float64),
        range_m=np.asarray(point_index["range_m"], np.float64),
        model_id=np.asarray(point_index["model_id"], dtype=object),
        frame_id=np.asarray(point_index["frame_id"], dtype=object),
        sensor=np.asarray(point_index["sensor"], dtype=object),
    )
    return ModelLibrary(meshes=meshes, point_models=point_models)


logging.getLogger("trimesh").setLevel(logging.ERROR)
