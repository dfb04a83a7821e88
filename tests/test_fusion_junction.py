"""Isosurface, cut and loop-to-loop bridging (PIPELINE.md section 3)."""

import numpy as np
import pytest
from fusion_shapes import sphere

from rigmix.fusion.junction import boundary_loops, bridge_loops, clip_mesh, isosurface
from rigmix.fusion.meshutil import boundary_halfedges, edge_counts, intersecting_face_pairs, triangle_min_angles
from rigmix.fusion.remesh import flip_to_improve_angles, untangle


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


def _square_with_a_long_border_edge(lift=0.0):
    """A 4 x 4 square in z = 0: its bottom side one border edge of length 4, the other sides
    of edges of length 1, free vertices on the unit grid inside and, crowded against the long
    edge, three more at height y = 0.25 (lifted by ``lift`` in z). Returns ``V, F, nfixed``:
    the 13 border vertices come first (Delaunay triangles, counter-clockwise)."""
    from scipy.spatial import Delaunay

    border = ([(0, 0), (4, 0)] + [(4, y) for y in (1, 2, 3, 4)] + [(x, 4) for x in (3, 2, 1, 0)]
              + [(0, y) for y in (3, 2, 1)])
    inner = [(x, y) for y in (1, 2, 3) for x in (1, 2, 3)] + [(1, 0.25), (2, 0.25), (3, 0.25)]
    P = np.array(border + inner, float)
    F = Delaunay(P).simplices
    a, b = P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]]
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    F[cross < 0] = F[cross < 0][:, [0, 2, 1]]
    V = np.c_[P, np.zeros(len(P))]
    V[-3:, 2] = lift
    return V, F.astype(np.int64), len(border)


def test_collapses_give_the_triangles_beside_a_long_border_edge_room():
    """Free vertices crowded against a long seam edge make flat caps that flips cannot repair;
    collapsing them into a neighbour does, with the border, the fixed vertices, the
    orientation and (flat here) the surface unchanged."""
    import igl

    from rigmix.fusion.remesh import collapse_to_improve_angles, is_edge_manifold

    V, F, nb = _square_with_a_long_border_edge()
    F = flip_to_improve_angles(V, F)
    assert triangle_min_angles(V, F).min() < 10.0  # the caps on the long edge
    U, G = collapse_to_improve_angles(V, F, nb, max_deviation=1e-6)
    assert len(U) < len(V)
    assert triangle_min_angles(U, G).min() >= 20.0
    assert np.array_equal(U[:nb], V[:nb])
    assert {tuple(e) for e in boundary_halfedges(G)} == {tuple(e) for e in boundary_halfedges(F)}
    assert is_edge_manifold(G)
    n = np.cross(U[G[:, 1]] - U[G[:, 0]], U[G[:, 2]] - U[G[:, 0]])
    assert np.all(n[:, 2] > 0)
    assert np.isclose(igl.doublearea(U, G).sum(), igl.doublearea(V, F).sum())


def test_collapses_never_change_the_shape_beyond_the_tolerance():
    """The same crowded vertices standing 0.3 out of the plane are shape, not noise: with a
    tolerance of 0.01 none of them goes."""
    from rigmix.fusion.remesh import collapse_to_improve_angles

    V, F, nb = _square_with_a_long_border_edge(lift=0.3)
    F = flip_to_improve_angles(V, F)
    U, G = collapse_to_improve_angles(V, F, nb, max_deviation=0.01)
    for x in V[-3:]:
        assert np.min(np.linalg.norm(U - x, axis=1)) == 0.0
    _, G1 = collapse_to_improve_angles(V, F, nb, max_deviation=1.0)
    assert len(G1) < len(G)  # a loose tolerance lets them go


