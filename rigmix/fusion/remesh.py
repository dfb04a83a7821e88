"""Isotropic remeshing and smoothing of the junction with its border fixed."""

from __future__ import annotations

import logging

import numpy as np

from .meshutil import (
    TooManyCandidates,
    corner_angles,
    cross3,
    edge_counts,
    intersecting_face_pairs,
    nondegenerate,
    stable_argsort,
    triangle_corner_angles,
    triangle_min_angles,
    undirected_edges,
    unique_ints,
    unique_rows,
    vertex_adjacency,
)

log = logging.getLogger(__name__)

#: :func:`untangle`'s budget of broad-phase pairs per face: about 10 on a healthy junction,
#: about 1500 on one whose kept vertices were written over the wrong vertices
UNTANGLE_CANDIDATES_PER_FACE = 200

__all__ = [
    "collapse_to_improve_angles",
    "flip_to_improve_angles",
    "insert_points",
    "is_edge_manifold",
    "refine_where_stray",
    "relocate_poor_vertices",
    "remesh_junction",
    "smooth_interior",
    "snap_to_points",
    "untangle",
]


def is_edge_manifold(F):
    """True when every edge has one or two faces and the faces are consistently oriented.

    (Botsch-Kobbelt remeshing in gpytoolbox aborts the process on anything else.)
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    if not np.all(nondegenerate(F)):
        return False
    _, cnt = edge_counts(F)
    if not np.all(cnt <= 2):
        return False
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    if len(unique_rows(E)) != len(E):
        return False
    import igl

    r = igl.is_vertex_manifold(F)
    ok = r[0] if isinstance(r, tuple) else r
    return bool(np.all(ok))


def flip_doubled_edges(V, F):
    """Faces ``F`` with each edge that two separate pairs of faces share made manifold by a flip.

    Bridging a seam loop that touches itself at a vertex (a pinched seam) to the isosurface can
    join that vertex to one isosurface vertex from both sides of the pinch: four faces on one
    edge, two running each way. Each face running one way pairs with the one running the other
    way that lies flattest against it (largest normal dot product); the pair whose flip makes
    the better smallest angle, and no edge that exists already, takes the other diagonal of its
    quad. Edges shared otherwise are left as they are.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Consistently oriented faces.

    Returns
    -------
    (m, 3) int64
        The same number of faces; only the flipped pairs differ.
    """
    F = np.array(F, dtype=np.int64).reshape(-1, 3)
    uE, cnt = edge_counts(F)
    if not np.any(cnt == 4):
        return F
    V = np.asarray(V, dtype=np.float64)
    present = {tuple(e) for e in uE.tolist()}
    for a, b in uE[cnt == 4]:
        has = np.isin(F, (a, b)).sum(axis=1) == 2
        fw, bw = [], []  # (face, opposite vertex): faces running a -> b, and b -> a
        for f in np.flatnonzero(has):
            k = int(np.flatnonzero(F[f] == a)[0])
            other = int(F[f][(F[f] != a) & (F[f] != b)][0])
            (fw if F[f][(k + 1) % 3] == b else bw).append((int(f), other))
        if len(fw) != 2 or len(bw) != 2:
            continue
        T = F[[f for f, _ in fw + bw]]
        n = _unit_normals(V[T[:, 0]], V[T[:, 1]], V[T[:, 2]])[0]  # fw[0], fw[1], bw[0], bw[1]
        straight = n[0] @ n[2] + n[1] @ n[3]
        crossed = n[0] @ n[3] + n[1] @ n[2]
        pairs = [(fw[0], bw[0]), (fw[1], bw[1])] if straight >= crossed else [(fw[0], bw[1]), (fw[1], bw[0])]
        best = None
        for (f, c), (g, d) in pairs:
            if c == d or tuple(sorted((c, d))) in present:
                continue
            flipped = np.array([(c, a, d), (d, b, c)], np.int64)
            angle = float(triangle_min_angles(V, flipped).min())
            if best is None or angle > best[0]:
                best = (angle, f, g, flipped)
        if best is not None:
            F[best[1]], F[best[2]] = best[3]
            c, d = best[3][0, 0], best[3][0, 2]
            present.add((min(c, d), max(c, d)))
    return F


def remesh_junction(V, F, fixed, *, target, iterations=5):
    """Botsch-Kobbelt isotropic remeshing (gpytoolbox) with ``fixed`` vertices kept exactly.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        An edge-manifold open surface whose boundary vertices are all in ``fixed``.
    fixed : (k,) int array
        Distinct vertices that must stay, in this order, at the start of the output.
    target : float
        Target edge length.
    iterations : int

    Returns
    -------
    U : (p, 3) float64
        ``U[:k] == V[fixed]`` exactly.
    G : (q, 3) int64

    Raises
    ------
    ValueError
        ``fixed`` repeats a vertex: gpytoolbox would keep it once and every kept vertex after
        it would then be written over the wrong output vertex.
    """
    import warnings

    with warnings.catch_warnings():  # gpytoolbox imports deprecated scipy/numpy names
        warnings.simplefilter("ignore", DeprecationWarning)
        import gpytoolbox

    fixed = np.asarray(fixed, dtype=np.int64)
    if len(np.unique(fixed)) != len(fixed):
        raise ValueError(f"remesh_junction: {len(fixed) - len(np.unique(fixed))} repeated fixed vertices")
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


def collapse_to_improve_angles(V, F, nfixed, *, max_deviation, threshold=20.0, passes=6, min_normal_dot=0.5,
                               forbidden=None):
    """Collapse free vertices of poor triangles into a neighbour where it raises the worst angle.

    A uniform target edge cannot meet a seam edge several times longer (a low-poly input's
    preserved face): the remesher fills the strip beside it with flat caps that no flip or
    move repairs, because the vertices are too many for the room. Removing one lets the
    neighbours form taller triangles. For each triangle below ``threshold`` degrees (worst
    first), each of its edges ``(v, u)`` with ``v`` free is a candidate: ``v`` goes onto ``u``;
    the best candidate is applied if the smallest angle of ``v``'s triangles rises, no triangle
    folds (normals within ``min_normal_dot`` of the old ones) or degenerates, the link
    condition holds (the surface stays a manifold) and ``v``'s old position lies within
    ``max_deviation`` of the new triangles (the surface keeps its shape).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Edge-manifold, consistently oriented; border vertices among the fixed ones.
    nfixed : int
        ``V[:nfixed]`` never move nor go.
    max_deviation : float
        Same unit as ``V``.
    forbidden : (k, 2) int array, optional
        Edges no collapse may create (they exist in the preserved faces around the junction).

    Returns
    -------
    U : (p, 3) float64, G : (q, 3) int64
        ``U[:nfixed] == V[:nfixed]``; removed vertices are dropped (the order kept).
    """
    import igl

    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64).copy()
    if len(G) == 0:
        return V.copy(), G
    alive = np.ones(len(G), bool)
    VF = [set() for _ in range(len(V))]
    for f, tri in enumerate(G):
        for v in tri:
            VF[v].add(f)
    thr = np.radians(threshold)
    banned = set()
    if forbidden is not None:
        banned = {(min(int(a), int(b)), max(int(a), int(b))) for a, b in np.asarray(forbidden).reshape(-1, 2)}

    def normals(T):
        n = cross3(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
        ln = np.linalg.norm(n, axis=1)
        return n / np.maximum(ln, 1e-300)[:, None], ln

    def try_collapse(v, u):
        """``(gain, ids of v's surviving faces, their corners after the collapse, ids of the two
        faces that go)``, or None when the collapse is refused."""
        rv, ru = VF[v], VF[u]
        shared = rv & ru
        if len(shared) != 2:
            return None
        nv = {int(x) for f in rv for x in G[f]} - {v}
        nu = {int(x) for f in ru for x in G[f]} - {u}
        opposite = {int(x) for f in shared for x in G[f]} - {u, v}
        if nv & nu != opposite:
            return None  # link condition: the collapse would pinch the surface
        if banned and any((min(u, x), max(u, x)) in banned for x in nv - {u}):
            return None
        moved = sorted(rv - shared)
        T = G[moved].copy()
        T[T == v] = u
        n0, _ = normals(G[moved])
        n1, l1 = normals(T)
        if np.any(l1 <= 0) or np.any(np.einsum("ij,ij->i", n0, n1) < min_normal_dot):
            return None
        # only v's triangles change (or go); the rest of u's ring keeps its angles
        before = corner_angles(V, G[sorted(rv)]).min()
        after = corner_angles(V, T).min()
        if after <= before + 1e-9:
            return None
        d2 = igl.point_mesh_squared_distance(V[v][None], V, T)[0]
        if np.sqrt(d2.min()) > max_deviation:
            return None
        return after - before, moved, T, shared

    for _ in range(passes):
        ang = triangle_corner_angles(V[G]).min(axis=1)
        order = np.flatnonzero(alive & (ang < thr))
        order = order[np.argsort(ang[order])]
        applied = 0
        for f in order:
            if not alive[f] or corner_angles(V, G[f][None]).min() >= thr:
                continue
            tri = [int(x) for x in G[f]]
            best = None
            for v in tri:
                if v < nfixed:
                    continue
                for u in tri:
                    if u == v:
                        continue
                    r = try_collapse(v, u)
                    if r is not None and (best is None or r[0] > best[1][0]):
                        best = ((v, u), r)
            if best is None:
                continue
            (v, u), (_, moved, T, shared) = best
            for g in shared:
                alive[g] = False
                for x in G[g]:
                    VF[x].discard(g)
            G[moved] = T
            for g in moved:
                VF[u].add(g)
            VF[v] = set()
            applied += 1
        if applied == 0:
            break
    G = G[alive]
    used = np.zeros(len(V), bool)
    used[:nfixed] = True
    used[G.ravel()] = True
    new = np.cumsum(used) - 1
    return V[used].copy(), new[G]


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


def _min_angles(A, B, C):
    """Smallest angle (radians) of triangles ``(A[i], B[i], C[i])``, each ``(k, 3)``."""
    return triangle_corner_angles(np.stack([A, B, C], axis=1)).min(axis=1, initial=np.pi)


def _unit_normals(A, B, C):
    n = cross3(B - A, C - A)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(ln, 1e-300), ln[:, 0]


def flip_to_improve_angles(V, F, *, max_passes=10, min_normal_dot=0.7, forbidden=None):
    """Flip interior edges where it raises the smaller of the two triangles' minimum angles.

    Boundary edges are never flipped, so a fixed border stays exactly as it is. A flip is
    refused when it would create an existing edge or fold the surface (the new triangles'
    normals must agree with the old ones within ``min_normal_dot``). Vectorized per pass; the
    best flips that share no triangle are applied together.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        An edge-manifold, consistently oriented triangle mesh.
    forbidden : (k, 2) int array, optional
        Edges that must not exist (they exist elsewhere, e.g. inside the preserved faces around
        a junction): flipped away when present, never created.

    Returns
    -------
    G : (m, 3) int64
        Same vertices, flipped faces (same count and orientation).
    """
    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64).copy()
    n = len(V) + 1
    fkey = np.zeros(0, np.int64)
    if forbidden is not None and len(forbidden):
        fb = np.sort(np.asarray(forbidden, np.int64).reshape(-1, 2), axis=1)
        fkey = unique_ints(fb[:, 0] * n + fb[:, 1])
    m = len(G)
    if m == 0:
        return G
    for _ in range(max_passes):
        a = G.ravel()
        b = np.roll(G, -1, axis=1).ravel()
        c = np.roll(G, -2, axis=1).ravel()
        f = np.repeat(np.arange(m), 3)
        key = a * n + b
        order = np.argsort(key)
        skey = key[order]
        tw = np.searchsorted(skey, b * n + a)
        tw = np.clip(tw, 0, len(skey) - 1)
        has = skey[tw] == b * n + a
        twin = np.where(has, order[tw], -1)
        h = np.flatnonzero(has & (a < b))
        if len(h) == 0:
            break
        t = twin[h]
        A, B, C, D = V[a[h]], V[b[h]], V[c[h]], V[c[t]]
        old = np.minimum(_min_angles(A, B, C), _min_angles(B, A, D))
        new = np.minimum(_min_angles(D, C, A), _min_angles(C, D, B))
        n0, l0 = _unit_normals(A, B, C)
        n1, l1 = _unit_normals(B, A, D)
        navg = n0 + n1
        navg /= np.maximum(np.linalg.norm(navg, axis=1, keepdims=True), 1e-300)
        m0, k0 = _unit_normals(D, C, A)
        m1, k1 = _unit_normals(C, D, B)
        abk = np.minimum(a[h], b[h]) * n + np.maximum(a[h], b[h])
        must = np.isin(abk, fkey)
        ok = ((new > old + 1e-9) | must) & (c[h] != c[t]) & (k0 > 0) & (k1 > 0)
        ok &= (np.einsum("ij,ij->i", m0, navg) >= min_normal_dot) & (np.einsum("ij,ij->i", m1, navg) >= min_normal_dot)
        ukey = unique_ints(np.minimum(a, b) * n + np.maximum(a, b))
        cd = np.minimum(c[h], c[t]) * n + np.maximum(c[h], c[t])
        pos = np.clip(np.searchsorted(ukey, cd), 0, len(ukey) - 1)
        ok &= (ukey[pos] != cd) & ~np.isin(cd, fkey)
        cand = np.flatnonzero(ok)
        if len(cand) == 0:
            break
        cand = cand[np.argsort(-(new[cand] - old[cand] + 10.0 * must[cand]))]
        used = np.zeros(m, bool)
        taken_cd = set()
        applied = 0
        for k in cand:
            fa, fb = f[h[k]], f[t[k]]
            if used[fa] or used[fb] or cd[k] in taken_cd:
                continue
            used[fa] = used[fb] = True
            taken_cd.add(int(cd[k]))
            va, vb, vc, vd = a[h[k]], b[h[k]], c[h[k]], c[t[k]]
            G[fa] = (vd, vc, va)
            G[fb] = (vc, vd, vb)
            applied += 1
        if applied == 0:
            break
    return G


def _ring_min_angle(V, tris):
    """Smallest angle (degrees) over the triangles ``tris`` ``(k, 3)`` of ``V`` (0 if one is degenerate)."""
    return float(np.degrees(corner_angles(V, tris).min(initial=np.inf)))


def _vertex_rings(F, n):
    """The faces around each vertex, in increasing face order: vertex ``v``'s are
    ``faces[ptr[v]:ptr[v + 1]]`` (``ptr`` ``(n + 1,)``, ``faces`` ``(3m,)`` int64)."""
    flat = F.ravel()
    faces = stable_argsort(flat) // 3
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(flat, minlength=n), out=ptr[1:])
    return ptr, faces


def _ring_entries(ptr, faces, verts):
    """The ring faces of ``verts`` ``(k,)`` stacked, ``(R,)``, with each one's owner (an index
    into ``verts``) and the start of each vertex's run ``(k,)``."""
    r = ptr[verts + 1] - ptr[verts]
    start = np.cumsum(r) - r
    owner = np.repeat(np.arange(len(verts)), r)
    return faces[ptr[verts][owner] + np.arange(len(owner)) - start[owner]], owner, start


