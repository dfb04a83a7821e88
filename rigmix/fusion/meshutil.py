"""Topology and quality helpers for the fusion stage (welded triangle meshes).

All functions take plain arrays: ``V`` (n, 3) positions, ``F`` (m, 3) triangles. Faces with a
repeated corner (collapsed by welding) are "degenerate" and ignored by the topology helpers.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from dfd.mesh import face_normals, weld

__all__ = [
    "stable_argsort",
    "nondegenerate",
    "undirected_edges",
    "face_adjacency",
    "vertex_adjacency",
    "vertex_components",
    "boundary_halfedges",
    "edges_to_loops",
    "triangle_min_angles",
    "edge_counts",
    "average_edge_length",
    "intersecting_face_pairs",
    "dihedral_angles",
]


def unique_ints(a, *, return_inverse=False):
    """``np.unique`` of an integer array (flattened), by sorting.

    The same values (sorted) and inverse as ``np.unique``; numpy's hash-based path for
    integers is many times slower than a sort on the edge and pair keys the fusion builds.

    Returns
    -------
    u : (k,) sorted distinct values, and with ``return_inverse`` ``inv`` ``(n,)`` int64, ``u[inv] == a``.
    """
    a = np.asarray(a).ravel()
    if not return_inverse:
        s = np.sort(a)
        return s[np.r_[True, s[1:] != s[:-1]]] if len(s) else s
    order = stable_argsort(a)
    s = a[order]
    first = np.r_[True, s[1:] != s[:-1]] if len(s) else np.zeros(0, bool)
    inv = np.empty(len(a), np.int64)
    inv[order] = np.cumsum(first) - 1
    return s[first], inv


def stable_argsort(a):
    """``np.argsort(a, kind="stable")`` of a 1-d integer array, ``(n,)`` int64.

    Where the values and the positions fit in one int64 together (non-negative values), each
    value is packed above its position and the packed keys are sorted in place: equal values
    then come in order of position, as a stable sort leaves them, and numpy's plain sort of
    int64 keys is several times faster than its stable argsort (the edge keys of a mesh of a
    million faces: 0.06 s against 0.5 s).
    """
    a = np.asarray(a).ravel()
    n = len(a)
    if n == 0:
        return np.zeros(0, np.int64)
    if a.dtype.kind not in "iu":
        return np.argsort(a, kind="stable").astype(np.int64)
    lo, hi = int(a.min()), int(a.max())
    shift = max(int(n - 1).bit_length(), 1)
    if lo < 0 or hi.bit_length() + shift > 62:
        return np.argsort(a, kind="stable").astype(np.int64)
    packed = (a.astype(np.int64) << shift) | np.arange(n, dtype=np.int64)
    packed.sort()
    return packed & np.int64((1 << shift) - 1)


def unique_rows(P, *, return_inverse=False):
    """``np.unique(P, axis=0)`` of non-negative integer pairs ``P`` ``(k, 2)`` (rows sorted
    lexicographically), by :func:`unique_ints` on one key per row."""
    P = np.asarray(P, np.int64).reshape(-1, 2)
    n = np.int64(int(P.max(initial=0)) + 1)
    out = unique_ints(P[:, 0] * n + P[:, 1], return_inverse=return_inverse)
    key = out[0] if return_inverse else out
    rows = np.stack([key // n, key % n], axis=1)
    return (rows, out[1]) if return_inverse else rows


def nondegenerate(F):
    """``(m,)`` bool: faces whose three corners are distinct."""
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    return (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])


def undirected_edges(F):
    """Edges of every face corner.

    Returns
    -------
    E : (3m, 2) int64
        Directed half-edges ``F[f, c] -> F[f, c+1]`` in corner order (face ``f`` at rows
        ``f, m+f, 2m+f``).
    uE : (k, 2) int64
        Unique undirected edges (sorted pairs).
    emap : (3m,) int64
        ``uE[emap[i]]`` is the undirected edge of half-edge ``i``.
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    S = np.stack([E.min(axis=1), E.max(axis=1)], axis=1)
    uE, emap = unique_rows(S, return_inverse=True)
    return E, uE.reshape(-1, 2), emap.reshape(-1)


