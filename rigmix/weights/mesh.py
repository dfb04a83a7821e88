"""The welded mesh and its operators for weight filling (cached per ``(V, F)``).

Laplacian, lumped areas, adjacency and components of the mesh welded by position, and the
constrained solves every fill method shares. Degenerate geometry is handled here (see the
package docstring).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from dfd.mesh import face_areas, welded_graph

from ..geometry import bounding_box_diagonal

__all__ = [
    "WeldedMesh", "welded_mesh", "array_key", "weld_rows", "nearest_vertex", "solvable_rows", "solve_fixed",
    "fill_orphans", "bilaplacian", "smooth_unknown", "edge_scale", "sparsify",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WeldedMesh:
    """The welded mesh and its operators (:func:`welded_mesh`, cached per ``(V, F, uniform)``).

    Attributes
    ----------
    V : (k, 3) welded positions.
    F : (f, 3) clean faces (no collapsed, duplicate or zero-area face).
    index : (n,) welded vertex of each input vertex.
    L : (k, k) regularized cotangent Laplacian (negative semi-definite).
    M : (k,) lumped Voronoi areas (clamped below).
    A : (k, k) 0/1 adjacency over every welded edge.
    component : (k,) connected component label.
    """

    V: np.ndarray
    F: np.ndarray
    index: np.ndarray
    L: sp.csr_matrix
    M: np.ndarray
    A: sp.csr_matrix
    component: np.ndarray


_CACHE: dict[bytes, WeldedMesh] = {}


def array_key(*arrays) -> bytes:
    """A 16-byte digest of the shapes and bytes of ``arrays`` (a memo key for meshes and planes)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.digest()


def _clean_faces(V, F):
    """Faces without repeated corners, duplicates or (near) zero area, ``(f, 3)``."""
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    if len(F) == 0:
        return F
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    F = F[np.sort(first)]
    area = face_areas(V, F)
    tiny = max(bounding_box_diagonal(V) ** 2 * 1e-14, 1e-300)
    return F[area > tiny]


def welded_mesh(V, F, *, uniform=1e-3) -> WeldedMesh:
    """The mesh welded by position, with its Laplacian, areas, adjacency and components.

    Parameters
    ----------
    V : (n, 3) float array
        Vertex positions (split glTF vertices are welded by position).
    F : (m, 3) int array
    uniform : float
        Weight of the uniform graph Laplacian added over every welded edge, relative to the mean
        absolute cotangent weight (keeps every connected component connected for the solvers).

    Returns
    -------
    WeldedMesh
        Cached: the last 8 ``(V, F, uniform)`` return the same object (its arrays are shared,
        never modify them).
    """
    key = array_key(V, F, np.float64(uniform))
    if key in _CACHE:
        return _CACHE[key]
    # adjacency over every welded edge, including edges of faces that collapse to a segment
    Vw, index, A = welded_graph(V, F, lengths=False)
    Fw = index[np.asarray(F, dtype=np.int64).reshape(-1, 3)]
    k = len(Vw)
    _, component = connected_components(A, directed=False)
    Fc = _clean_faces(Vw, Fw)
    if len(Fc):
        C = igl.cotmatrix(Vw, Fc)
        if C.nnz == 0:
            raise RuntimeError("weights: igl.cotmatrix returned an empty matrix")
        C = sp.csr_matrix(C)
        C.resize((k, k))  # igl sizes by the largest referenced vertex
        C.setdiag(0.0)
        C.eliminate_zeros()
        # raw cotangent weights (negative across obtuse angles): the stiffness matrix stays
        # positive semi-definite, and clamping them worsens the fill (band benchmark, Fox: 0.43
        # clamped against 0.39)
        C.data = np.nan_to_num(C.data, nan=0.0, posinf=0.0, neginf=0.0)
        scale = float(np.abs(C.data).mean()) if C.nnz else 1.0
        m = np.zeros(k)
        mv = np.asarray(igl.massmatrix(Vw, Fc, igl.MASSMATRIX_TYPE_VORONOI).diagonal()).ravel()
        m[: len(mv)] = mv
    else:
        C = sp.csr_matrix((k, k))
        scale = 1.0
        m = np.zeros(k)
    Wgt = C + uniform * scale * A
    L = (Wgt - sp.diags(np.asarray(Wgt.sum(axis=1)).ravel())).tocsr()
    m = np.nan_to_num(m, nan=0.0)
    mean_m = m[m > 0].mean() if np.any(m > 0) else 1.0
    m = np.maximum(m, 1e-2 * mean_m)
    out = WeldedMesh(Vw, Fc, index, L, m, A, component)
    if len(_CACHE) >= 8:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = out
    return out


def weld_rows(W, index, unknown, k):
    """Welded weights (mean of the known split rows) and the welded unknown mask.

    A welded vertex is unknown as soon as one of its split vertices is.

    Parameters
    ----------
    W : (n, J) float array
    index : (n,) int array
        Welded vertex of each split vertex (:attr:`WeldedMesh.index`).
    unknown : (n,) bool array
    k : int
        Number of welded vertices.

    Returns
    -------
    Ww : (k, J) float64
        Zero on welded vertices with no known split vertex.
    unk : (k,) bool
    """
    unk = np.zeros(k, dtype=bool)
    unk[index[unknown]] = True
    Ww = np.zeros((k, W.shape[1]))
    cnt = np.zeros(k)
    known = ~unknown
    np.add.at(Ww, index[known], W[known])
    np.add.at(cnt, index[known], 1.0)
    ok = cnt > 0
    Ww[ok] /= cnt[ok, None]
    return Ww, unk