def _ring_centroids(V, F, ring, owner, verts):
    """Mean of each vertex's distinct ring neighbours ``(k, 3)``, the floats of
    ``V[nbr].mean(axis=0)``: the neighbours added one row at a time in increasing index order,
    then divided by their count."""
    nb = F[ring].ravel()
    own = np.repeat(owner, 3)
    keep = nb != verts[own]
    n = len(V) + 1
    key = unique_ints(own[keep] * n + nb[keep])
    own, nb = key // n, key % n
    deg = np.bincount(own, minlength=len(verts))
    col = np.arange(len(nb)) - (np.cumsum(deg) - deg)[own]
    X = np.zeros((len(verts), int(deg.max(initial=1)), 3))
    X[own, col] = V[nb]
    acc = X[:, 0].copy()
    for j in range(1, X.shape[1]):
        m = deg > j
        acc[m] = acc[m] + X[m, j]
    return acc / deg[:, None]


def _border_apex(V, v, a, b):
    """Apex of the equilateral triangle on the fixed edge ``(a, b)`` on ``v``'s side, or None."""
    a, b = V[a], V[b]
    mid = 0.5 * (a + b)
    e = b - a
    L = np.linalg.norm(e)
    off = V[v] - mid
    if L == 0:
        return None
    off -= (off @ e) / (L * L) * e
    lo = np.linalg.norm(off)
    if lo == 0:
        return None
    return mid + off / lo * (np.sqrt(3) / 2) * L