def edge_counts(F):
    """Unique undirected edges of the non-degenerate faces and how many faces use each.

    Returns
    -------
    uE : (k, 2) int64
    count : (k,) int64
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    F = F[nondegenerate(F)]
    if len(F) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    _, uE, emap = undirected_edges(F)
    return uE, np.bincount(emap, minlength=len(uE))


def face_adjacency(F):
    """Faces sharing an edge (non-degenerate faces only).

    Returns
    -------
    A : (m, m) scipy.sparse.csr_matrix of bool
        Symmetric, no diagonal.
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    m = len(F)
    ok = nondegenerate(F)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return sp.csr_matrix((m, m), dtype=bool)
    _, uE, emap = undirected_edges(F[idx])
    face = np.tile(idx, 3)
    # incidence edge x face, then face x face through shared edges
    Inc = sp.csr_matrix((np.ones(len(emap)), (emap, face)), shape=(len(uE), m))
    A = (Inc.T @ Inc).tocsr()
    A.setdiag(0)
    A.eliminate_zeros()
    return (A > 0).tocsr()


def vertex_adjacency(F, n):
    """Vertices sharing an edge, ``(n, n)`` symmetric sparse bool matrix."""
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    F = F[nondegenerate(F)]
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.csr_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n))
    A = ((A + A.T) > 0).tocsr()
    return A


def vertex_components(F, n):
    """Connected components of the vertices through the faces.

    Returns
    -------
    labels : (n,) int64
        Component of each vertex (isolated vertices get their own).
    """
    _, labels = connected_components(vertex_adjacency(F, n), directed=False)
    return labels.astype(np.int64)


def boundary_halfedges(F):
    """Half-edges of the faces whose undirected edge has exactly one incident face.

    Returns
    -------
    B : (b, 2) int64
        Directed as in their face (the face lies to the left when walking ``B[i,0] -> B[i,1]``
        on a counter-clockwise face).
    """
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    F = F[nondegenerate(F)]
    if len(F) == 0:
        return np.zeros((0, 2), np.int64)
    E, uE, emap = undirected_edges(F)
    count = np.bincount(emap, minlength=len(uE))
    return E[count[emap] == 1]


def edges_to_loops(B):
    """Chain directed edges into closed loops (or open chains where they do not close).

    Parameters
    ----------
    B : (b, 2) int
        Directed edges, each used once.

    Returns
    -------
    loops : list of (k,) int64 arrays
        Vertex sequences; ``loops[i][-1] -> loops[i][0]`` closes the loop when ``closed[i]``.
    closed : list of bool
    """
    B = np.asarray(B, dtype=np.int64).reshape(-1, 2)
    out: dict[int, list[int]] = {}
    for e, (a, _) in enumerate(B):
        out.setdefault(int(a), []).append(e)
    indeg: dict[int, int] = {}
    for b in B[:, 1]:
        indeg[int(b)] = indeg.get(int(b), 0) + 1
    used = np.zeros(len(B), dtype=bool)
    loops, closed = [], []
    # start open chains at vertices with no incoming edge, then close the rest
    starts = [e for e in range(len(B)) if indeg.get(int(B[e, 0]), 0) == 0]
    order = starts + list(range(len(B)))
    for e0 in order:
        if used[e0]:
            continue
        seq = [int(B[e0, 0])]
        e = e0
        while True:
            used[e] = True
            v = int(B[e, 1])
            if v == seq[0]:
                loops.append(np.array(seq, np.int64))
                closed.append(True)
                break
            cand = [c for c in out.get(v, []) if not used[c]]
            if not cand:
                seq.append(v)
                loops.append(np.array(seq, np.int64))
                closed.append(False)
                break
            seq.append(v)
            e = cand[0]
    return loops, closed


#: Corner indices of the next and the previous corner of a triangle.
_NEXT_CORNER = np.array([1, 2, 0])
_PREVIOUS_CORNER = np.array([2, 0, 1])


