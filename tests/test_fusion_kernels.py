"""The remeshers' small kernels give exactly the floats and faces of their plain numpy forms.

They were rewritten for speed (issue 26): a junction remeshing calls them tens of thousands of
times on a few triangles each, or once per inserted point on the whole junction. The fusion's
output must not change with them, so each is checked bit for bit against the plain form it
replaces, on random data and on a real junction.
"""

from __future__ import annotations

import numpy as np
import pytest

from dfd.mesh import weld
from rigmix.fusion.fields import prepare_surface
from rigmix.fusion.meshutil import (
    cross3,
    stable_argsort,
    triangle_corner_angles,
    undirected_edges,
    unique_ints,
    unique_rows,
)
from rigmix.fusion.remesh import insert_points


def _corner_angles_one_by_one(P):
    out = np.zeros(P.shape[:2])
    for c in range(3):
        u = P[:, (c + 1) % 3] - P[:, c]
        w = P[:, (c + 2) % 3] - P[:, c]
        nu = np.linalg.norm(u, axis=1)
        nw = np.linalg.norm(w, axis=1)
        cos = np.einsum("ij,ij->i", u, w) / np.maximum(nu * nw, 1e-300)
        out[:, c] = np.where((nu > 0) & (nw > 0), np.arccos(np.clip(cos, -1.0, 1.0)), 0.0)
    return out


@pytest.mark.parametrize("m", [1, 3, 7, 64, 5000])
def test_corner_angles_equal_the_corner_by_corner_form(m):
    rng = np.random.default_rng(m)
    for trial in range(20):
        P = rng.normal(size=(m, 3, 3)) * 10.0 ** rng.integers(-4, 4)
        if trial % 4 == 0:
            P[:, 1] = P[:, 0]  # degenerate: zero-length edges give 0
        got = triangle_corner_angles(P)
        assert np.array_equal(got, _corner_angles_one_by_one(P))
    assert np.allclose(triangle_corner_angles(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]])).sum(), np.pi)


def test_cross3_equals_numpy_cross():
    rng = np.random.default_rng(1)
    for m in (1, 5, 1000):
        a = rng.normal(size=(m, 3)) * 10.0 ** rng.integers(-5, 5)
        b = rng.normal(size=(m, 3)) * 10.0 ** rng.integers(-5, 5)
        assert np.array_equal(cross3(a, b), np.cross(a, b))
        assert np.array_equal(cross3(a[:, None], b[None, :3]), np.cross(a[:, None], b[None, :3]))


