"""The pull of a plain junction's vertices onto the inputs (issue 25, a clean seam).

A plain junction (no kept features) takes the blended field's shape; its vertices are pulled
back onto the inputs only where the inputs agree. Two surfaces that meet at an angle (the crease
of their union) do not agree, even where their closest points are close: pulled there, the
junction gets the crease back. One surface composed with itself agrees everywhere, its own
creases included.
"""

from __future__ import annotations

import numpy as np

from rigmix.fusion.presence import compute_presence
from rigmix.fusion.stitch import project_to_inputs


def _grid(n, size):
    """A square of ``n x n`` quads (two triangles each) in the plane z = 0, side ``size``."""
    t = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(t, t, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    k = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return V, F


def _present(V, F):
    """A presence of 1 everywhere (one joint, kept)."""
    P = compute_presence(V, F, np.ones((len(V), 1)), np.array([True]))
    assert np.all(P.p_welded == 1.0)
    return P


def _pulled(points, surfaces, h, agreeing):
    pres = [_present(V, F) for V, F in surfaces]
    U = np.asarray(points, np.float64)
    out = project_to_inputs(U, 0, pres, [P.welded.F for P in pres], {0: None, 1: None}, h, 1.0,
                             agreeing=agreeing)
    return np.linalg.norm(out - U, axis=1)


def test_two_surfaces_meeting_at_a_crease_do_not_agree():
    """A floor and a wall (the crease of their union along x); vertices of a junction rounded
    off over that crease, a fraction of a voxel from either surface: pulled without agreement,
    kept with it."""
    floor = _grid(8, 2.0)
    wall = (floor[0][:, [0, 2, 1]] + [0.0, 0.0, 1.0], floor[1])  # the plane y = 0, above the floor
    h = 0.1
    s = np.linspace(0.02, 0.06, 5)
    points = np.stack([np.linspace(-0.5, 0.5, 5), s, s], axis=1)  # inside the corner, near both
    assert np.all(_pulled(points, [floor, wall], h, agreeing=False) > 0.01)
    assert np.all(_pulled(points, [floor, wall], h, agreeing=True) == 0.0)


def test_one_surface_composed_with_itself_agrees_at_its_creases():
    """The same bent sheet twice (a self-composition): its closest points are one point, on a
    crease of it or not; vertices a fraction of a voxel off it go back onto it."""
    V, F = _grid(8, 2.0)
    V = V.copy()
    V[:, 2] = np.abs(V[:, 0])  # a 90-degree crease along x = 0
    h = 0.1
    points = np.array([[0.0, 0.1, 0.05], [0.5, -0.2, 0.55], [-0.3, 0.3, 0.27]])
    moved = _pulled(points, [(V, F), (V, F)], h, agreeing=True)
    assert np.all(moved > 0.0)
    assert np.allclose(moved, _pulled(points, [(V, F), (V, F)], h, agreeing=False))


def test_a_target_farther_than_the_reach_stays():
    """With agreement asked, a vertex whose target is over ``max_voxels`` voxels away stays
    (the blend between different shapes), where the plain pull moves it the full reach."""
    V, F = _grid(4, 2.0)
    h = 0.1
    points = np.array([[0.0, 0.0, 0.25], [0.2, 0.1, 0.05]])
    with_agreement = _pulled(points, [(V, F), (V, F)], h, agreeing=True)
    plain = _pulled(points, [(V, F), (V, F)], h, agreeing=False)
    assert with_agreement[0] == 0.0 and np.isclose(plain[0], h)
    assert np.isclose(with_agreement[1], 0.05) and np.isclose(plain[1], 0.05)


def test_closest_points_near_first_agree_with_the_whole_surface():
    """:func:`closest_points` looks among the faces near the queries first: queries close to the
    surface and queries far beyond the reach (answered by the whole surface) get the distances and
    closest points of a query on every face."""
    import igl

    from rigmix.geometry import closest_points

    V, F = _grid(60, 2.0)
    V = V.copy()
    V[:, 2] = 0.2 * np.sin(3.0 * V[:, 0]) * np.cos(2.0 * V[:, 1])  # a wavy sheet
    rng = np.random.default_rng(0)
    Q = np.concatenate([rng.uniform([-0.3, -0.3, -0.05], [0.3, 0.3, 0.05], (200, 3)),
                        rng.uniform([-0.3, -0.3, 0.6], [0.3, 0.3, 0.9], (20, 3))])  # beyond the reach
    d2, fid, C = closest_points(Q, V, F, 0.1)
    d2_all, _, C_all = igl.point_mesh_squared_distance(Q, V, F)
    np.testing.assert_allclose(d2, d2_all, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(C, C_all, atol=1e-12)
    # the faces named hold the closest points
    T = V[F[fid]]
    B = igl.barycentric_coordinates(C, T[:, 0].copy(), T[:, 1].copy(), T[:, 2].copy())
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", B, T), C, atol=1e-9)
    assert np.all(B > -1e-9)