def test_collapses_never_create_a_forbidden_edge():
    """An edge the preserved faces already have must not appear in the junction too: with
    every edge the mesh does not have forbidden, collapses still go where they create none,
    and the result has no forbidden edge (unconstrained, it has some)."""
    from itertools import combinations

    from rigmix.fusion.remesh import collapse_to_improve_angles

    V, F, nb = _square_with_a_long_border_edge()
    F = flip_to_improve_angles(V, F)
    existing = {tuple(int(x) for x in e) for e in edge_counts(F)[0]}
    forbidden = np.array([e for e in combinations(range(len(V)), 2) if e not in existing])
    banned = {tuple(e) for e in forbidden.tolist()}

    def created(U, G):
        back = np.array([int(np.flatnonzero(np.all(V == x, axis=1))[0]) for x in U])  # kept vertices do not move
        return {tuple(sorted(int(x) for x in back[e])) for e in edge_counts(G)[0]} & banned

    U, G = collapse_to_improve_angles(V, F, nb, max_deviation=1e-6, forbidden=forbidden)
    assert not created(U, G)
    U1, G1 = collapse_to_improve_angles(V, F, nb, max_deviation=1e-6)
    assert created(U1, G1)

def test_remeshing_keeps_the_corners_it_would_chord_off():
    """A fine cap with a sharp bump, remeshed at a coarse edge length: plain remeshing flattens
    the bump; keeping what strays beyond the tolerance (the bump's tip) brings most of it back
    (feature vertices stay half a target edge apart, so not all of a bump this narrow), with
    the border untouched and the surface still edge-manifold and outward."""
    import igl

    from rigmix.fusion.remesh import is_edge_manifold
    from rigmix.fusion.stitch import remesh_keeping_features

    V, F = sphere(5)
    V = V * (1.0 + 0.3 * np.exp(-((V[:, 0] ** 2 + V[:, 1] ** 2) / 0.005)) * (V[:, 2] > 0))[:, None]
    F = F[V[F].mean(axis=1)[:, 2] > 0.3]
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    V, F = V[used], remap[F]
    border = np.unique(boundary_halfedges(F).ravel())
    target, tol = 0.25, 0.02

    def stray(U, G):
        return np.sqrt(igl.point_mesh_squared_distance(V, U, G)[0]).max()

    U0, G0, n0, _ = remesh_keeping_features(V, F, border, target, 5, 0.0, 2)
    U1, G1, n1, _ = remesh_keeping_features(V, F, border, target, 5, tol, 3)
    assert n0 == len(border) and n1 > len(border)
    assert stray(U0, G0) > 5 * tol  # the bump's tip is gone
    assert stray(U1, G1) < 0.25 * stray(U0, G0), (stray(U0, G0), stray(U1, G1))
    assert np.array_equal(U1[: len(border)], V[border])
    assert is_edge_manifold(G1)  # also: consistently oriented
    N = np.cross(U1[G1[:, 1]] - U1[G1[:, 0]], U1[G1[:, 2]] - U1[G1[:, 0]])
    assert np.einsum("ij,ij->", N, U1[G1].mean(axis=1)) > 0  # outward


def _cap(V, F, z):
    """The faces of ``(V, F)`` whose centroid is above height ``z``, without the other vertices."""
    F = F[V[F].mean(axis=1)[:, 2] > z]
    used = np.unique(F)
    return V[used], np.searchsorted(used, F)


def test_refinement_follows_the_reference_where_the_coarse_mesh_strays():
    """A coarse cap of a sphere against the fine sphere: its faces chord the sphere by more than
    the tolerance; refined, the new vertices lie on the sphere, the mesh strays less, the border
    edges stay as they are, and the surface is still edge-manifold and outward. Edges shorter
    than twice ``min_edge`` are left alone."""
    import igl

    from rigmix.fusion.remesh import is_edge_manifold, refine_where_stray

    RV, RF = sphere(5)
    RV, RF = _cap(RV, RF, 0.5)  # inside the coarse cap
    V, F = _cap(*sphere(1), 0.2)
    border = boundary_halfedges(F)

    def stray(U, G):
        return np.sqrt(igl.point_mesh_squared_distance(RV, U, G)[0]).max()

    tol = 0.25 * stray(V, F)
    U, G, split = refine_where_stray(V, F, (RV, RF), tol=tol, min_edge=0.01)
    assert split > 0 and len(U) == len(V) + split and np.array_equal(U[: len(V)], V)
    assert np.abs(np.linalg.norm(U[len(V):], axis=1) - 1.0).max() < 0.01  # on the fine sphere
    assert stray(U, G) < stray(V, F)
    assert is_edge_manifold(G)
    assert {tuple(e) for e in np.sort(boundary_halfedges(G), axis=1)} == {tuple(e) for e in np.sort(border, axis=1)}
    N = np.cross(U[G[:, 1]] - U[G[:, 0]], U[G[:, 2]] - U[G[:, 0]])
    assert np.all(np.einsum("ij,ij->i", N, U[G].mean(axis=1)) > 0)  # every face outward
    assert refine_where_stray(V, F, (RV, RF), tol=tol, min_edge=10.0)[2] == 0  # too short to split


