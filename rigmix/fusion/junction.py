"""The junction surface: isosurface, cut, and loop-to-loop bridging (PIPELINE.md section 3).

The zero isosurface of the blended field is cut where preserved faces take over (its part
closer than a voxel or so to a preserved face is removed), which leaves it with boundary loops
parallel to the preserved boundary loops. Each preserved loop is then bridged to the nearest
isosurface loop (or, where the junction band is thinner than the cut, directly to a preserved
loop of another input) by a minimum-length loop-to-loop triangulation (dynamic programming,
Fuchs-Kedem-Uselton style), so the result has no gap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .meshutil import boundary_halfedges, edges_to_loops, nondegenerate, undirected_edges, vertex_components

log = logging.getLogger(__name__)

__all__ = [
    "isosurface",
    "drop_cancelling_faces",
    "clip_mesh",
    "remove_unreferenced",
    "Loop",
    "boundary_loops",
    "bridge_loops",
    "loop_distance",
    "match_loops",
    "orientation_agrees",
    "keep_components_touching",
]


def remove_unreferenced(V, F):
    """Drop vertices no face uses.

    Returns
    -------
    V2 : (k, 3), F2 : (m, 3), old : (k,) int64
        ``V2 = V[old]``.
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    old = np.flatnonzero(used)
    new = np.full(len(V), -1, np.int64)
    new[old] = np.arange(len(old))
    return np.asarray(V)[old], new[F], old


def isosurface(field, origin, voxel):
    """Zero isosurface of a signed field (negative inside), outward-oriented triangles.

    Parameters
    ----------
    field : (nx, ny, nz) float array
        Samples at ``origin + voxel * (i, j, k)``.
    origin : (3,) float
    voxel : float

    Returns
    -------
    V : (k, 3) float64, F : (m, 3) int64
        Empty when the field does not change sign.
    """
    from skimage.measure import marching_cubes

    field = np.asarray(field, dtype=np.float64)
    if field.min() >= 0 or field.max() <= 0 or min(field.shape) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    # samples exactly on the level (a planar input face through grid points) make the
    # ambiguous cube cases that emit a triangle and its reverse: nudge them outside
    tiny = np.finfo(np.float32).eps * max(float(np.abs(field).max()), 1e-30)
    field = np.where(field == 0.0, tiny, field)
    V, F, _, _ = marching_cubes(field, level=0.0, spacing=(voxel, voxel, voxel), allow_degenerate=False)
    V = V.astype(np.float64) + np.asarray(origin, dtype=np.float64)
    # with gradient_direction="descent" (default) skimage's triangles face increasing values,
    # i.e. outward for a field negative inside (checked by the sphere test)
    F = np.ascontiguousarray(F.astype(np.int64))
    return V, drop_cancelling_faces(F)