def triangle_corner_angles(P):
    """Interior angle at each corner of triangles ``P`` ``(m, 3, 3)``, ``(m, 3)`` radians.

    Corner ``c`` is at ``P[:, c]``; a corner with a zero-length edge gets 0. The three corners
    are computed together (the remeshers call this on a few triangles at a time, where numpy's
    per-call overhead is the cost).
    """
    P = np.asarray(P, dtype=np.float64)
    U = P[:, _NEXT_CORNER] - P
    W = P[:, _PREVIOUS_CORNER] - P
    nu = np.sqrt(np.add.reduce(U * U, axis=2))
    nw = np.sqrt(np.add.reduce(W * W, axis=2))
    cos = np.einsum("ijk,ijk->ij", U, W) / np.maximum(nu * nw, 1e-300)
    return np.where((nu > 0) & (nw > 0), np.arccos(np.clip(cos, -1.0, 1.0)), 0.0)


def cross3(a, b):
    """Cross products of 3-vectors ``a`` and ``b`` ``(..., 3)`` (broadcast), float64.

    The same floats as ``np.cross``, without its axis handling, which costs more than the
    product on the few triangles of a vertex's ring.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def corner_angles(V, F):
    """Interior angle at each corner of the faces ``F`` of ``V``, ``(m, 3)`` radians (0 if degenerate)."""
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    return triangle_corner_angles(np.asarray(V, dtype=np.float64)[F])


def triangle_min_angles(V, F):
    """Smallest interior angle of each triangle, ``(m,)`` degrees (0 for degenerate ones)."""
    return np.degrees(corner_angles(V, F).min(axis=1, initial=np.pi))


def average_edge_length(V, F):
    """Mean length of the unique edges of the non-degenerate faces (0 if none)."""
    uE, _ = edge_counts(F)
    if len(uE) == 0:
        return 0.0
    V = np.asarray(V, dtype=np.float64)
    return float(np.linalg.norm(V[uE[:, 0]] - V[uE[:, 1]], axis=1).mean())


def boxes_meet(lo, hi, qlo, qhi, margin, *, chunk=256):
    """``(len(lo),) bool``: boxes within ``margin`` of one of the boxes ``qlo``, ``qhi`` (the crossing
    repair's boxes much larger than its grid's cells).

    Box ``i`` meets query ``q`` where, on every axis, ``lo[i] <= qhi[q] + margin`` and
    ``qlo[q] <= hi[i] + margin``. The boxes are taken in chunks along x; a chunk is compared only
    with the queries that meet the chunk's own bounding box (a query that misses it misses every
    box in it), so the work follows the pairs that are near, not all pairs.
    """
    out = np.zeros(len(lo), bool)
    if len(lo) == 0 or len(qlo) == 0:
        return out
    qhi_m = qhi + margin
    hi_m = hi + margin
    order = np.argsort(lo[:, 0] + hi[:, 0], kind="stable")
    for s in range(0, len(order), chunk):
        c = order[s:s + chunk]
        clo, chi = lo[c].min(axis=0), hi_m[c].max(axis=0)
        qs = np.flatnonzero(np.all((clo <= qhi_m) & (qlo <= chi), axis=1))
        if not len(qs):
            continue
        meet = lo[c, 0, None] <= qhi_m[None, qs, 0]
        for a in range(3):
            if a:
                meet &= lo[c, a, None] <= qhi_m[None, qs, a]
            meet &= qlo[None, qs, a] <= hi_m[c, a, None]
        out[c] = meet.any(axis=1)
    return out


class TooManyCandidates(RuntimeError):
    """The broad phase of :func:`intersecting_face_pairs` found more candidate pairs than its
    budget: the surface is folded onto itself far beyond what a local repair can undo."""


def _grid_pairs(lo, hi, in_set, max_cells=64, max_pairs=None):
    """Broad phase: pairs of boxes that share a cell of a uniform grid, one of them in ``in_set``.

    Cells are as large as the median box (at least 1/``max_cells`` of the largest box, so that
    no box spans more than ``max_cells`` cells a side); each box is entered in every cell its
    extent touches.

    Parameters
    ----------
    lo, hi : (m, 3) float arrays
        Box corners.
    in_set : (m,) bool array
    max_pairs : int, optional
        Budget of box pairs sharing a cell (counted before any is made).

    Returns
    -------
    a, b : (p,) int64 arrays
        Each unordered pair once, ``a != b``, ``a`` in ``in_set``.

    Raises
    ------
    TooManyCandidates
        More than ``max_pairs`` pairs share a cell.
    """
    ext = (hi - lo).max(axis=1)
    cell = max(float(np.median(ext)), float(ext.max()) / max_cells, 1e-300)
    origin = lo.min(axis=0)
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    n = c1 - c0 + 1
    count = n.prod(axis=1)
    box = np.repeat(np.arange(len(lo)), count)
    k = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
    nx, ny = n[box, 0], n[box, 1]
    dims = c1.max(axis=0) + 1
    key = ((c0[box, 0] + k % nx) * dims[1] + c0[box, 1] + (k // nx) % ny) * dims[2] + c0[box, 2] + k // (nx * ny)
    order = np.argsort(key, kind="stable")
    key, box = key[order], box[order]
    start = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    end = np.r_[start[1:], len(key)]
    group_end = np.repeat(end, end - start)
    later = group_end - np.arange(len(key)) - 1  # members after this one in its cell
    if max_pairs is not None and int(later.sum()) > max_pairs:
        raise TooManyCandidates(f"{int(later.sum())} box pairs share a grid cell (budget {max_pairs})")
    a = np.repeat(box, later)
    first = np.repeat(np.arange(len(key)) + 1, later)
    b = box[first + np.arange(len(a)) - np.repeat(np.cumsum(later) - later, later)]
    keep = (a != b) & (in_set[a] | in_set[b])
    a, b = a[keep], b[keep]
    m = np.int64(len(lo))
    pair = unique_ints(np.minimum(a, b) * m + np.maximum(a, b))  # two boxes share several cells
    a, b = pair // m, pair % m
    swap = ~in_set[a]  # ``a`` from the set
    a[swap], b[swap] = b[swap], a[swap]
    return a, b


def intersecting_face_pairs(V, F, faces=None, *, tol=1e-9, max_candidates=None):
    """Pairs of triangles that cross each other (self-intersections), by the separating axis test.

    Triangles that share a corner (an index, or a position) are never paired: neighbours meet by
    construction. Triangles without area and triangles that only touch (within ``tol`` times
    the mesh's extent) do not count.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    faces : (k,) int array, optional
        Only pairs with at least one of these faces (default: all).
    tol : float
    max_candidates : int, optional
        Budget of the broad phase (pairs of faces whose boxes share a grid cell); a healthy
        surface has about 10 per face, one folded onto itself everywhere a thousand.

    Returns
    -------
    (p, 2) int64
        Face index pairs ``(a, b)``, ``a`` from ``faces``; each unordered pair once.

    Raises
    ------
    TooManyCandidates
        Over ``max_candidates``.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if len(F) < 2:
        return np.zeros((0, 2), np.int64)
    T = V[F]
    lo, hi = T.min(axis=1), T.max(axis=1)
    faces = np.arange(len(F)) if faces is None else unique_ints(np.asarray(faces, np.int64))
    if len(faces) == 0:
        return np.zeros((0, 2), np.int64)
    eps = tol * float(np.ptp(V, axis=0).max() or 1.0)
    sub = None
    if max_candidates is None and len(faces) < len(F):
        # a face whose box misses the joint box of ``faces`` pairs with none of them: the rest
        # runs on those that meet it (the broad phase's candidates are fewer, the pairs whose
        # boxes meet the same, in the same order, since ``sub`` is increasing)
        qlo, qhi = lo[faces].min(axis=0), hi[faces].max(axis=0)
        sub = np.flatnonzero(np.all((lo <= qhi + eps) & (qlo <= hi + eps), axis=1))
        F, T, lo, hi = F[sub], T[sub], lo[sub], hi[sub]
        faces = np.searchsorted(sub, faces)
    in_set = np.zeros(len(F), bool)
    in_set[faces] = True
    a, b = _grid_pairs(lo - eps, hi + eps, in_set, max_pairs=max_candidates)
    keep = np.all((lo[a] <= hi[b] + eps) & (lo[b] <= hi[a] + eps), axis=1)
    keep &= ~(F[a][:, :, None] == F[b][:, None, :]).any(axis=(1, 2))
    a, b = a[keep], b[keep]
    # a corner at the same position counts as shared (split or duplicated seam vertices), and a
    # triangle without area crosses nothing
    same = (T[a][:, :, None, :] == T[b][:, None, :, :]).all(axis=3).any(axis=(1, 2))
    area2 = np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)
    flat = area2 <= (eps * eps)
    keep = ~same & ~flat[a] & ~flat[b]
    a, b = a[keep], b[keep]
    if len(a) == 0:
        return np.zeros((0, 2), np.int64)
    pairs = _crossing(T[a], T[b], a, b, eps)
    return pairs if sub is None else sub[pairs]


