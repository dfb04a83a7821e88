"""Small topology helpers shared by every stage (PIPELINE.md section 0).

glTF meshes are split at every UV, normal and material seam, and flat-shaded assets at every
face. Every topological operation (Laplacians, components, boundary loops, geodesics) runs on
the mesh welded by position, with the map back to the split vertices: :func:`weld` is
:func:`dfd.mesh.weld`, named here for the rigmix modules.
"""

from __future__ import annotations

import numpy as np

from dfd.mesh import weld

__all__ = ["bounding_box_diagonal", "neighbour_roughness", "weld"]


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