def _relocation_candidates(V, F, ring, owner, verts, nfixed):
    """Candidate positions of ``verts``: per vertex its ring centroid, then the apex of each
    ring triangle standing on a fixed edge, then each of those halfway from the vertex.

    Returns
    -------
    C : (c, 3) float64
        Vertex ``i``'s candidates are ``C[cptr[i]:cptr[i + 1]]``.
    cptr : (k + 1,) int64
    """
    tris = F[ring]
    is_v = tris == verts[owner][:, None]
    border = (np.count_nonzero(is_v, axis=1) == 1) & np.all(is_v | (tris < nfixed), axis=1)
    apex_owner, apexes = [], []
    for e in np.flatnonzero(border):
        v = verts[owner[e]]
        a, b = tris[e][~is_v[e]]
        p = _border_apex(V, v, a, b)
        if p is not None:
            apex_owner.append(owner[e])
            apexes.append(p)
    apex_owner = np.asarray(apex_owner, np.int64)
    m = np.bincount(apex_owner, minlength=len(verts))
    base = np.concatenate([_ring_centroids(V, F, ring, owner, verts), np.reshape(apexes, (-1, 3))])
    base_owner = np.concatenate([np.arange(len(verts)), apex_owner])
    base = base[stable_argsort(base_owner)]
    base_owner = np.sort(base_owner)
    k = 1 + m
    cptr = np.zeros(len(verts) + 1, np.int64)
    np.cumsum(2 * k, out=cptr[1:])
    pos = np.arange(len(base)) - (np.cumsum(k) - k)[base_owner]
    C = np.empty((cptr[-1], 3))
    C[cptr[base_owner] + pos] = base
    C[cptr[base_owner] + k[base_owner] + pos] = 0.5 * (base + V[verts][base_owner])
    return C, cptr