def test_points_inserted_into_a_mesh_become_vertices():
    from rigmix.fusion.remesh import insert_points, is_edge_manifold

    V, F = sphere(2)
    X = np.array([[0.0, 0.0, 1.05], [0.3, 0.3, 0.95], [-0.5, 0.2, 0.85]])
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    fixed = np.zeros(len(V), bool)
    U, G, placed = insert_points(V, F, fixed, X, max_dist=0.2)
    assert len(placed) == 3
    assert np.allclose(np.sort(U[placed], axis=0), np.sort(X, axis=0))
    assert is_edge_manifold(G)
    assert len(boundary_halfedges(G)) == 0


def test_points_inserted_next_to_each_other_get_vertices_of_their_own():
    """Two points close to one free vertex, the second one waiting a pass (its triangle changed):
    each ends on a vertex of its own, and the first stays where it was put. A shared vertex
    made the remesher's feature list repeat a vertex, which shifted every kept vertex after it
    onto the wrong output vertex (a junction torn across the whole cluster)."""
    from rigmix.fusion.remesh import insert_points, is_edge_manifold

    V, F = sphere(2)
    v = 7
    n = V[v] / np.linalg.norm(V[v])
    side = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    X = np.array([V[v] + 0.01 * side, V[v] - 0.01 * side])
    U, G, placed = insert_points(V, F, np.zeros(len(V), bool), X, max_dist=0.2)
    assert len(placed) == 2 and len(np.unique(placed)) == 2
    np.testing.assert_allclose(U[placed], X, atol=1e-12)
    assert is_edge_manifold(G)


def test_remeshing_refuses_a_repeated_fixed_vertex():
    from rigmix.fusion.remesh import remesh_junction

    V, F = sphere(2)
    F = F[V[F].mean(axis=1)[:, 2] > 0.0]
    border = np.unique(boundary_halfedges(F).ravel())
    with pytest.raises(ValueError, match="repeated fixed"):
        remesh_junction(V, F, np.r_[border, border[:1]], target=0.3)
    U, _ = remesh_junction(V, F, border, target=0.3)
    assert np.array_equal(U[: len(border)], V[border])


def test_untangle_leaves_a_surface_folded_everywhere_as_it_is():
    """A triangle soup crossing itself everywhere (what a junction with its kept vertices written
    over the wrong vertices looked like): every face's box meets hundreds of others, so the
    broad phase is over budget and the surface comes back untouched at once, where rounds of
    smoothing each tested millions of pairs. A healthy surface stays well under the budget."""
    from rigmix.fusion.meshutil import TooManyCandidates
    from rigmix.fusion.remesh import UNTANGLE_CANDIDATES_PER_FACE, untangle

    rng = np.random.default_rng(0)
    V = rng.random((3000, 3))
    F = np.arange(3000).reshape(-1, 3)
    U, left = untangle(V, F, 0)
    assert left == -1 and np.array_equal(U, V)
    with pytest.raises(TooManyCandidates):
        intersecting_face_pairs(V, F, max_candidates=UNTANGLE_CANDIDATES_PER_FACE * len(F))
    S, G = sphere(3)
    assert len(intersecting_face_pairs(S, G, max_candidates=UNTANGLE_CANDIDATES_PER_FACE * len(G))) == 0


def test_cancelling_isosurface_faces_are_dropped():
    from rigmix.fusion.junction import drop_cancelling_faces

    F = np.array([[0, 1, 2], [2, 1, 3], [3, 1, 2], [4, 5, 6], [5, 6, 4], [7, 8, 9]])
    # (2,1,3) and (3,1,2) cancel (a fin); (4,5,6) and (5,6,4) are one face twice
    G = drop_cancelling_faces(F)
    assert sorted(map(tuple, G)) == [(0, 1, 2), (4, 5, 6), (7, 8, 9)]


