"""Ray casting: hits against analytic geometry, transformed rays, multi-geometry scenes, guards."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from dali_cli import raycast
from dali_cli.raycast import MeshBVH, Scene, cast, cast_into_box, get_bvh


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _plane(z: float, half: float = 1000.0) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return vertices, np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("height", [1.73, 0.05])
def test_plane_hits_match_analytic_from_1_to_150_m_including_grazing(height):
    rng = np.random.default_rng(0)
    distance = np.geomspace(1.0, 150.0, 400)  # along-ground range of the hit
    distance = np.maximum(distance, height * 1.0001)
    azimuth = rng.uniform(-np.pi, np.pi, distance.size)
    horizontal = np.sqrt(np.maximum(distance**2 - height**2, 0.0))
    target = np.stack(
        [
            horizontal * np.cos(azimuth),
            horizontal * np.sin(azimuth),
            -np.full_like(distance, height),
        ],
        1,
    )
    directions = _unit(target)
    hits = cast(MeshBVH.from_mesh(*_plane(-height)), np.zeros(3), directions, threads=1)
    assert hits.hit.all()
    # at 150 m with a 5 cm mount the ray meets the plane at 0.02 deg: a grazing hit
    expected = height / -directions[:, 2]
    np.testing.assert_allclose(hits.distance, expected, rtol=1e-4)
    error = np.linalg.norm(hits.points - target, axis=1)
    assert np.all(error <= 1e-4 * distance)
    assert (hits.geometry_id == 0).all()
    np.testing.assert_allclose(np.abs(hits.normals[:, 2]), 1.0, atol=1e-6)


def test_sphere_hits_match_analytic_and_lie_on_their_triangle():
    radius = 1.0
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    bvh = MeshBVH.from_mesh(sphere.vertices, sphere.faces)
    rng = np.random.default_rng(1)
    ranges = np.geomspace(2.0, 150.0, 300)
    centers = _unit(rng.normal(size=(300, 3))) * ranges[:, None]
    # rays aimed at the sphere's center offset by up to 0.97 R (near grazing at the silhouette)
    offsets = rng.normal(size=(300, 3))
    offsets -= np.einsum("ij,ij->i", offsets, _unit(centers))[:, None] * _unit(centers)
    offsets = _unit(offsets) * rng.uniform(0.0, 0.97, (300, 1)) * radius
    directions = _unit(centers + offsets)
    shifted = cast(bvh, -centers, directions, threads=1)
    # the same rays through cast_into_box with an identity placement (origins moved near the model)
    moved = cast_into_box(
        bvh,
        -centers,
        directions,
        np.r_[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0],
        model_lwh=sphere.extents,
        threads=1,
    )
    assert shifted.hit.all() and moved.hit.all()
    # analytic sphere seen from -c: t = d.c - sqrt((d.c)^2 - |c|^2 + r^2)
    along = np.einsum("ij,ij->i", directions, centers)
    exact = along - np.sqrt(along**2 - ranges**2 + radius**2)
    # tessellation error of the icosphere (sagitta) bounds the difference, not float32 tracing
    edge = np.linalg.norm(
        sphere.vertices[sphere.faces[:, 0]] - sphere.vertices[sphere.faces[:, 1]], axis=1
    ).max()
    sagitta = radius - np.sqrt(radius**2 - (edge / np.sqrt(3)) ** 2)
    grazing = np.sqrt(np.maximum(1e-12, 1.0 - (np.linalg.norm(offsets, axis=1) / radius) ** 2))
    assert np.all(np.abs(shifted.distance - exact) <= sagitta / grazing + 1e-4 * exact)
    # exactness against the hit triangle's plane (float64), 1e-4 relative at every range
    triangles = sphere.vertices[sphere.faces[shifted.primitive_id]]  # (N, 3, 3)
    normal = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    plane_t = np.einsum("ij,ij->i", normal, triangles[:, 0] + centers) / np.einsum(
        "ij,ij->i", normal, directions
    )
    np.testing.assert_allclose(shifted.distance, plane_t, rtol=1e-4)
    np.testing.assert_allclose(moved.distance, shifted.distance, rtol=1e-6)


def _slab(origins, directions, lower, upper):
    """Analytic ray/axis-aligned-box entry distance (inf on miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lower - origins) / directions
        t2 = (upper - origins) / directions
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((far >= near) & (far > 0), np.maximum(near, 0), np.inf)


def test_box_hits_match_slab_intersection_including_vertices_and_edges():
    lwh = np.array([4.0, 1.8, 1.5])
    box = trimesh.creation.box(extents=lwh).subdivide().subdivide()
    bvh = MeshBVH.from_mesh(box.vertices, box.faces)
    rng = np.random.default_rng(2)
    count = 3000
    # aim at vertices and edge midpoints shared by several triangles (where a non-watertight test
    # lets rays slip through) and at random surface points, from 1-150 m outside the box
    edges = box.edges_unique
    targets = np.concatenate(
        [
            box.vertices[rng.integers(0, len(box.vertices), count)],
            0.5
            * (box.vertices[edges[:, 0]] + box.vertices[edges[:, 1]])[
                rng.integers(0, len(edges), count)
            ],
            box.sample(count, seed=3),
        ]
    )
    # the outward face of each target (the axis where it touches the box surface)
    slack = np.abs(np.abs(targets) - lwh / 2)
    axis = np.argmin(slack, axis=1)
    inner = np.sort(slack, axis=1)[:, 1] > 1e-6  # not on a box edge: not a silhouette point
    targets, axis = targets[inner], axis[inner]
    rows = np.arange(len(targets))
    origins = (
        targets
        + _unit(rng.normal(size=targets.shape)) * np.geomspace(1.0, 150.0, len(targets))[:, None]
    )
    outward = np.sign(targets[rows, axis])
    origins[rows, axis] = targets[rows, axis] + outward * np.abs(
        origins[rows, axis] - targets[rows, axis]
    )
    directions = _unit(targets - origins)
    hits = cast(bvh, origins, directions, threads=1)
    expected = _slab(origins, directions, -lwh / 2, lwh / 2)
    assert np.isfinite(expected).all()
    assert hits.hit.all()
    np.testing.assert_allclose(hits.distance, expected, rtol=1e-4, atol=1e-5)