# --------------------------------------------------------------------------------------------
# Methods (all on the welded mesh: W (k, J), unk (k,) bool; return (k, J) with known rows kept)
# --------------------------------------------------------------------------------------------


def nearest_vertex(Vw, W, unk, rows):
    """Weights ``(r, J)`` of the closest known welded vertex (Euclidean) for ``rows`` ``(r,)``.

    ``Vw`` (k, 3) welded positions, ``W`` (k, J) welded weights, ``unk`` (k,) bool unknown mask.
    """
    tree = cKDTree(Vw[~unk])
    _, i = tree.query(Vw[rows])
    return W[np.flatnonzero(~unk)[i]]


def solvable_rows(g: WeldedMesh, unk):
    """``(k,)`` bool: unknown vertices whose component has a known vertex (the others would be
    singular); ``unk`` (k,) bool."""
    has_known = np.zeros(g.component.max() + 1 if len(g.component) else 0, dtype=bool)
    has_known[g.component[~unk]] = True
    return unk & has_known[g.component]


def solve_fixed(Q, W, unk, solve):
    """Minimize ``w^T Q w`` per column for the rows ``solve``, every other row fixed.

    ``Q`` (k, k) sparse, ``W`` (k, J), ``unk`` and ``solve`` (k,) bool. Returns ``(k, J)``:
    ``W`` with the ``solve`` rows replaced by the minimizer.
    """
    out = W.copy()
    s = np.flatnonzero(solve)
    if len(s) == 0:
        return out
    k = np.flatnonzero(~solve)
    Q = sp.csr_matrix(Q)
    Quu = Q[s][:, s].tocsc()
    rhs = -(Q[s][:, k] @ W[k])
    lu = splu(Quu)
    out[s] = lu.solve(np.ascontiguousarray(rhs))
    return out


def fill_orphans(g: WeldedMesh, W, unk, solve):
    """Fill the unknown vertices of components without any known vertex: closest known vertex.

    ``W`` (k, J), ``unk`` and ``solve`` (k,) bool (``solve``: the rows a solver filled). Returns
    ``(k, J)``, a copy where anything changed.
    """
    orphan = unk & ~solve
    if np.any(orphan):
        log.debug("weights: %d unknown vertices in components with no known vertex", orphan.sum())
        W = W.copy()
        W[orphan] = nearest_vertex(g.V, W, unk, np.flatnonzero(orphan))
    return W


def bilaplacian(g: WeldedMesh):
    """The squared Laplacian energy of the Robust Skin Weights Transfer, ``-L + L M^-1 L``
    ``(k, k)`` csr."""
    return (-g.L + g.L @ sp.diags(1.0 / g.M) @ g.L).tocsr()


def smooth_unknown(g: WeldedMesh, W, unk, *, iterations=10, keep=0.8):
    """``iterations`` of ``w <- keep w + (1 - keep) mean(neighbours)`` on the unknown rows.

    ``W`` (k, J) welded weights, ``unk`` (k,) bool rows to smooth (the others fixed). Returns
    ``(k, J)``. This is :func:`dfd.mesh.smooth` with ``alpha = 1 - keep``, written with its own
    arithmetic (the mean as a product with ``1 / degree``), to which the fills' results are
    bit-for-bit.
    """
    deg = np.asarray(g.A.sum(axis=1)).ravel()
    rows = np.flatnonzero(unk & (deg > 0))
    if len(rows) == 0:
        return W
    Ar = g.A[rows]
    inv = 1.0 / deg[rows, None]
    W = W.copy()
    for _ in range(iterations):
        W[rows] = keep * W[rows] + (1.0 - keep) * (Ar @ W) * inv
    return W


def edge_scale(g: WeldedMesh):
    """Mean length of the welded edges at each vertex, ``(k,)`` (the diagonal for isolated ones)."""
    A = sp.triu(g.A, k=1).tocoo()
    length = np.linalg.norm(g.V[A.row] - g.V[A.col], axis=1)
    total = np.bincount(A.row, length, len(g.V)) + np.bincount(A.col, length, len(g.V))
    count = np.bincount(A.row, None, len(g.V)) + np.bincount(A.col, None, len(g.V))
    out = np.full(len(g.V), bounding_box_diagonal(g.V))
    out[count > 0] = total[count > 0] / count[count > 0]
    return out


def sparsify(W, k=4):
    """Keep the ``k`` largest weights of each row, clamp at zero and renormalize.

    Parameters
    ----------
    W : (n, J) float array
    k : int
        Maximum number of non-zero weights per row (glTF: 4 per JOINTS_n set).

    Returns
    -------
    W : (n, J) float64
        Non-negative, at most ``k`` non-zeros per row, rows summing to 1. A row with no positive
        entry gets weight 1 on its largest entry.
    """
    W = np.nan_to_num(np.asarray(W, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    n, J = W.shape
    out = np.clip(W, 0.0, None)
    if J > k:
        drop = np.argpartition(-out, k - 1, axis=1)[:, k:]  # (n, J-k): all but the k largest
        np.put_along_axis(out, drop, 0.0, axis=1)
    s = out.sum(axis=1)
    empty = s <= 0
    if np.any(empty):
        out[empty] = 0.0
        out[np.flatnonzero(empty), np.argmax(W[empty], axis=1)] = 1.0
        s[empty] = 1.0
    return out / s[:, None]
