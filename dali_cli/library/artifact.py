"""The model library's on-disk artifact (the layout: dali_cli/library/__init__.py): written
and read back with its meshes and point models."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dali_cli.library.meshes import CarModel, LibraryError
from dali_cli.library.point_models import PointModels
from dali_cli.store.artifacts import (
    COMPLETE_CHUNKS_ATTR,
    STORE_EVERY_CHUNK,
    read_whole_array,
)

LIBRARY_ZARR = "library.zarr"
MESHES_INDEX = "meshes.parquet"
POINTS_INDEX = "point_models.parquet"


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