def _ring_moves(V, F, ring, owner, start, verts, C, cptr, min_normal_dot):
    """Each vertex's ring with the vertex at each of its candidate positions, all at once.

    Returns
    -------
    ok : (c,) bool
        Per candidate: no ring triangle degenerates and none turns past ``min_normal_dot``.
    angle : (c,) float64
        Per candidate: the smallest angle of the moved ring, degrees.
    current : (k,) float64
        Per vertex: the smallest angle of its ring as it is, degrees.
    """
    tris = F[ring]
    P = V[tris]
    n0 = cross3(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    n0 /= np.maximum(np.linalg.norm(n0, axis=1, keepdims=True), 1e-300)
    current = np.minimum.reduceat(np.degrees(triangle_corner_angles(P).min(axis=1)), start)
    is_v = tris == verts[owner][:, None]
    # one row per (vertex, candidate, ring triangle), in that order
    r = np.diff(np.r_[start, len(ring)])
    cand_vert = np.repeat(np.arange(len(verts)), np.diff(cptr))
    rows = r[cand_vert]
    first = np.cumsum(rows) - rows
    cand = np.repeat(np.arange(len(C)), rows)
    tri = start[cand_vert[cand]] + np.arange(len(cand)) - first[cand]
    T = P[tri]
    at = is_v[tri]
    T[at] = np.repeat(C[cand], np.count_nonzero(at, axis=1), axis=0)
    n1 = cross3(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    ln = np.linalg.norm(n1, axis=1)
    dots = np.einsum("ij,ij->i", n1 / np.where(ln == 0, 1.0, ln)[:, None], n0[tri])
    ok = np.logical_and.reduceat((ln > 0) & (dots >= min_normal_dot), first)
    angle = np.minimum.reduceat(np.degrees(triangle_corner_angles(T).min(axis=1)), first)
    return ok, angle, current


def relocate_poor_vertices(V, F, nfixed, *, surface=None, threshold=25.0, iterations=4, min_normal_dot=0.5):
    """Move free vertices of poor triangles where it raises the worst angle around them.

    For each free vertex of a triangle whose minimum angle is below ``threshold`` degrees, try
    its 1-ring centroid and, for each incident triangle standing on a fixed (border) edge, the
    apex of the equilateral triangle on that edge, and each of those halfway from the vertex;
    keep the candidate (projected back onto ``surface``) with the best minimum angle over the
    ring, if it beats the current position and folds nothing.

    The vertices move one after another, in increasing index order, each seeing the moves
    before it (Gauss-Seidel). A vertex's move depends only on its ring, so the vertices are
    moved in waves (:func:`_relocation_waves`), each wave's rings evaluated at once: the
    result is that of the one-at-a-time order.

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

    V = np.asarray(V, dtype=np.float64).copy()
    F = np.asarray(F, dtype=np.int64)
    if len(F) == 0:
        return V
    ptr, faces = _vertex_rings(F, len(V))
    tree = None
    if surface is not None:
        tree = igl.AABB()
        SV = np.ascontiguousarray(surface[0], dtype=np.float64)
        SF = np.ascontiguousarray(surface[1], dtype=np.int64)
        tree.init(SV, SF)
    for _ in range(iterations):
        ang = triangle_min_angles(V, F)
        bad = np.flatnonzero(ang < threshold)
        verts = unique_ints(F[bad])
        verts = verts[verts >= nfixed]
        if len(verts) == 0:
            break
        ring, owner, start = _ring_entries(ptr, faces, verts)
        C, cptr = _relocation_candidates(V, F, ring, owner, verts, nfixed)
        if tree is not None:
            C = np.asarray(tree.squared_distance(SV, SF, C)[2])
        if not _relocate_in_order(V, F, ptr, faces, verts, C, cptr, min_normal_dot):
            break
    return V


def _relocation_waves(F, verts, n):
    """``(k,) int``: the wave of each of ``verts`` (sorted), the longest chain of earlier
    ``verts`` sharing a face with it, one after another.

    Moved in increasing index order, a vertex sees the moves of the earlier ones of its ring and
    none of the later ones; moved wave by wave, it sees the same (the earlier ones are in earlier
    waves, the later ones in later waves), and no two vertices of a wave share a face.
    """
    member = np.zeros(n, bool)
    member[verts] = True
    E = undirected_edges(F)[1]
    E = E[member[E[:, 0]] & member[E[:, 1]] & (E[:, 0] != E[:, 1])]
    wave = np.zeros(n, np.int64)
    while True:
        later = wave.copy()
        np.maximum.at(later, E[:, 1], wave[E[:, 0]] + 1)
        if np.array_equal(later, wave):
            return wave[verts]
        wave = later


def _relocate_in_order(V, F, ptr, faces, verts, C, cptr, min_normal_dot):
    """Move ``verts`` (in place in ``V``) to their best candidates, as one after another in
    increasing index order would.

    Returns True where a vertex moved.
    """
    moved = False
    wave = _relocation_waves(F, verts, len(V))
    for w in range(int(wave.max(initial=-1)) + 1):
        idx = np.flatnonzero(wave == w)
        sub = verts[idx]
        kc = cptr[idx + 1] - cptr[idx]
        sub_ptr = np.zeros(len(idx) + 1, np.int64)
        np.cumsum(kc, out=sub_ptr[1:])
        rows = np.repeat(cptr[idx] - sub_ptr[:-1], kc) + np.arange(sub_ptr[-1])
        Cs = C[rows]
        ring, owner, start = _ring_entries(ptr, faces, sub)
        ok, angle, current = _ring_moves(V, F, ring, owner, start, sub, Cs, sub_ptr, min_normal_dot)
        for i, v in enumerate(sub):
            best, best_pos = current[i], None
            for c in np.flatnonzero(ok[sub_ptr[i]:sub_ptr[i + 1]]) + sub_ptr[i]:  # must beat the best before it
                if angle[c] > best + 1e-6:
                    best, best_pos = angle[c], Cs[c]
            if best_pos is not None:
                V[v] = best_pos
                moved = True
    return moved


def snap_to_points(V, F, nfixed, P, *, max_dist, min_angle=15.0, min_normal_dot=0.5):
    """Move free vertices onto nearby target points (input vertices lying on the surface).

    Each target takes the nearest free vertex within ``max_dist`` (closest pairs first, one
    vertex per target); a move is kept when it folds no triangle of the vertex's ring and
    keeps its smallest angle at least ``min_angle`` degrees (or no worse than before).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    nfixed : int
        ``V[:nfixed]`` never move.
    P : (k, 3) float array
        Target points.

    Returns
    -------
    (n, 3) float64
    """
    from scipy.spatial import cKDTree

    V = np.asarray(V, dtype=np.float64).copy()
    F = np.asarray(F, dtype=np.int64)
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0 or len(V) <= nfixed or len(F) == 0:
        return V
    free = np.arange(nfixed, len(V))
    dist, nn = cKDTree(V[free]).query(P, distance_upper_bound=max_dist)
    ok = np.isfinite(dist)
    order = np.flatnonzero(ok)[np.argsort(dist[ok])]
    VF = [[] for _ in range(len(V))]
    for f, tri in enumerate(F):
        for v in tri:
            VF[v].append(f)
    taken = set()
    for k in order:
        v = int(free[nn[k]])
        if v in taken:
            continue
        ring = F[VF[v]]
        if len(ring) == 0:
            continue
        Q = V[ring]
        n0 = cross3(Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0])
        n0 /= np.maximum(np.linalg.norm(n0, axis=1, keepdims=True), 1e-300)
        before = _ring_min_angle(V, ring)
        old = V[v].copy()
        V[v] = P[k]
        Q = V[ring]
        n1 = cross3(Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0])
        ln = np.linalg.norm(n1, axis=1)
        after = _ring_min_angle(V, ring)
        good = np.all(ln > 0) and np.all(
            np.einsum("ij,ij->i", n1 / np.maximum(ln, 1e-300)[:, None], n0) >= min_normal_dot)
        if not good or after < min(min_angle, before):
            V[v] = old
            continue
        taken.add(v)
    return V


class _FaceList:
    """Triangles that points are inserted into one at a time, in order.

    Removed faces leave a hole and new ones go at the end, so :meth:`faces` lists the survivors
    in the order ``np.concatenate([F[keep], new])`` after each insertion would have given them.
    Faces are found through their corners (the input's vertex-face incidence, sorted once, and
    a dictionary for the added faces), so an insertion costs the size of its neighbourhood, not
    of the mesh.
    """

    def __init__(self, F):
        self.F = np.asarray(F, np.int64).reshape(-1, 3)
        self.added: list[tuple[int, int, int]] = []
        self.alive = np.ones(len(self.F), bool)
        self.alive_added: list[bool] = []
        corners = self.F.ravel()
        by_vertex = np.argsort(corners, kind="stable")
        self.order = by_vertex // 3
        self.starts = np.searchsorted(corners[by_vertex], np.arange(int(corners.max(initial=-1)) + 2))
        self.added_at: dict[int, list[int]] = {}

    def row(self, g) -> tuple[int, int, int]:
        m = len(self.F)
        return tuple(int(v) for v in self.F[g]) if g < m else self.added[g - m]

    def is_alive(self, g) -> bool:
        m = len(self.F)
        return bool(self.alive[g]) if g < m else self.alive_added[g - m]

    def add(self, t):
        g = len(self.F) + len(self.added)
        self.added.append(t)
        self.alive_added.append(True)
        for v in set(t):
            self.added_at.setdefault(v, []).append(g)

    def remove(self, g):
        m = len(self.F)
        if g < m:
            self.alive[g] = False
        else:
            self.alive_added[g - m] = False

    def _at(self, v) -> list[int]:
        """Positions, in order, of the live faces with corner ``v``."""
        out = []
        if v + 1 < len(self.starts):
            out = [int(g) for g in unique_ints(self.order[self.starts[v]:self.starts[v + 1]]) if self.alive[g]]
        return out + [g for g in self.added_at.get(v, ()) if self.is_alive(g)]

    def with_corners(self, tri):
        """Positions of the live faces that have every vertex of ``tri`` as a corner."""
        key = set(int(v) for v in tri)
        return [g for g in self._at(int(tri[0])) if key <= set(self.row(g))]

    def on_edge(self, a, b):
        """Positions, in order, of the live faces with the corners ``a`` and ``b`` and a third one."""
        return [g for g in self._at(a) if b in self.row(g) and len(set(self.row(g)) - {a, b}) == 1]

    def faces(self):
        added = np.asarray(self.added, np.int64).reshape(-1, 3)[np.asarray(self.alive_added, bool)]
        return np.concatenate([self.F[self.alive], added])


def _insert_point(V, faces: _FaceList, f, bary, x, fixed, inner, snap=0.75, edge_bary=0.15):
    """Insert point ``x`` into face ``f`` (its projection has barycentric coordinates ``bary``).

    Near a free vertex (``bary`` above ``snap``) that vertex moves to ``x``; near an interior
    edge (a coordinate below ``edge_bary``) the edge is split at ``x``; else, and next to a
    fixed vertex or a border edge (neither may change), the face is split in three.
    ``V``: list of ``(3,)`` positions, appended to and moved in place; ``faces`` is changed in
    place; ``fixed``: list of bool over the first vertices (later ones, inserted, are free);
    ``inner(a, b)``: whether ``a``-``b`` is an interior edge.

    Returns
    -------
    vertex : int, the vertex now at ``x``.
    """
    tri = faces.row(f)
    k = int(np.argmax(bary))
    v = tri[k]
    if bary[k] > snap and not (v < len(fixed) and fixed[v]):
        V[v] = x
        return v
    j = int(np.argmin(bary))
    n = len(V)
    a, b = tri[(j + 1) % 3], tri[(j + 2) % 3]
    V.append(x)
    if bary[j] < edge_bary and inner(a, b):
        new = []
        for g in faces.on_edge(a, b):
            t = faces.row(g)
            for x0, y0, z0 in ((t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])):
                if {x0, y0} == {a, b}:
                    new += [(x0, n, z0), (n, y0, z0)]
                    faces.remove(g)
                    break
        for t in new:
            faces.add(t)
        return n
    a, b, c = tri
    faces.remove(f)
    for t in ((a, b, n), (b, c, n), (c, a, n)):
        faces.add(t)
    return n


def insert_points(V, F, fixed, X, *, max_dist, passes=4):
    """Insert points lying on the surface ``(V, F)`` represents into it (one pass).

    Each point of ``X`` within ``max_dist`` of the mesh goes into its closest triangle
    (:func:`_insert_point`: a nearby free vertex moves onto it, or the nearby interior edge or
    the triangle is split; next to a fixed vertex or a border edge, the triangle: the result
    is meant to be remeshed, slivers do not matter); a point whose triangle another one
    changed waits for the next of at most ``passes`` passes.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Edge-manifold, consistently oriented.
    fixed : (n,) bool
        Vertices that must not move.
    X : (k, 3) float array
    max_dist : float

    Returns
    -------
    U : (p, 3) float64, G : (q, 3) int64, placed : (r,) int64
        ``U[:n]`` are the old vertices (moved ones excepted); ``placed``: the distinct vertices
        now at points of ``X``. A placed vertex is fixed for the points after it: two points
        never share a vertex, and a later one never moves an earlier one away.
    """
    import igl

    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64)
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    fixed = [bool(b) for b in np.asarray(fixed, bool)]  # a copy: placed vertices join it
    if len(X) == 0 or len(G) == 0:
        return V, G, np.zeros(0, np.int64)
    placed: list[int] = []
    for _ in range(passes):
        if len(X) == 0:
            break
        d2, fid, C = igl.point_mesh_squared_distance(X, V, G)
        ok = d2 <= max_dist * max_dist
        X, fid, C = X[ok], fid[ok], C[ok]
        T = G[fid]
        B = np.nan_to_num(np.asarray(igl.barycentric_coordinates(C, V[T[:, 0]], V[T[:, 1]], V[T[:, 2]])), nan=1 / 3)
        uE, cnt = edge_counts(G)
        nv = len(V) + len(X) + 1
        inner_keys = uE[cnt == 2, 0] * nv + uE[cnt == 2, 1]  # sorted, as uE's rows are

        def inner(a, b, keys=inner_keys, nv=nv):
            key = min(a, b) * nv + max(a, b)
            i = int(np.searchsorted(keys, key))
            return i < len(keys) and int(keys[i]) == key

        faces = _FaceList(G)
        U = list(V.copy())
        touched: set[int] = set()
        waiting = np.zeros(len(X), bool)
        for k, (x, tri, bary) in enumerate(zip(X, T, B)):
            if touched.intersection(int(t) for t in tri):
                waiting[k] = True  # its triangle changed: next pass
                continue
            rows = faces.with_corners(tri)
            if len(rows) != 1:
                continue
            v = _insert_point(U, faces, rows[0], bary, x, fixed, inner)
            touched.add(v)
            placed.append(v)
            if v >= len(fixed):
                fixed += [False] * (v + 1 - len(fixed))
            fixed[v] = True
        V = np.asarray(U, np.float64).reshape(-1, 3)
        G = faces.faces()
        X = X[waiting]
    return V, G, np.asarray(placed, np.int64)


def _split_faces(G, Mf, U):
    """Triangles of the faces ``G`` (m, 3) with their split edges' midpoints ``Mf`` (m, 3)
    (the vertex on the edge from corner ``c`` to ``c + 1``, -1 where unsplit): a face with three
    splits gives four, one with one split two, and one with two splits a triangle at their
    shared corner and the rest of it cut along its shorter diagonal (positions ``U``)."""
    out = [G[(Mf < 0).all(axis=1)]]
    for f in np.flatnonzero((Mf >= 0).any(axis=1)):
        t, m = G[f], Mf[f]
        k = int(np.count_nonzero(m >= 0))
        if k == 3:
            a, b, c = t
            ab, bc, ca = m
            out.append(np.array([(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]))
        elif k == 1:
            r = int(np.flatnonzero(m >= 0)[0])
            a, b, c = t[r], t[(r + 1) % 3], t[(r + 2) % 3]
            out.append(np.array([(a, m[r], c), (m[r], b, c)]))
        else:
            r = int(np.flatnonzero(m < 0)[0])  # the unsplit edge a -> b
            a, b, c = t[r], t[(r + 1) % 3], t[(r + 2) % 3]
            x, y = m[(r + 1) % 3], m[(r + 2) % 3]  # on b -> c and c -> a
            if np.linalg.norm(U[a] - U[x]) < np.linalg.norm(U[b] - U[y]):
                out.append(np.array([(x, c, y), (a, b, x), (a, x, y)]))
            else:
                out.append(np.array([(x, c, y), (a, b, y), (b, x, y)]))
    return np.concatenate(out).astype(np.int64)


def refine_where_stray(V, F, reference, *, tol, min_edge):
    """Split the faces of ``(V, F)`` that stray from ``reference`` by more than ``tol``.

    A remeshing to one target edge chords off the curved parts of the surface it follows; a
    vertex pinned there instead stands as a spike over coarse triangles (and the remesher,
    which treats pinned vertices as border ones, leaves them three faces). Here the triangles
    get finer where they miss the shape: a face is marked when a reference vertex's closest
    point is on it farther than ``tol`` away, or its centroid lies farther than ``tol`` from the
    reference; the interior edges of marked faces at least ``2 min_edge`` long are split at
    their midpoints, moved onto the closest reference point, and a face with two split edges
    gets the third too (red-green closure, so the new triangles keep their parents' angles
    where they can). Border edges never split: the border stays as it is.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Edge-manifold, consistently oriented.
    reference : (RV, RF)
        The surface to follow, ``(r, 3)`` float and ``(s, 3)`` int.
    tol, min_edge : float
        Same units as ``V``.

    Returns
    -------
    U : (n + k, 3) float64
        ``U[:n] == V``, then the ``k`` new vertices.
    G : (q, 3) int64
        Same orientation as ``F``.
    k : int
        Edges split (0: nothing strays, or nothing left to split).
    """
    import igl

    V = np.asarray(V, dtype=np.float64)
    G = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    RV = np.asarray(reference[0], dtype=np.float64)
    RF = np.asarray(reference[1], dtype=np.int64)
    if len(G) == 0 or len(RF) == 0:
        return V, G, 0
    d2, fid, _ = igl.point_mesh_squared_distance(RV, V, G)
    marked = np.zeros(len(G), bool)
    marked[fid[d2 > tol * tol]] = True
    c2 = igl.point_mesh_squared_distance(V[G].mean(axis=1), RV, RF)[0]
    marked |= c2 > tol * tol
    if not marked.any():
        return V, G, 0
    m = len(G)
    _, uE, emap = undirected_edges(G)
    emap = emap.reshape(3, m).T  # (m, 3): the edge from corner c to c + 1
    count = np.bincount(emap.ravel(), minlength=len(uE))
    length = np.linalg.norm(V[uE[:, 0]] - V[uE[:, 1]], axis=1)
    can = (count == 2) & (length >= 2.0 * min_edge)
    split = np.zeros(len(uE), bool)
    split[emap[marked].ravel()] = True
    split &= can
    for _ in range(len(uE)):  # closure; each round splits more edges, so it ends
        grow = (split[emap].sum(axis=1) == 2)[:, None] & can[emap] & ~split[emap]
        if not grow.any():
            break
        split[emap[grow]] = True
    es = np.flatnonzero(split)
    if len(es) == 0:
        return V, G, 0
    _, _, P = igl.point_mesh_squared_distance(0.5 * (V[uE[es, 0]] + V[uE[es, 1]]), RV, RF)
    mid = np.full(len(uE), -1, np.int64)
    mid[es] = len(V) + np.arange(len(es))
    U = np.concatenate([V, np.asarray(P, np.float64)])
    return U, _split_faces(G, mid[emap], U), int(len(es))


def untangle(V, F, nfixed, *, rounds=8, step=0.5, max_move=None):
    """Smooth the corners of crossing triangles until they cross no more.

    Each round moves the free corners (index ``>= nfixed``) of every crossing pair, and their
    neighbours, a ``step`` towards the mean of their neighbours (umbrella smoothing): a fold
    left by a projection or an inserted feature point opens up with the least change of shape.
    The result is kept only if it crosses itself less than ``V`` does and, with ``max_move``,
    no vertex moved farther than that (a fold at a sharp corner is not worth the corner).
    A surface folded onto itself everywhere (over :data:`UNTANGLE_CANDIDATES_PER_FACE` broad
    phase pairs per face) is returned as it is: smoothing cannot open it, and each round's
    test would cost time quadratic in its faces.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    nfixed : int
        Vertices ``0 .. nfixed - 1`` never move (the seam).
    max_move : float, optional

    Returns
    -------
    V_out : (n, 3) float64
    crossings : int
        Crossing pairs of triangles left; -1 for a surface over the budget (not counted).
    """
    V = np.array(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    budget = UNTANGLE_CANDIDATES_PER_FACE * max(len(F), 1)
    try:
        start = intersecting_face_pairs(V, F, max_candidates=budget)
    except TooManyCandidates:
        log.warning("fusion: a remeshed junction of %d faces folds onto itself everywhere; not untangled", len(F))
        return V, -1
    if len(start) == 0:
        return V, 0
    A = vertex_adjacency(F, len(V)).astype(np.float64).tocsr()
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)
    U, pairs = V.copy(), start
    for _ in range(rounds):
        move = np.zeros(len(V), bool)
        move[F[pairs.ravel()].ravel()] = True
        move |= (A @ move.astype(np.float64)) > 0
        move[:nfixed] = False
        if not move.any():
            break
        mean = (A @ U) / deg[:, None]
        U[move] += step * (mean[move] - U[move])
        try:
            pairs = intersecting_face_pairs(U, F, max_candidates=budget)
        except TooManyCandidates:
            return V, int(len(start))
        if len(pairs) == 0:
            break
    moved = float(np.linalg.norm(U - V, axis=1).max())
    if len(pairs) < len(start) and (max_move is None or moved <= max_move):
        return U, int(len(pairs))
    return V, int(len(start))
