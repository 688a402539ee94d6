"""Car meshes of the model library: procedural cars and CAD files (OBJ, PLY, STL, glTF, OFF),
normalized to the unit box centered at the origin (l along +x, w along +y, up +z) with their
native l/w/h kept."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dali_cli.procedural import KINDS, generate_car_mesh
from dali_cli.store.artifacts import ArtifactError

CAD_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
_AXES = {"x": 0, "y": 1, "z": 2}


class LibraryError(ArtifactError):
    """A bad model file or library artifact; the message names the file and the problem."""


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


logging.getLogger("trimesh").setLevel(logging.ERROR)