@settings(max_examples=20, deadline=None)
@given(
    x=st.floats(-60, 60),
    y=st.floats(-60, 60),
    yaw=st.floats(-np.pi, np.pi),
    lwh=st.tuples(st.floats(0.5, 8), st.floats(0.5, 3), st.floats(0.5, 3)),
)
def test_transformed_rays_equal_rebuilt_mesh_hits(x, y, yaw, lwh):
    mesh = trimesh.creation.capsule(height=1.0, radius=0.4, count=[16, 16])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    extent = mesh.extents
    bvh = get_bvh(mesh.vertices, mesh.faces)
    box = np.array([x, y, -0.5, *lwh, yaw])
    affine = raycast.box_affine(box, extent)
    rebuilt = MeshBVH.from_mesh(raycast.transform_vertices(mesh.vertices, affine), mesh.faces)
    rng = np.random.default_rng(4)
    targets = raycast.transform_vertices(rng.uniform(-0.6, 0.6, (300, 3)) * extent, affine)
    directions = _unit(targets)
    moved = cast_into_box(bvh, np.zeros(3), directions, box, model_lwh=extent, threads=1)
    direct = cast(rebuilt, np.zeros(3), directions, threads=1)
    agree = moved.hit == direct.hit
    # only rays that graze the silhouette may differ (float32 rounding of the two meshes)
    assert agree.mean() >= 0.99
    both = moved.hit & direct.hit
    np.testing.assert_allclose(moved.distance[both], direct.distance[both], rtol=1e-5, atol=1e-5)
    # float32 hits of a rebuilt (float32) mesh: a few ulp of 60 m apart
    np.testing.assert_allclose(moved.points[both], direct.points[both], rtol=1e-5, atol=1e-4)
    if moved.hit.any():
        ordered = np.sort(moved.distance[moved.hit])
        limit = float(ordered[len(ordered) // 2 :][:2].mean())  # between two hits, not on one
        capped = cast_into_box(bvh, np.zeros(3), directions, box, extent, max_distance=limit)
        np.testing.assert_array_equal(capped.hit, moved.hit & (moved.distance <= limit))
    same_face = both & (moved.primitive_id == direct.primitive_id)
    cosine = np.einsum("ij,ij->i", moved.normals[same_face], direct.normals[same_face])
    assert np.all(cosine > 0.999)


def test_scene_returns_geometry_ids_and_first_hit():
    def sphere_at(center):
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        mesh.apply_translation(center)
        return mesh.vertices, mesh.faces

    # geometry 0 hides behind geometry 1 on the +x axis
    centers = ([20.0, 0, 0], [10.0, 0, 0], [0, 10.0, 0], [20.0, 4.0, 0])
    scene = Scene.from_meshes([sphere_at(c) for c in centers])
    assert scene.num_geometries == 4 and scene.num_triangles == 4 * 1280
    directions = _unit(np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [20.0, 4.0, 0]]))
    hits = cast(scene, np.zeros(3), directions, threads=1)
    np.testing.assert_array_equal(hits.geometry_id, [1, 2, -1, 3])
    np.testing.assert_array_equal(hits.hit, [True, True, False, True])
    assert np.isinf(hits.distance[2]) and np.isnan(hits.points[2]).all()
    assert 8.9 < hits.distance[0] < 9.01
    limited = cast(scene, np.zeros(3), directions, max_distance=15.0, threads=1)
    np.testing.assert_array_equal(limited.geometry_id, [1, 2, -1, -1])


def test_threads_give_identical_results_and_cache_reuses_bvh():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    bvh = get_bvh(sphere.vertices, sphere.faces)
    assert get_bvh(sphere.vertices.copy(), sphere.faces.copy()) is bvh
    rng = np.random.default_rng(5)
    directions = _unit(rng.normal(size=(40_000, 3)))
    origins = rng.normal(size=(40_000, 3))
    one = cast(bvh, origins, directions, threads=1)
    many = cast(bvh, origins, directions, threads=3)
    np.testing.assert_array_equal(one.distance, many.distance)
    np.testing.assert_array_equal(one.primitive_id, many.primitive_id)
    assert one.hit.all()


def test_bad_inputs_raise_clear_errors():
    bvh = MeshBVH.from_mesh(*_plane(-1.0))
    with pytest.raises(ValueError, match="differ in shape"):
        cast(bvh, np.zeros((3, 3)), np.ones((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        cast(bvh, np.zeros(3), np.array([[np.nan, 0, 1]]))
    with pytest.raises(ValueError, match="out of range"):
        MeshBVH.from_mesh(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="non-empty"):
        MeshBVH.from_mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert len(cast(bvh, np.zeros(3), np.zeros((0, 3)))) == 0