@pytest.mark.parametrize("n", [0, 1, 2, 9, 1000])
def test_unique_ints_and_rows_equal_numpy_unique(n):
    rng = np.random.default_rng(n)
    for _ in range(10):
        a = rng.integers(0, max(n // 3, 1), size=n)
        assert np.array_equal(unique_ints(a), np.unique(a))
        u, inv = unique_ints(a, return_inverse=True)
        u0, inv0 = np.unique(a, return_inverse=True)
        assert np.array_equal(u, u0) and np.array_equal(inv, inv0.ravel())
        P = rng.integers(0, max(n // 2, 1), size=(n, 2))
        r, rinv = unique_rows(P, return_inverse=True)
        r0, rinv0 = np.unique(P, axis=0, return_inverse=True)
        assert np.array_equal(r, r0.reshape(-1, 2)) and np.array_equal(rinv, rinv0.ravel())


@pytest.mark.parametrize("bits", [3, 20, 40, 62])
def test_stable_argsort_equals_numpy_stable_argsort(bits):
    # 62 bits leave no room for the positions: the plain stable argsort answers then
    rng = np.random.default_rng(bits)
    for n in (0, 1, 2, 17, 20000):
        a = rng.integers(0, 2 ** bits, size=n)
        assert np.array_equal(stable_argsort(a), np.argsort(a, kind="stable"))
    a = rng.integers(-50, 50, size=1000)  # negative values: the plain argsort
    assert np.array_equal(stable_argsort(a), np.argsort(a, kind="stable"))


def _weld_by_numpy_unique(V, F):
    _, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse.reshape(-1)]
    return V[np.sort(first)], index, index[F]


def test_weld_equals_the_numpy_unique_form():
    """Split copies, signed zeros (equal to zeros as numbers) and a NaN row (equal to none)."""
    rng = np.random.default_rng(3)
    base = rng.integers(-3, 4, size=(400, 3)) * 0.25
    V = base[rng.integers(0, 400, size=3000)].astype(np.float64)
    V[rng.integers(0, 3000, size=60), rng.integers(0, 3, size=60)] *= -1.0  # -0.0 where zero
    V[7] = [np.nan, 0.0, 0.0]
    V[9] = [np.nan, 0.0, 0.0]
    F = rng.integers(0, 3000, size=(2000, 3))
    for got, want in zip(weld(V, F), _weld_by_numpy_unique(V, F)):
        assert np.array_equal(got, want, equal_nan=True)


def test_edges_and_prepared_surface_equal_the_numpy_unique_forms():
    """Undirected edges and the duplicate faces of a doubled surface, as np.unique gives them."""
    rng = np.random.default_rng(4)
    F = rng.integers(0, 3000, size=(4000, 3))  # so many vertices that no two random faces coincide
    F = np.concatenate([F, F[:500], F[500:900, ::-1]])  # same-orientation and opposite copies
    E, uE, emap = undirected_edges(F)
    u0, inv0 = np.unique(np.sort(E, axis=1), axis=0, return_inverse=True)
    assert np.array_equal(uE, u0) and np.array_equal(emap, inv0.ravel())
    G = prepare_surface(rng.random((3000, 3)), F)
    key = lambda X: [tuple(r) for r in np.sort(X, axis=1)]  # noqa: E731
    got = key(G)
    assert len(set(got)) == len(got)  # each face once
    cancelled = set(key(F[500:900]))  # one copy each way: a tie, no face kept
    doubled = set(key(F[:500])) - cancelled
    assert not cancelled & set(got)
    assert doubled <= set(got)


def _insert_points_by_concatenation(V, F, fixed, X, *, max_dist, passes=4, snap=0.75, edge_bary=0.15):
    """The plain form: the whole face array searched and rebuilt for every point."""
    import igl

    from rigmix.fusion.meshutil import edge_counts

    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64)
    fixed = np.array(fixed, bool)
    placed = []
    for _ in range(passes):
        if len(X) == 0:
            break
        d2, fid, C = igl.point_mesh_squared_distance(X, V, G)
        ok = d2 <= max_dist * max_dist
        X, fid, C = X[ok], fid[ok], C[ok]
        T = G[fid]
        B = np.nan_to_num(np.asarray(igl.barycentric_coordinates(C, V[T[:, 0]], V[T[:, 1]], V[T[:, 2]])), nan=1 / 3)
        uE, cnt = edge_counts(G)
        inner = {(int(a), int(b)) for a, b in uE[cnt == 2]}
        touched, waiting = set(), np.zeros(len(X), bool)
        for k, (x, tri, bary) in enumerate(zip(X, T, B)):
            if touched.intersection(int(t) for t in tri):
                waiting[k] = True
                continue
            rows = np.flatnonzero((G == tri[0]).any(axis=1) & (G == tri[1]).any(axis=1) & (G == tri[2]).any(axis=1))
            if len(rows) != 1:
                continue
            f = int(rows[0])
            i = int(np.argmax(bary))
            v = int(G[f][i])
            if bary[i] > snap and not (v < len(fixed) and fixed[v]):
                V = V.copy()
                V[v] = x
            else:
                j = int(np.argmin(bary))
                v = len(V)
                a, b = int(G[f][(j + 1) % 3]), int(G[f][(j + 2) % 3])
                V = np.concatenate([V, x[None]])
                keep = np.ones(len(G), bool)
                if bary[j] < edge_bary and (min(a, b), max(a, b)) in inner:
                    new = []
                    for g in np.flatnonzero(np.isin(G, [a, b]).sum(axis=1) == 2):
                        t = G[g]
                        for x0, y0, z0 in ((t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])):
                            if {int(x0), int(y0)} == {a, b}:
                                new += [(x0, v, z0), (v, y0, z0)]
                                keep[g] = False
                                break
                else:
                    p, q, r = (int(t) for t in G[f])
                    keep[f] = False
                    new = [(p, q, v), (q, r, v), (r, p, v)]
                G = np.concatenate([G[keep], np.asarray(new, np.int64)])
            touched.add(v)
            placed.append(v)
            if v >= len(fixed):
                fixed = np.concatenate([fixed, np.zeros(v + 1 - len(fixed), bool)])
            fixed[v] = True
        X = X[waiting]
    return V, G, np.asarray(placed, np.int64)


def test_insert_points_equals_the_plain_form_on_a_real_surface():
    """Points on CesiumMan's whole welded surface (snaps, edge splits and face splits, some
    points sharing a triangle so that they wait a pass): the same vertices, faces in the same
    order, the same placed vertices."""
    from conftest import asset

    from rigmix.fusion.presence import weld_mesh
    from rigmix.io import load_character

    c = load_character(asset("CesiumMan"))
    welded = weld_mesh(np.concatenate([m.positions for m in c.meshes]), c.meshes[0].faces)
    V, F = np.asarray(welded.V, np.float64), np.asarray(welded.F, np.int64)
    rng = np.random.default_rng(0)
    f = rng.choice(len(F), 400)
    bary = rng.dirichlet([0.4, 0.4, 0.4], size=len(f))
    X = np.einsum("ij,ijk->ik", bary, V[F[f]])
    fixed = rng.random(len(V)) < 0.2
    got = insert_points(V, F, fixed, X, max_dist=np.inf)
    want = _insert_points_by_concatenation(V, F, fixed, X, max_dist=np.inf)
    assert len(got[2]) > 300 and len(got[1]) > len(F) + 300
    for g, w in zip(got, want):
        assert g.shape == w.shape and np.array_equal(g, w)
