"""Small topology helpers shared by every stage (PIPELINE.md section 0).

glTF meshes are split at every UV, normal and material seam, and flat-shaded assets at every
face. Every topological operation (Laplacians, components, boundary loops, geodesics) runs on
the mesh welded by position, with the map back to the split vertices.
"""

from __future__ import annotations

import numpy as np

__all__ = ["weld", "bounding_box_diagonal", "neighbour_roughness"]


def weld(V, F=None, *, tol=0.0):
    """Merge vertices at the same position.

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
        Only when ``F`` is given.
    """
    V = np.asarray(V, dtype=np.float64)
    if len(V) == 0:
        index = np.zeros(0, dtype=np.int64)
        Vw = V.reshape(0, 3)
    else:
        key = V if tol <= 0 else np.round(V / tol)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        # renumber groups in order of first appearance, so welding is stable and predictable
        order = np.argsort(first, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        index = rank[inverse].astype(np.int64)
        Vw = V[np.sort(first)]
    if F is None:
        return Vw, index
    return Vw, index, index[np.asarray(F, dtype=np.int64)]


def bounding_box_diagonal(V) -> float:
    """Length of the axis-aligned bounding box diagonal of points ``(n, 3)``."""
    V = np.asarray(V, dtype=np.float64)
    if len(V) == 0:
        return 0.0
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def neighbour_roughness(A, X):
    """Half the L1 distance from each row of ``X`` to the mean of its neighbours' rows.

    Parameters
    ----------
    A : (k, k) scipy.sparse matrix
        Adjacency of the rows; any positive entry is an edge (its value is not used), no
        self-loops.
    X : (k, c) float array
        Rows summing to 1 (skinning weights): the figure is in ``[0, 1]``, 1 for a row sharing
        nothing with its neighbours.

    Returns
    -------
    roughness : (k,) float64
        0 for a row without neighbours.
    has_neighbours : (k,) bool
    """
    A = (A > 0).astype(np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    mean = (A @ X) / np.maximum(deg, 1)[:, None]
    return np.where(deg > 0, 0.5 * np.abs(X - mean).sum(axis=1), 0.0), deg > 0