def drop_cancelling_faces(F):
    """Remove a triangle together with its reverse (a zero-thickness fin, three or four faces
    on one edge) and keep one copy of plain duplicates.

    Parameters
    ----------
    F : (m, 3) int array

    Returns
    -------
    (k, 3) int array
        The rows of ``F`` kept, in order. Of a group of faces over the same three vertices, one
        face of the majority orientation is kept; none where the orientations cancel.
    """
    if len(F) == 0:
        return F
    key = np.sort(F, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    keep = cnt[inv] == 1
    for g in np.flatnonzero(cnt > 1):
        rows = np.flatnonzero(inv == g)
        # orientation: the cyclic order of the sorted triple, +1 or -1
        sign = [1 if tuple(np.roll(F[r], -int(np.argmin(F[r])))) == tuple(key[r]) else -1 for r in rows]
        net = sum(sign)
        for r, sg in zip(rows, sign):
            if net != 0 and sg == np.sign(net):
                keep[r] = True
                break
    return F[keep]


def clip_mesh(V, F, s):
    """Keep the part of a triangle mesh where ``s > 0``, splitting the triangles ``s`` crosses.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    s : (n,) float array
        Piecewise-linear scalar on the vertices.

    Returns
    -------
    V2 : (k, 3) float64
        Kept old vertices first (in order), then one new vertex per crossed edge.
    F2 : (q, 3) int64
        Orientation of the input kept.
    old : (k,) int64
        Source vertex of each output vertex, ``-1`` for new (cut) vertices.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    s = np.asarray(s, dtype=np.float64).copy()
    s[s == 0] = -1e-300  # a vertex exactly on the cut counts as removed
    inside = s > 0
    if len(F) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    E, uE, emap = undirected_edges(F)
    cross = inside[uE[:, 0]] != inside[uE[:, 1]]
    ce = np.flatnonzero(cross)
    a, b = uE[ce, 0], uE[ce, 1]
    t = s[a] / (s[a] - s[b])
    Pn = V[a] + t[:, None] * (V[b] - V[a])
    n = len(V)
    cut_id = np.full(len(uE), -1, np.int64)
    cut_id[ce] = n + np.arange(len(ce))
    m = len(F)
    # x[f, c]: the cut vertex on edge F[f,c] -> F[f,c+1]
    X = cut_id[emap].reshape(3, m).T
    ins = inside[F]
    k = ins.sum(axis=1)
    out = [F[k == 3]]
    for r in range(3):
        # one vertex inside: it sits at corner r
        f = (k == 1) & ins[:, r]
        if f.any():
            a0 = F[f, r]
            xa = X[f, r]              # edge r -> r+1
            xc = X[f, (r + 2) % 3]    # edge r+2 -> r
            out.append(np.stack([a0, xa, xc], axis=1))
        # two inside: corner r is the outside one
        f = (k == 2) & ~ins[:, r]
        if f.any():
            b0 = F[f, (r + 1) % 3]
            c0 = F[f, (r + 2) % 3]
            xr = X[f, r]              # edge r -> r+1 (outside -> b0)
            xl = X[f, (r + 2) % 3]    # edge r+2 -> r (c0 -> outside)
            out.append(np.stack([b0, c0, xl], axis=1))
            out.append(np.stack([b0, xl, xr], axis=1))
    F2 = np.concatenate(out).astype(np.int64)
    Vall = np.concatenate([V, Pn])
    src = np.concatenate([np.arange(n), np.full(len(Pn), -1)])
    V2, F2, keep = remove_unreferenced(Vall, F2)
    return V2, F2, src[keep]


@dataclass(frozen=True)
class Loop:
    """A closed boundary loop.

    Attributes
    ----------
    source : int
        Which piece it bounds: an input index, or ``-1`` for the isosurface.
    vertices : (k,) int64
        Vertex ids in that piece, in boundary order (the piece lies to the left).
    positions : (k, 3) float64
    hole_edges : int
        Its edges along a hole of its input's mesh (:func:`.seams.preserved_loops`: a seam
        closed along the hole it runs into); 0 for a seam loop.
    """

    source: int
    vertices: np.ndarray
    positions: np.ndarray
    hole_edges: int = 0


def boundary_loops(V, F, source=-1, *, halfedges=None):
    """Closed boundary loops of a mesh (open chains are returned separately).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    source : int
        Stored in each :class:`Loop`.
    halfedges : (b, 2) int array, optional
        Boundary half-edges to chain instead of all the boundary edges of ``F``.

    Returns
    -------
    loops : list of Loop
    chains : list of (k,) int64 arrays
        Open chains (boundaries through non-manifold vertices).
    """
    B = boundary_halfedges(F) if halfedges is None else np.asarray(halfedges, np.int64).reshape(-1, 2)
    seqs, closed = edges_to_loops(B)
    loops, chains = [], []
    for q, c in zip(seqs, closed):
        if c and len(q) >= 3:
            loops.append(Loop(source, q, np.asarray(V)[q]))
        else:
            chains.append(q)
    return loops, chains


def _resample(P, k):
    """``k`` points evenly spaced by arc length along closed polyline ``P``."""
    Q = np.concatenate([P, P[:1]])
    seg = np.linalg.norm(np.diff(Q, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return np.repeat(P[:1], k, axis=0)
    t = np.linspace(0.0, cum[-1], k, endpoint=False)
    return np.stack([np.interp(t, cum, Q[:, a]) for a in range(3)], axis=1)


def loop_distance(A, B):
    """Symmetric mean closest-point distance between two loops' vertex sets (a matching cost)."""
    from scipy.spatial import cKDTree

    da, _ = cKDTree(B).query(A)
    db, _ = cKDTree(A).query(B)
    return 0.5 * (da.mean() + db.mean())