def _crossing(A, B, a, b, eps):
    """The pairs ``(a, b)`` whose triangles ``A``, ``B`` ``(p, 3, 3)`` no axis separates (by more
    than ``eps``): the two normals, the nine edge-edge cross products and the six in-plane edge
    normals. A pair leaves the test at the first axis that separates it, so most pairs (boxes
    that overlap, triangles that do not) cost one or two axes.

    Returns
    -------
    (q, 2) int64
    """
    ea = np.roll(A, -1, axis=1) - A
    eb = np.roll(B, -1, axis=1) - B
    na = cross3(ea[:, 0], ea[:, 1])
    nb = cross3(eb[:, 0], eb[:, 1])
    # an axis shorter than this (parallel edges) separates nothing
    scale = 1e-12 * np.maximum(np.sqrt((ea * ea).sum(axis=2)).max(axis=1) * np.sqrt((eb * eb).sum(axis=2)).max(axis=1),
                               1e-300)
    axes = [lambda: na, lambda: nb]
    axes += [lambda i=i, j=j: cross3(ea[:, i], eb[:, j]) for i in range(3) for j in range(3)]
    axes += [lambda i=i: cross3(na, ea[:, i]) for i in range(3)] + [lambda j=j: cross3(nb, eb[:, j]) for j in range(3)]
    alive = np.arange(len(a))
    for axis in axes:
        ax = axis()
        norm = np.sqrt((ax * ax).sum(axis=1))
        u = ax / np.maximum(norm, 1e-300)[:, None]
        pa = np.einsum("pkc,pc->pk", A, u)
        pb = np.einsum("pkc,pc->pk", B, u)
        apart = (pa.max(axis=1) <= pb.min(axis=1) + eps) | (pb.max(axis=1) <= pa.min(axis=1) + eps)
        separated = (norm > scale) & apart
        if separated.any():
            keep = ~separated
            alive, A, B, ea, eb, na, nb, scale = (x[keep] for x in (alive, A, B, ea, eb, na, nb, scale))
        if not len(alive):
            break
    return np.stack([a[alive], b[alive]], axis=1)


