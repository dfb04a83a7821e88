"""Isosurface, cut and loop-to-loop bridging (PIPELINE.md section 3)."""

import numpy as np
import pytest

from rigmix.fusion.junction import boundary_loops, bridge_loops, clip_mesh, isosurface
from rigmix.fusion.meshutil import boundary_halfedges, edge_counts
from rigmix.fusion.remesh import flip_to_improve_angles
from rigmix.fusion.meshutil import triangle_min_angles

from fusion_shapes import sphere


def signed_volume(V, F):
    P = V[F]
    return np.einsum("ij,ij->i", P[:, 0], np.cross(P[:, 1], P[:, 2])).sum() / 6


def test_isosurface_of_a_sphere_is_closed_and_outward():
    h = 0.05
    x = np.arange(-1, 1 + h / 2, h)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    field = np.sqrt(X**2 + Y**2 + Z**2) - 0.7
    V, F = isosurface(field, np.array([-1.0, -1.0, -1.0]), h)
    _, cnt = edge_counts(F)
    assert np.all(cnt == 2)
    assert np.abs(np.linalg.norm(V, axis=1) - 0.7).max() < 0.01
    assert np.isclose(signed_volume(V, F), 4 / 3 * np.pi * 0.7**3, rtol=0.02)


def test_clip_mesh_cuts_exactly_on_the_level_set():
    V, F = sphere(3)
    s = V[:, 2] - 0.3
    Vc, Fc, old = clip_mesh(V, F, s)
    assert np.all(Vc[:, 2] >= 0.3 - 1e-12)
    loops, chains = boundary_loops(Vc, Fc)
    assert len(loops) == 1 and not chains
    assert np.allclose(loops[0].positions[:, 2], 0.3)
    # kept old vertices are untouched, new ones lie on the sphere's edges
    assert np.array_equal(Vc[old >= 0], V[old[old >= 0]])
    # area of the cap: 2 pi r h on the unit sphere (chords make it slightly smaller)
    P = Vc[Fc]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum()
    assert np.isclose(area, 2 * np.pi * 0.7, rtol=0.03)
    assert signed_volume(np.vstack([Vc]), Fc) > 0  # orientation kept (outward)


@pytest.mark.parametrize("n,m,twist", [(12, 12, 0.0), (7, 23, 0.3), (40, 9, 2.0)])
def test_bridge_two_circles_gives_a_closed_consistent_tube(n, m, twist):
    # two caps of a cylinder facing each other; bridging must close the tube without gaps
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    b = np.linspace(0, 2 * np.pi, m, endpoint=False) + twist
    # boundary of a bottom cap facing -z (clockwise seen from +z) and of a top cap facing +z
    P = np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)[::-1]
    Q = np.stack([np.cos(b), np.sin(b), np.full(m, 0.5)], axis=1)
    T = bridge_loops(P, Q)
    assert len(T) == n + m
    V = np.concatenate([P, Q])
    # with the two caps (fans), the result is a closed oriented surface of positive volume
    cb = np.array([[n + m, i, (i + 1) % n] for i in range(n)])
    V2 = np.concatenate([V, [[0, 0, 0], [0, 0, 0.5]]])
    ct = np.array([[n + m + 1, n + j, n + (j + 1) % m] for j in range(m)])
    F = np.concatenate([T, cb, ct])
    _, cnt = edge_counts(F)
    assert np.all(cnt == 2)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    assert len(np.unique(E, axis=0)) == len(E)  # every directed edge once: consistent
    assert signed_volume(V2, F) > 0.75 * np.pi * 0.5


def test_flips_raise_the_minimum_angle_and_keep_the_border():
    rng = np.random.default_rng(3)
    V, F = sphere(2)
    keep = V[F].mean(axis=1)[:, 2] > 0
    V2 = V + 0.03 * rng.standard_normal(V.shape)
    F2 = F[keep][:, [0, 1, 2]]
    G = flip_to_improve_angles(V2, F2)
    assert len(G) == len(F2)
    b0 = {tuple(e) for e in boundary_halfedges(F2)}
    b1 = {tuple(e) for e in boundary_halfedges(G)}
    assert b0 == b1
    assert triangle_min_angles(V2, G).min() >= triangle_min_angles(V2, F2).min()


def test_refine_to_surface_follows_the_reference_both_ways():
    """A coarse open cap refined against a fine bumpy one: within tolerance both ways, border
    and original vertices untouched, still an edge-manifold, consistently oriented surface."""
    import igl

    from rigmix.fusion.remesh import is_edge_manifold, refine_to_surface

    def cap(subdivisions, bump):
        V, F = sphere(subdivisions)
        # a sharp bump on top: what remeshing at a coarse edge length chords off
        V = V * (1.0 + bump * np.exp(-((V[:, 0] ** 2 + V[:, 1] ** 2) / 0.02)) * (V[:, 2] > 0))[:, None]
        keep = V[F].mean(axis=1)[:, 2] > 0.3
        F = F[keep]
        used = np.unique(F)
        remap = np.full(len(V), -1)
        remap[used] = np.arange(len(used))
        return V[used], remap[F]

    RV, RF = cap(5, 0.3)
    V, F = cap(2, 0.0)
    # border of the coarse cap fixed and first, as the junction gets it
    border = np.unique(boundary_halfedges(F).ravel())
    order = np.concatenate([border, np.setdiff1d(np.arange(len(V)), border)])
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    V, F = V[order], inv[F]
    tol = 0.02
    before = np.sqrt(igl.point_mesh_squared_distance(RV, V, F)[0]).max()
    assert before > 5 * tol  # the bump is missing
    U, G, pinned = refine_to_surface(V, F, len(border), (RV, RF), tol=tol)
    assert np.array_equal(U[: len(V)][: len(border)], V[: len(border)])
    assert is_edge_manifold(G)
    assert len(boundary_halfedges(G)) == len(boundary_halfedges(F))  # border edges unchanged
    ref_to_mesh = np.sqrt(igl.point_mesh_squared_distance(RV, U, G)[0]).max()
    assert ref_to_mesh <= tol * 1.01, ref_to_mesh
    uE, cnt = edge_counts(G)
    uE = uE[cnt == 2]  # border edges are the seam: never changed
    mid = 0.5 * (U[uE[:, 0]] + U[uE[:, 1]])
    assert np.sqrt(igl.point_mesh_squared_distance(mid, RV, RF)[0]).max() <= 2 * tol
    assert pinned.sum() > 0
    # orientation: normals still point outwards
    N = np.cross(U[G[:, 1]] - U[G[:, 0]], U[G[:, 2]] - U[G[:, 0]])
    assert np.all(np.einsum("ij,ij->i", N, U[G].mean(axis=1)) > 0)


def test_cancelling_isosurface_faces_are_dropped():
    from rigmix.fusion.junction import _drop_cancelling_faces

    F = np.array([[0, 1, 2], [2, 1, 3], [3, 1, 2], [4, 5, 6], [5, 6, 4], [7, 8, 9]])
    # (2,1,3) and (3,1,2) cancel (a fin); (4,5,6) and (5,6,4) are one face twice
    G = _drop_cancelling_faces(F)
    assert sorted(map(tuple, G)) == [(0, 1, 2), (4, 5, 6), (7, 8, 9)]