def match_loops(preserved, others, *, max_cost):
    """Pair each preserved loop with a partner loop, greedily by increasing cost.

    Parameters
    ----------
    preserved : list of Loop
        Boundary loops of the preserved faces (one per seam).
    others : list of Loop
        Candidate partners: isosurface loops (``source == -1``).
    max_cost : float
        Pairs farther apart than this (see :func:`loop_distance`) are not matched.

    Returns
    -------
    pairs : list of (int, str, int)
        ``(i, kind, j)``: preserved loop ``i`` with ``others[j]`` (``kind == "iso"``) or with
        preserved loop ``j`` of another input (``kind == "preserved"``).
    """
    cand = []
    for i, P in enumerate(preserved):
        for j, Q in enumerate(others):
            cand.append((loop_distance(P.positions, Q.positions), i, "iso", j))
        for j in range(i + 1, len(preserved)):
            Q = preserved[j]
            if Q.source != P.source:
                # an isosurface partner follows the blended shape: prefer it at similar cost
                cand.append((2.0 * loop_distance(P.positions, Q.positions), i, "preserved", j))
    cand.sort(key=lambda c: c[0])
    used_p, used_o, pairs = set(), set(), []
    for cost, i, kind, j in cand:
        if cost > max_cost or i in used_p:
            continue
        if kind == "iso" and j in used_o:
            continue
        if kind == "preserved" and j in used_p:
            continue
        used_p.add(i)
        (used_o if kind == "iso" else used_p).add(j)
        pairs.append((i, kind, j))
    return pairs


def bridge_loops(P, Q):
    """Triangulate the band between two boundary loops facing each other.

    ``P`` and ``Q`` are boundary loops of two pieces (each piece to the left of its loop), so
    they run in opposite directions around the gap. The strip between them is the
    minimum-total-diagonal-length triangulation (dynamic programming over the two loops, exact
    and vectorized per row), starting from the pair of closest vertices.

    Parameters
    ----------
    P : (n, 3) float array
        Positions of the first loop, in its boundary order.
    Q : (m, 3) float array
        Positions of the second loop, in its boundary order.

    Returns
    -------
    T : (n + m, 3) int64
        Triangles over the concatenated vertices ``[P, Q]`` (indices ``< n`` are P's), oriented
        consistently with both pieces.
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    n, m = len(P), len(Q)
    # strip order: P reversed; Q as is; both then run the same way around the gap
    pi = np.arange(n)[::-1]
    Ps = P[pi]
    qi0 = int(np.argmin(np.linalg.norm(Q - Ps[0], axis=1)))
    qi = np.roll(np.arange(m), -qi0)
    # closing: index n of P' is P'[0], index m of Q' is Q'[0]
    pe = np.concatenate([pi, pi[:1]])
    qe = np.concatenate([qi, qi[:1]])
    Pe, Qe = P[pe], Q[qe]
    D = np.linalg.norm(Pe[:, None, :] - Qe[None, :, :], axis=2)  # (n+1, m+1)
    cost = np.full((n + 1, m + 1), np.inf)
    came = np.zeros((n + 1, m + 1), np.int8)  # 1: from (i-1, j), 2: from (i, j-1)
    cost[0, 0] = D[0, 0]
    C0 = np.cumsum(D[0, 1:])
    cost[0, 1:] = D[0, 0] + C0
    came[0, 1:] = 2
    for i in range(1, n + 1):
        A = cost[i - 1] + D[i]  # arriving from the row below
        # cost[i, j] = min_k<=j (A[k] + sum_{l=k+1..j} D[i, l])
        S = np.concatenate([[0.0], np.cumsum(D[i, 1:])])
        M = np.minimum.accumulate(A - S)
        cost[i] = M + S
        came[i] = np.where(np.isclose(cost[i], A) | (A <= cost[i]), 1, 2)
        came[i, 0] = 1
    tris = []
    i, j = n, m
    while i > 0 or j > 0:
        if came[i, j] == 1:
            tris.append((pe[i - 1], pe[i], n + qe[j]))
            i -= 1
        else:
            tris.append((pe[i], n + qe[j], n + qe[j - 1]))
            j -= 1
    return np.array(tris[::-1], dtype=np.int64)


def orientation_agrees(P, Q):
    """True when the loops run in opposite directions around the gap (as they should)."""
    k = 64
    A = _resample(np.asarray(P, float)[::-1], k)
    B = _resample(np.asarray(Q, float), k)
    Br = B[::-1]
    best_same = min(np.linalg.norm(A - np.roll(B, r, axis=0), axis=1).mean() for r in range(k))
    best_rev = min(np.linalg.norm(A - np.roll(Br, r, axis=0), axis=1).mean() for r in range(k))
    return best_same <= best_rev * 1.05


def keep_components_touching(F, n, keep_vertices):
    """Faces of the vertex-connected components that contain any of ``keep_vertices``."""
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    if len(F) == 0:
        return np.zeros(0, bool)
    lab = vertex_components(F, n)
    good = np.zeros(lab.max() + 1, bool)
    good[lab[np.asarray(keep_vertices, np.int64)]] = True
    return good[lab[F[:, 0]]] & nondegenerate(F)
