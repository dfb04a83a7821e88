"""dfd.render: the fast Embree path against the reference rasterizer, cameras, shading."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset

from dfd.io import read_mesh
from dfd.mesh import normalization
from dfd.render import AMBIENT, DEFAULT_COLOR, camera_layout, render_views, surface_points
from dfd.shapes import ellipsoids, icosphere


def test_prototype_layout():
    cams = camera_layout(24)
    assert len(cams) == 24
    np.testing.assert_allclose(np.linalg.norm(cams.eye, axis=1), 2.8)
    elevations = np.degrees(np.arcsin(cams.eye[:, 1] / 2.8))
    np.testing.assert_allclose(sorted(set(np.round(elevations, 6))), [-15.0, 0.0, 15.0])
    azimuths = np.degrees(np.arctan2(cams.eye[:, 0], cams.eye[:, 2])) % 360
    np.testing.assert_allclose(sorted(set(np.round(azimuths, 6))), np.arange(8) * 45.0, atol=1e-6)
    # rotations are orthonormal and every camera looks at the origin
    R = cams.rotation
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.einsum("bij,bj->bi", R, -cams.eye)[:, :2], 0.0, atol=1e-12)


def test_sphere_layout_any_count():
    cams = camera_layout(10, layout="sphere")
    assert len(cams) == 10
    with pytest.raises(ValueError, match="multiple of 3"):
        camera_layout(10)


@pytest.mark.parametrize("shape", ["sphere", "figure"])
def test_embree_matches_reference_rasterizer(shape):
    if shape == "sphere":
        V, F = icosphere(2)
        V = V * [1.5, 1.0, 0.7]
    else:
        V, F = ellipsoids([((0, 0, 0), (0.6, 1.0, 0.5)), ((0.9, 0.3, 0), (0.35, 0.2, 0.2))], subdivisions=2)
    fast = render_views(V, F, n_views=6, resolution=48, backend="embree")
    ref = render_views(V, F, n_views=6, resolution=48, backend="numpy")
    same = fast.face_ids == ref.face_ids
    assert same.mean() > 0.995  # ties on shared edges may go either way
    assert fast.mask.sum() > 0.1 * fast.mask.size
    np.testing.assert_allclose(fast.barycentric[same], ref.barycentric[same], atol=1e-4)
    np.testing.assert_allclose(fast.depth[same], ref.depth[same], atol=1e-4)
    np.testing.assert_allclose(fast.rgb[same], ref.rgb[same], atol=1e-4)


def test_surface_points_lie_on_mesh_and_in_their_pixels():
    import igl

    V, F = icosphere(3)
    V = V * 3.0 + [10.0, -2.0, 5.0]  # units and offset: normalization handles them
    views = render_views(V, F, n_views=3, resolution=40)
    P = surface_points(V, F, views)
    assert len(P) == views.mask.sum()
    d2 = igl.point_mesh_squared_distance(P, V, F)[0]
    assert np.sqrt(d2).max() < 1e-6 * 3.0
    # each point lies on its pixel's ray at the rendered depth (normalized frame)
    norm = normalization(V)
    origins, directions = views.cameras.rays()
    expected = origins[views.mask] + views.depth[views.mask, None] * directions[views.mask]
    np.testing.assert_allclose(norm.apply(P), expected, atol=1e-4)


def test_shading_and_background():
    V, F = icosphere(2)
    views = render_views(V, F, n_views=3, resolution=32)
    assert (views.rgb[~views.mask] == 1.0).all()
    assert (views.face_ids[~views.mask] == -1).all()
    grey = np.asarray(DEFAULT_COLOR, dtype=np.float32)
    lit = views.rgb[views.mask]
    assert (lit >= grey * AMBIENT - 1e-6).all() and (lit <= grey + 1e-6).all()
    # the sphere's centre pixel faces the headlight: full diffuse
    np.testing.assert_allclose(views.rgb[:, 16, 16], np.broadcast_to(grey, (3, 3)), atol=0.01)
    np.testing.assert_allclose(np.linalg.norm(views.normals[views.mask], axis=1), 1.0, atol=1e-5)


def test_vertex_colours():
    V, F = icosphere(2)
    C = np.where(V[:, :1] > 0, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    views = render_views(V, F, vertex_colors=C, n_views=3, resolution=32)
    front = views.rgb[0][views.mask[0]]
    assert front[:, 0].max() > 0.5 and front[:, 2].max() > 0.5 and front[:, 1].max() < 1e-6


def test_textured_character():
    mesh = read_mesh(asset("CesiumMan"))
    assert mesh.texture is not None and mesh.uvs is not None
    views = render_views(mesh.V, mesh.F, uvs=mesh.uvs, texture=mesh.texture, n_views=3, resolution=64)
    lit = views.rgb[views.mask]
    assert views.mask.sum() > 300
    assert lit.std(axis=0).max() > 0.05  # the texture shows, not one flat colour