def _two_triangles(second):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], *second], dtype=float)
    return V, np.array([[0, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize("second, crosses", [
    ([[0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [0.3, 0.5, 0.5]], True),     # pierces the first through its interior
    ([[0.5, -0.5, 0.3], [0.5, 2, 0.3], [0.5, -0.5, -0.3]], True),     # crosses it along a segment
    ([[0.2, 0.2, 0.1], [0.6, 0.2, 0.1], [0.2, 0.6, 0.1]], False),     # parallel, above it
    ([[0.5, 0.5, 0.0], [1, 1, 0.5], [1, 1, -0.5]], False),            # touches its edge at one point
    ([[2, 0, -1], [2, 0, 1], [3, 1, 0]], False),                      # far apart
    ([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.2, 0.2, 0]], False),          # no area: crosses nothing
])
def test_intersecting_face_pairs_tells_crossing_from_touching(second, crosses):
    V, F = _two_triangles(second)
    pairs = intersecting_face_pairs(V, F)
    assert (len(pairs) == 1) == crosses
    if crosses:
        assert sorted(pairs[0].tolist()) == [0, 1]
    # the same pair found from either face, and not at all from an unrelated subset
    assert len(intersecting_face_pairs(V, F, faces=[1])) == len(pairs)
    assert len(intersecting_face_pairs(V, F, faces=[])) == 0


def test_neighbours_sharing_a_corner_never_count():
    """Fan triangles meet at their shared corner, also when it is split into two vertices at
    one position (a glTF seam); a closed sphere has no self-intersection at all."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [-1, 0.2, 0.5], [-0.5, -1, -0.5]], dtype=float)
    F = np.array([[0, 1, 2], [3, 4, 5]])
    assert len(intersecting_face_pairs(V, F)) == 0
    Vs, Fs = sphere(2)
    assert len(intersecting_face_pairs(Vs, Fs)) == 0
    # pushing one vertex through the opposite side makes its fan cross that side's faces
    Vs = Vs.copy()
    top = int(np.argmax(Vs[:, 2]))
    Vs[top] = -1.2 * Vs[top]
    assert len(intersecting_face_pairs(Vs, Fs)) > 0


def test_untangle_opens_a_fold_and_keeps_the_fixed_vertices():
    """A sphere with one vertex pushed through to the other side: smoothing the crossing
    triangles' corners opens the fold, the fixed vertices stay, and the rest of the sphere
    stays where it was."""
    V0, F = sphere(2)
    order = np.argsort(V0[:, 2])  # fixed: the lower half (renumbered first)
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    V0, F = V0[order], inv[F]
    nfixed = len(V0) // 2
    V = V0.copy()
    top = len(V) - 1
    V[top] = [0.0, 0.0, -1.2]  # through the bottom of the sphere
    assert len(intersecting_face_pairs(V, F)) > 0
    U, left = untangle(V, F, nfixed)
    assert left == 0 and len(intersecting_face_pairs(U, F)) == 0
    assert np.array_equal(U[:nfixed], V[:nfixed])
    far = np.linalg.norm(V0 - V0[top], axis=1) > 1.0
    assert np.array_equal(U[far], V[far])
    # nothing to open: the mesh comes back as it is
    U2, left2 = untangle(V0, F, nfixed)
    assert left2 == 0 and np.array_equal(U2, V0)


def _cesium_arm():
    """CesiumMan's welded surface around its right arm: ``(V, F)`` of real, unevenly sized
    triangles."""
    from conftest import asset

    from rigmix.fusion.inputs import fusion_input
    from rigmix.io import load_character

    c = load_character(asset("CesiumMan"))
    inp = fusion_input(c, c.skeleton.subtree(c.skeleton.index("Skeleton_arm_joint_R")))
    F = np.asarray(inp.F, np.int64)
    used = np.unique(F)
    new = np.full(len(inp.V), -1)
    new[used] = np.arange(len(used))
    return np.asarray(inp.V, np.float64)[used], new[F]


def test_spread_keeps_points_apart_and_greedy():
    """The feature rounds' spread (``stitch._spread``) on a real character's vertices: picked
    points are at least the spacing apart and from the avoided points, and every other point
    was refused for a picked point of higher priority within the spacing (or an avoided one)."""
    from scipy.spatial import cKDTree

    from rigmix.fusion import stitch

    V, _ = _cesium_arm()
    rng = np.random.default_rng(1)
    prio = rng.random(len(V))
    spacing = 0.02 * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    avoid = V[:: 50]
    pick = stitch._spread(V, prio, spacing, avoid=avoid, avoid_spacing=0.5 * spacing)
    assert len(pick) > 10 and len(np.unique(pick)) == len(pick)
    P = V[pick]
    d, _ = cKDTree(P).query(P, k=2)
    assert d[:, 1].min() >= spacing
    assert cKDTree(avoid).query(P)[0].min() >= 0.5 * spacing
    rest = np.setdiff1d(np.arange(len(V)), pick)
    blocked = cKDTree(avoid).query(V[rest])[0] < 0.5 * spacing
    for k in rest[~blocked]:
        near = pick[np.linalg.norm(P - V[k], axis=1) < spacing]
        assert len(near) and prio[near].max() >= prio[k]


def _relocated_one_at_a_time(U, F, nfixed, surface):
    """One pass of :func:`rigmix.fusion.remesh.relocate_poor_vertices` written plainly: each poor
    vertex in turn tries its candidates one by one, seeing the moves before it."""
    import igl

    VF = [[] for _ in range(len(U))]
    for f, t in enumerate(F):
        for v in t:
            VF[v].append(f)
    W = U.copy()
    bad = np.flatnonzero(triangle_min_angles(U, F) < 25.0)
    verts = np.unique(F[bad].ravel())
    verts = verts[verts >= nfixed]
    cands = []
    for v in verts:
        nbr = np.unique(F[VF[v]].ravel())
        c = [W[nbr[nbr != v]].mean(axis=0)]
        for t in F[VF[v]]:
            a, b = [u for u in t if u != v]
            if a < nfixed and b < nfixed:  # the apex of the equilateral triangle on a fixed edge
                e = W[b] - W[a]
                off = W[v] - 0.5 * (W[a] + W[b])
                off -= (off @ e) / (e @ e) * e
                c.append(0.5 * (W[a] + W[b]) + off / np.linalg.norm(off) * np.sqrt(3) / 2 * np.linalg.norm(e))
        c = np.asarray(c)
        cands.append(np.concatenate([c, 0.5 * (c + W[v])]))
    allC = np.asarray(igl.point_mesh_squared_distance(np.concatenate(cands), *surface)[2])
    for v, C in zip(verts, np.split(allC, np.cumsum([len(c) for c in cands])[:-1])):
        ring = F[VF[v]]
        n0 = np.cross(W[ring[:, 1]] - W[ring[:, 0]], W[ring[:, 2]] - W[ring[:, 0]])
        n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
        best, pos = triangle_min_angles(W, ring).min(), None
        for c in C:
            old = W[v].copy()
            W[v] = c
            n1 = np.cross(W[ring[:, 1]] - W[ring[:, 0]], W[ring[:, 2]] - W[ring[:, 0]])
            ln = np.linalg.norm(n1, axis=1)
            ok = np.all(ln > 0) and np.all(np.einsum("ij,ij->i", n1 / ln[:, None], n0) >= 0.5)
            a = triangle_min_angles(W, ring).min()
            W[v] = old
            if ok and a > best + 1e-6:
                best, pos = a, c.copy()
        if pos is not None:
            W[v] = pos
    return W


def test_relocation_matches_one_candidate_at_a_time():
    """``relocate_poor_vertices`` on a real character's arm with free vertices jittered into
    poor triangles gives what trying each candidate position in turn, one vertex after another,
    gives (the rings are evaluated in batches and again where a neighbour moved), with and
    without fixed vertices (their edges add equilateral apexes), and never lowers the worst
    angle."""
    from rigmix.fusion.remesh import relocate_poor_vertices

    V, F = _cesium_arm()
    rng = np.random.default_rng(2)
    edge = float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
    for nfixed in (len(V) // 3, 0):
        U = V.copy()
        U[nfixed:] += rng.normal(scale=0.3 * edge, size=(len(V) - nfixed, 3))
        out = relocate_poor_vertices(U, F, nfixed, surface=(V, F), iterations=1)
        assert np.array_equal(out[:nfixed], U[:nfixed])
        assert np.count_nonzero(np.any(out != U, axis=1)) > 20
        assert triangle_min_angles(out, F).min() >= triangle_min_angles(U, F).min() - 1e-9
        assert np.allclose(out, _relocated_one_at_a_time(U, F, nfixed, (V, F)), rtol=0, atol=1e-12 * edge)


def test_an_edge_two_fans_share_is_flipped_apart():
    """A pinched seam bridged from both sides of its pinch: two quads, each split along the same
    edge ``a b`` (four faces on it). One quad takes its other diagonal; the faces stay
    consistently oriented and cover the same quads."""
    from rigmix.fusion.remesh import flip_doubled_edges

    a, b = (0.0, 0.0, 0.0), (1.0, 1.0, 0.0)
    V = np.array([a, b, (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.5, 0.5, 0.7), (0.5, 0.5, -0.7)])
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 0, 5]])
    _, cnt = edge_counts(F)
    assert cnt.max() == 4
    G = flip_doubled_edges(V, F)
    uE, cnt = edge_counts(G)
    assert len(G) == len(F) and cnt.max() == 2
    assert sum(1 for e in uE.tolist() if sorted(e) == [0, 1]) == 1  # one quad keeps the edge a b
    halfedges = np.concatenate([G[:, [0, 1]], G[:, [1, 2]], G[:, [2, 0]]])
    assert len(np.unique(halfedges, axis=0)) == len(halfedges)  # consistently oriented

    def area(T):
        return 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1).sum()

    assert area(G) == pytest.approx(area(F))  # each quad split the other way covers the same (planar) quad
    assert np.array_equal(flip_doubled_edges(V, G), G)  # nothing left to flip


def _edge_through_triangle(p, q, T):
    """Whether the segment ``p``-``q`` passes through the inside of triangle ``T`` (3, 3)
    (Möller-Trumbore on the segment: an independent test of the separating axis one)."""
    d = q - p
    e1, e2 = T[1] - T[0], T[2] - T[0]
    h = np.cross(d, e2)
    det = e1 @ h
    if abs(det) < 1e-12:
        return False
    s = p - T[0]
    u = (s @ h) / det
    w = np.cross(s, e1)
    v = (d @ w) / det
    t = (e2 @ w) / det
    return 0 < u < 1 and 0 < v < 1 and u + v < 1 and 0 < t < 1


def test_intersecting_face_pairs_match_a_brute_force_on_random_triangles():
    """Random triangles in a box (no two sharing a corner, none coplanar): a pair crosses
    exactly when an edge of one passes through the other; every pair is found, from any subset
    of faces, and none is found twice."""
    rng = np.random.default_rng(7)
    n = 300
    centres = rng.uniform(0, 4, (n, 1, 3))
    V = (centres + rng.normal(scale=0.35, size=(n, 3, 3))).reshape(-1, 3)
    F = np.arange(3 * n).reshape(n, 3)
    T = V[F]
    truth = set()
    for a in range(n):
        for b in range(a + 1, n):
            if np.any(T[a].min(axis=0) > T[b].max(axis=0)) or np.any(T[b].min(axis=0) > T[a].max(axis=0)):
                continue
            if any(_edge_through_triangle(X[i], X[(i + 1) % 3], Y) for X, Y in ((T[a], T[b]), (T[b], T[a]))
                   for i in range(3)):
                truth.add((a, b))
    assert len(truth) > 50  # the box is crowded enough to test something
    pairs = intersecting_face_pairs(V, F)
    assert len(pairs) == len(truth)
    assert {tuple(sorted(p)) for p in pairs.tolist()} == truth
    subset = rng.choice(n, size=n // 3, replace=False)
    pairs = intersecting_face_pairs(V, F, faces=subset)
    assert all(a in set(subset.tolist()) for a, _ in pairs.tolist())
    assert {tuple(sorted(p)) for p in pairs.tolist()} == {p for p in truth if p[0] in subset or p[1] in subset}
