"""The 3D model library: car meshes (procedural or CAD; meshes.py), point models (point_models.py)
and its on-disk artifact (artifact.py).

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

from dali_cli.library.artifact import (
    LIBRARY_ZARR,
    MESHES_INDEX,
    POINTS_INDEX,
    ModelLibrary,
    read_library,
    write_library,
)
from dali_cli.library.meshes import (
    CAD_SUFFIXES,
    CarModel,
    LibraryError,
    axis_rotation,
    load_cad_directory,
    load_cad_file,
    normalize_mesh,
    procedural_car,
    procedural_library,
    proportions_problem,
)
from dali_cli.library.point_models import (
    PointModels,
    point_models_from_frame,
    point_models_from_frameset,
)

__all__ = [
    "CAD_SUFFIXES", "LIBRARY_ZARR", "MESHES_INDEX", "POINTS_INDEX", "CarModel", "LibraryError",
    "ModelLibrary", "PointModels", "axis_rotation", "load_cad_directory", "load_cad_file",
    "normalize_mesh", "point_models_from_frame", "point_models_from_frameset", "procedural_car",
    "procedural_library", "proportions_problem", "read_library", "write_library",
]  # fmt: skip
