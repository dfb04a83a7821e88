"""Isotropic remeshing and smoothing of the junction with its border fixed."""

from __future__ import annotations

import logging

import numpy as np

from .meshutil import edge_counts, nondegenerate, vertex_adjacency

log = logging.getLogger(__name__)

__all__ = ["is_edge_manifold", "remesh_junction", "smooth_interior"]


def is_edge_manifold(F):
    """True when every edge of the non-degenerate faces has one or two faces."""
    _, cnt = edge_counts(F)
    return bool(np.all(cnt <= 2))


def remesh_junction(V, F, fixed, *, target, iterations=5):
    """Botsch-Kobbelt isotropic remeshing (gpytoolbox) with ``fixed`` vertices kept exactly.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        An edge-manifold open surface whose boundary vertices are all in ``fixed``.
    fixed : (k,) int array
        Vertices that must stay, in this order, at the start of the output.
    target : float
        Target edge length.
    iterations : int

    Returns
    -------
    U : (p, 3) float64
        ``U[:k] == V[fixed]`` exactly.
    G : (q, 3) int64
    """
    import warnings

    with warnings.catch_warnings():  # gpytoolbox imports deprecated scipy/numpy names
        warnings.simplefilter("ignore", DeprecationWarning)
        import gpytoolbox

    fixed = np.asarray(fixed, dtype=np.int64)
    U, G = gpytoolbox.remesh_botsch(
        np.ascontiguousarray(V, dtype=np.float64),
        np.ascontiguousarray(F, dtype=np.int32),
        int(iterations),
        float(target),
        True,
        feature=fixed.astype(np.int32),
    )
    U = np.asarray(U, dtype=np.float64)
    G = np.asarray(G, dtype=np.int64)
    U[: len(fixed)] = np.asarray(V, dtype=np.float64)[fixed]  # bit-exact border
    return U, G[nondegenerate(G)]


def smooth_interior(V, F, fixed, *, iterations=3, lam=0.5, mu=-0.53):
    """Taubin smoothing (no shrinkage) of the vertices not in ``fixed``.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    fixed : (k,) int array or (n,) bool

    Returns
    -------
    (n, 3) float64
    """
    V = np.asarray(V, dtype=np.float64).copy()
    n = len(V)
    A = vertex_adjacency(F, n).astype(np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    free = deg > 0
    fx = np.asarray(fixed)
    if fx.dtype == bool:
        free &= ~fx
    else:
        free[fx] = False
    for _ in range(iterations):
        for f in (lam, mu):
            L = (A @ V) / np.maximum(deg, 1)[:, None] - V
            V[free] += f * L[free]
    return V


def _tri_min_angle(a, b, c):
    """Smallest angle (radians) of triangle ``a, b, c`` (3-vectors)."""
    def ang(p, q, r):
        u, w = q - p, r - p
        nu, nw = np.linalg.norm(u), np.linalg.norm(w)
        if nu == 0 or nw == 0:
            return 0.0
        return float(np.arccos(np.clip(u @ w / (nu * nw), -1.0, 1.0)))
    return min(ang(a, b, c), ang(b, c, a), ang(c, a, b))


def _normal(a, b, c):
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n)
    return n / ln if ln > 0 else n


def flip_to_improve_angles(V, F, *, max_passes=10, min_normal_dot=0.7):
    """Flip interior edges where it raises the smaller of the two triangles' minimum angles.

    Boundary edges are never flipped, so a fixed border stays exactly as it is. A flip is
    refused when it would create an existing edge or fold the surface (the new triangles'
    normals must agree with the old ones within ``min_normal_dot``).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        An edge-manifold, consistently oriented triangle mesh.

    Returns
    -------
    G : (m, 3) int64
        Same vertices, flipped faces (same count and orientation).
    """
    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64).copy()
    for _ in range(max_passes):
        he = {}
        for f, (a, b, c) in enumerate(G):
            he[(a, b)] = (f, c)
            he[(b, c)] = (f, a)
            he[(c, a)] = (f, b)
        edges = {(min(a, b), max(a, b)) for (a, b) in he}
        changed = False
        done = set()
        for (a, b), (f, c) in list(he.items()):
            if a > b or (b, a) not in he:
                continue
            g, d = he[(b, a)]
            if f in done or g in done or c == d:
                continue
            if (min(c, d), max(c, d)) in edges:
                continue
            # current triangles (a, b, c) and (b, a, d); flipped: (c, d, b)... keep orientation
            old = min(_tri_min_angle(V[a], V[b], V[c]), _tri_min_angle(V[b], V[a], V[d]))
            new = min(_tri_min_angle(V[d], V[c], V[a]), _tri_min_angle(V[c], V[d], V[b]))
            if new <= old + 1e-9:
                continue
            n_old = _normal(V[a], V[b], V[c]) + _normal(V[b], V[a], V[d])
            ln = np.linalg.norm(n_old)
            if ln == 0:
                continue
            n_old /= ln
            if _normal(V[d], V[c], V[a]) @ n_old < min_normal_dot or _normal(V[c], V[d], V[b]) @ n_old < min_normal_dot:
                continue
            G[f] = (d, c, a)
            G[g] = (c, d, b)
            edges.discard((min(a, b), max(a, b)))
            edges.add((min(c, d), max(c, d)))
            done.update((f, g))
            changed = True
        if not changed:
            break
    return G


