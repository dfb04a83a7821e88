"""Mesh operators used by every dfd stage and by rigmix: checks, normalization, hashing,
welding and the welded edge graph, smoothing, normals and areas.

Rendering and the feature field work in a normalized frame (bounding-box centre at the origin,
largest half-extent 1, PIPELINE.md section 6); everything public takes and returns the mesh's
own coordinates, and stores the :class:`Normalization` needed to go between the two.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from dfd.errors import DfdInputError

__all__ = [
    "Normalization",
    "check_mesh",
    "face_areas",
    "face_normals",
    "mesh_hash",
    "normalization",
    "smooth",
    "surface_samples",
    "vertex_normals",
    "weld",
    "welded_graph",
]


@dataclass(frozen=True)
class Normalization:
    """Similarity that maps mesh coordinates to the normalized frame: ``p_n = (p - center) * scale``.

    Attributes
    ----------
    center : (3,) float64
        Centre of the axis-aligned bounding box, in mesh units.
    scale : float
        ``1 / largest half-extent``, so the normalized mesh fits in ``[-1, 1]^3``.
    """

    center: np.ndarray
    scale: float

    def apply(self, P):
        """Mesh coordinates ``(n, 3)`` -> normalized coordinates ``(n, 3)`` float64."""
        return (np.asarray(P, dtype=np.float64) - self.center) * self.scale

    def invert(self, Q):
        """Normalized coordinates ``(n, 3)`` -> mesh coordinates ``(n, 3)`` float64."""
        return np.asarray(Q, dtype=np.float64) / self.scale + self.center


def check_mesh(V, F, *, stage="dfd"):
    """Validate and convert a triangle mesh.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Indices into ``V``.
    stage : str
        Named in error messages.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise DfdInputError(f"{stage}: vertices must be a non-empty (n, 3) array, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise DfdInputError(f"{stage}: faces must be a non-empty (m, 3) array of triangles, got shape {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise DfdInputError(f"{stage}: faces must be integer indices, got dtype {F.dtype}")
    F = F.astype(np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise DfdInputError(f"{stage}: face indices must lie in [0, {len(V)}), got [{F.min()}, {F.max()}]")
    if not np.isfinite(V).all():
        raise DfdInputError(f"{stage}: vertex positions contain NaN or infinity")
    return V, F


def normalization(V) -> Normalization:
    """The normalization of section 6: bounding-box centre to the origin, half-extent 1.

    Parameters
    ----------
    V : (n, 3) float array

    Returns
    -------
    Normalization
    """
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    half = float((hi - lo).max()) / 2.0
    if half <= 0:
        raise DfdInputError("dfd: the mesh has zero extent (all vertices coincide)")
    return Normalization(center=(lo + hi) / 2.0, scale=1.0 / half)


def mesh_hash(V, F) -> str:
    """SHA-256 hex digest of the positions (float64) and triangles (int64)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(V, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(F, dtype=np.int64).tobytes())
    return h.hexdigest()


def _group_positions(P):
    """Equal rows of ``P`` ``(n, 3)`` float64: the first row of each group and the group of each
    row ``(n,)``, groups in lexicographic order.

    What ``np.unique(P, axis=0, return_index=True, return_inverse=True)`` gives (rows compared
    as numbers: ``-0.0`` equals ``0.0``, a row with a NaN equals no other), by a stable
    lexicographic sort of the columns: about twice as fast on a million rows."""
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    order = np.lexsort((P[:, 2], P[:, 1], P[:, 0]))
    Ps = P[order]
    new = np.r_[True, np.any(Ps[1:] != Ps[:-1], axis=1)]
    inverse = np.empty(len(P), np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse


def weld(V, F=None, *, tol=0.0):
    """Merge vertices at the same position (glTF meshes are split at every UV, normal and
    material seam, and flat-shaded assets at every face).

    Parameters
    ----------
    V : (n, 3) float array
        Split vertex positions.
    F : (m, 3) int array, optional
        Triangles over ``V``; returned re-indexed onto the welded vertices, with the faces that
        collapse (two equal corners after welding) kept, so face order and count never change.
    tol : float
        Positions closer than about ``tol`` (same cell of a ``tol`` grid) are merged; ``0`` merges
        exactly equal positions only.

    Returns
    -------
    Vw : (k, 3) float64
        Welded positions (the first split vertex of each group, in order of first appearance).
    index : (n,) int64
        ``Vw[index] == V`` (up to ``tol``): the welded vertex of each split vertex.
    Fw : (m, 3) int64
        ``index[F]``; only when ``F`` is given.
    """
    V = np.asarray(V, dtype=np.float64)
    if len(V) == 0:
        index = np.zeros(0, dtype=np.int64)
        Vw = V.reshape(0, 3)
    else:
        key = V if tol <= 0 else np.round(V / tol)
        first, inverse = _group_positions(key)
        # renumber groups in order of first appearance, so welding is stable and predictable
        order = np.argsort(first, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        index = rank[inverse].astype(np.int64)
        Vw = V[np.sort(first)]
    if F is None:
        return Vw, index
    return Vw, index, index[np.asarray(F, dtype=np.int64)]


def welded_graph(V, F, *, lengths=True):
    """The mesh welded by position (:func:`weld`) and its edge graph.

    Every edge of every welded face is an edge of the graph, including the edges of faces that
    collapse to a segment; an edge collapsed to a point is not (no self-loops).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    lengths : bool
        ``True``: entry ``(a, b)`` is the length of welded edge ``ab`` plus ``1e-12`` (so a
        zero-length edge stays an edge; the edges are deduplicated first, each once).
        ``False``: entries are 1 (the 0/1 adjacency, built without sorting the edges: at a
        million faces the sort is most of the cost).

    Returns
    -------
    Vw : (k, 3) float64
        Welded positions.
    index : (n,) int64
        Welded vertex of each input vertex.
    G : (k, k) scipy.sparse.csr_matrix, float64
        Symmetric, canonical (sorted indices, no duplicates).
    """
    import scipy.sparse as sp  # imported where used: dfd.mesh stays light to import

    Vw, index, Fw = weld(np.asarray(V, np.float64), np.asarray(F, np.int64).reshape(-1, 3))
    k = len(Vw)
    E = np.concatenate([Fw[:, [0, 1]], Fw[:, [1, 2]], Fw[:, [2, 0]]])
    E = E[E[:, 0] != E[:, 1]]
    if not lengths:
        A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(k, k)).tocsr()
        return Vw, index, ((A + A.T) > 0).astype(np.float64).tocsr()
    E = np.unique(np.sort(E, axis=1), axis=0)  # each edge once: duplicates would sum their lengths
    d = np.linalg.norm(Vw[E[:, 0]] - Vw[E[:, 1]], axis=1) + 1e-12
    G = sp.csr_matrix((np.r_[d, d], (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(k, k))
    return Vw, index, G


def smooth(A, X, free, *, iterations=10, alpha=0.5):
    """Laplacian smoothing of the ``free`` rows, the others fixed:
    ``iterations`` of ``x <- (1 - alpha) x + alpha mean(neighbours)``.

    ``alpha`` is the fraction of the way to the neighbours' mean taken per iteration: 0 leaves
    ``X`` unchanged, 1 replaces each free row by its neighbours' mean. Every smoothing of rigmix
    and dfd states its ``alpha`` in this sense.

    Parameters
    ----------
    A : (k, k) scipy.sparse matrix, float64
        Edge weights (a 0/1 adjacency for the uniform Laplacian); the mean is
        ``(A @ X) / max(degree, 1)`` with ``degree = A.sum(axis=1)``.
    X : (k,) or (k, c) float array
        Values per vertex.
    free : (k,) bool array
        Rows that move; a row without neighbours never does.
    iterations : int
    alpha : float

    Returns
    -------
    (k,) or (k, c) float64
        A new array; rows not free equal ``X``'s.
    """
    X = np.array(X, dtype=np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    rows = np.flatnonzero(np.asarray(free, bool) & (deg > 0))
    if len(rows) == 0 or iterations <= 0:
        return X
    Ar = A[rows]
    scale = np.maximum(deg, 1)[rows]
    if X.ndim == 2:
        scale = scale[:, None]
    for _ in range(iterations):
        X[rows] = (1 - alpha) * X[rows] + alpha * ((Ar @ X) / scale)
    return X


def face_normals(V, F):
    """Unit normals ``(m, 3)`` of the triangles (zero for degenerate ones)."""
    V = np.asarray(V, dtype=np.float64)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    length = np.linalg.norm(N, axis=1, keepdims=True)
    return np.divide(N, length, out=np.zeros_like(N), where=length > 0)


def face_areas(V, F):
    """Areas ``(m,)`` of the triangles."""
    V = np.asarray(V, dtype=np.float64)
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def surface_samples(V, F, n, rng):
    """``n`` points drawn uniformly by area on the triangles, ``(n, 3)``.

    Independent of the tessellation: a remeshed region and a coarse original one are sampled
    equally densely. ``rng`` is a :class:`numpy.random.Generator`.

    Raises
    ------
    DfdInputError
        The mesh has zero area.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    A = face_areas(V, F)
    if len(F) == 0 or A.sum() <= 0:
        raise DfdInputError("mesh: cannot sample a surface with zero area")
    face = rng.choice(len(F), n, p=A / A.sum())
    s, r = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1 - s, s * (1 - r), s * r], axis=1)
    return np.einsum("nk,nkj->nj", bary, V[F[face]])


def vertex_normals(V, F):
    """Area-weighted unit vertex normals ``(n, 3)`` (zero for isolated vertices)."""
    V = np.asarray(V, dtype=np.float64)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    out = np.zeros_like(V)
    for k in range(3):
        np.add.at(out, F[:, k], N)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=np.zeros_like(out), where=length > 0)