def dihedral_angles(V, F, faces=None):
    """Angles between the normals of neighbouring faces, degrees.

    Parameters
    ----------
    V : (n, 3) float array
        Split vertices: welded by position here, so faces split at a UV or normal seam are
        neighbours.
    F : (m, 3) int array
    faces : (m,) bool or (k,) int array, optional
        The faces measured (default all); an edge counts when exactly two of them with a
        non-zero area share it.

    Returns
    -------
    (e,) float64
        One angle per such edge, in ``[0, 180]``: 0 across a flat edge, 180 across a fold onto
        itself (or two faces of opposite orientation).
    """
    Vw, _, Fw = weld(V, F)
    if faces is not None:
        Fw = Fw[faces]
    N = face_normals(Vw, Fw)
    ok = np.linalg.norm(N, axis=1) > 0
    Fw, N = Fw[ok], N[ok]
    if not len(Fw):
        return np.zeros(0)
    _, uE, emap = undirected_edges(Fw)
    count = np.bincount(emap, minlength=len(uE))
    order = np.argsort(emap, kind="stable")  # the half-edges of each edge side by side
    start = np.searchsorted(emap[order], np.flatnonzero(count == 2))
    m = len(Fw)
    a, b = order[start] % m, order[start + 1] % m  # half-edge i belongs to face i mod m
    cos = np.clip(np.einsum("ij,ij->i", N[a], N[b]), -1.0, 1.0)
    return np.degrees(np.arccos(cos))