def _ring_min_angle(V, tris):
    """Smallest angle (degrees) over the triangles ``tris`` ``(k, 3)`` of ``V``."""
    P = V[tris]
    best = np.inf
    for c in range(3):
        u = P[:, (c + 1) % 3] - P[:, c]
        w = P[:, (c + 2) % 3] - P[:, c]
        nu = np.linalg.norm(u, axis=1)
        nw = np.linalg.norm(w, axis=1)
        if np.any(nu == 0) or np.any(nw == 0):
            return 0.0
        cos = np.einsum("ij,ij->i", u, w) / (nu * nw)
        best = min(best, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).min()))
    return best


def relocate_poor_vertices(V, F, nfixed, *, surface=None, threshold=25.0, iterations=4, min_normal_dot=0.5):
    """Move free vertices of poor triangles where it raises the worst angle around them.

    For each free vertex of a triangle whose minimum angle is below ``threshold`` degrees, try
    its 1-ring centroid and, for each incident triangle standing on a fixed (border) edge, the
    apex of the equilateral triangle on that edge; keep the candidate (projected back onto
    ``surface``) with the best minimum angle over the ring, if it beats the current position
    and folds nothing.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    nfixed : int
        ``V[:nfixed]`` never move.
    surface : (SV, SF), optional
        Candidates are projected onto this mesh (the surface being remeshed).

    Returns
    -------
    (n, 3) float64
    """
    import igl

    from .meshutil import triangle_min_angles

    V = np.asarray(V, dtype=np.float64).copy()
    F = np.asarray(F, dtype=np.int64)
    if len(F) == 0:
        return V
    VF = [[] for _ in range(len(V))]
    for f, tri in enumerate(F):
        for v in tri:
            VF[v].append(f)
    for _ in range(iterations):
        ang = triangle_min_angles(V, F)
        bad = np.flatnonzero(ang < threshold)
        verts = np.unique(F[bad].ravel())
        verts = verts[verts >= nfixed]
        if len(verts) == 0:
            break
        moved = False
        for v in verts:
            ring = F[VF[v]]
            P = V[ring]
            n0 = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
            n0 /= np.maximum(np.linalg.norm(n0, axis=1, keepdims=True), 1e-300)
            nbr = np.unique(ring.ravel())
            nbr = nbr[nbr != v]
            cands = [V[nbr].mean(axis=0)]
            for tri in ring:
                others = [u for u in tri if u != v]
                if len(others) == 2 and others[0] < nfixed and others[1] < nfixed:
                    a, b = V[others[0]], V[others[1]]
                    mid = 0.5 * (a + b)
                    e = b - a
                    L = np.linalg.norm(e)
                    if L == 0:
                        continue
                    off = V[v] - mid
                    off -= (off @ e) / (L * L) * e
                    lo = np.linalg.norm(off)
                    if lo == 0:
                        continue
                    cands.append(mid + off / lo * (np.sqrt(3) / 2) * L)
            C = np.asarray(cands)
            C = np.concatenate([C, 0.5 * (C + V[v])])
            if surface is not None:
                C = np.asarray(igl.point_mesh_squared_distance(C, surface[0], surface[1])[2])
            cur = _ring_min_angle(V, ring)
            best, best_pos = cur, None
            old = V[v].copy()
            for c in C:
                V[v] = c
                P = V[ring]
                n1 = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
                ln = np.linalg.norm(n1, axis=1)
                if np.any(ln == 0) or np.any(np.einsum("ij,ij->i", n1 / ln[:, None], n0) < min_normal_dot):
                    continue
                a = _ring_min_angle(V, ring)
                if a > best + 1e-6:
                    best, best_pos = a, c.copy()
            V[v] = old if best_pos is None else best_pos
            moved |= best_pos is not None
        if not moved:
            break
    return V
