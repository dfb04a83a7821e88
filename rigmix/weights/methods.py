"""The smooth fills: ``nearest``, ``harmonic`` and ``inpaint`` (the Robust Skin Weights
Transfer anchor). Each takes the welded mesh, welded weights ``W (k, J)`` and the unknown mask
``unk (k,)`` and returns ``(k, J)`` with the known rows kept.
"""

from __future__ import annotations

import igl
import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from .mesh import WeldedMesh, bilaplacian, fill_orphans, nearest_vertex, smooth_unknown, solvable_rows, solve_fixed

__all__ = ["fill_nearest", "fill_harmonic", "fill_inpaint", "known_surface_weights"]


def fill_nearest(g: WeldedMesh, W, unk, *, mode="vertex"):
    """Closest known welded vertex (``mode="vertex"``, the anchor protocol) or closest point of
    the known surface (:func:`known_surface_weights`, ``mode="surface"``), for the unknown rows."""
    out = W.copy()
    rows = np.flatnonzero(unk)
    if len(rows) == 0:
        return out
    if mode == "vertex":
        out[rows] = nearest_vertex(g.V, W, unk, rows)
    elif mode == "surface":
        out[rows] = known_surface_weights(g, W, unk, g.V[rows])[0]
    else:
        raise InputError(f"weights: unknown nearest mode {mode!r} (use 'surface' or 'vertex')")
    return out


def known_surface_weights(g: WeldedMesh, W, unk, X):
    """Weights ``(q, J)`` at the points of the known surface closest to ``X`` ``(q, 3)``, and the
    distances ``(q,)``: interpolated on faces with three known corners, else the closest known
    vertex's (a known vertex outside every known face, isolated or only on faces touching the
    unknown rows, may be closer than the known faces)."""
    known = np.flatnonzero(~unk)
    d, i = cKDTree(g.V[known]).query(X)
    src = W[known[i]]
    Fk = g.F[~unk[g.F].any(axis=1)] if len(g.F) else g.F
    if len(Fk):
        sqd, fi, C = igl.point_mesh_squared_distance(X, g.V, Fk)
        T = Fk[fi]
        B = igl.barycentric_coordinates(C, g.V[T[:, 0]], g.V[T[:, 1]], g.V[T[:, 2]])
        B = np.clip(np.nan_to_num(B, nan=1.0 / 3.0), 0.0, None)
        B /= np.maximum(B.sum(axis=1, keepdims=True), 1e-300)
        ds = np.sqrt(np.maximum(sqd, 0.0))
        closer = ds < d
        src[closer] = np.einsum("nc,ncj->nj", B[closer], W[T[closer]])
        d = np.where(closer, ds, d)
    return src, d


def fill_harmonic(g: WeldedMesh, W, unk):
    """Cotangent-Laplacian interpolation of the unknown rows, the known rows fixed."""
    solve = solvable_rows(g, unk)
    out = solve_fixed(-g.L, W, unk, solve)
    return fill_orphans(g, out, unk, solve)


def fill_inpaint(g: WeldedMesh, W, unk, *, iterations=10, keep=0.8):
    """The Robust Skin Weights Transfer's inpainting: the squared Laplacian energy
    (:func:`.mesh.bilaplacian`) minimized with the known rows fixed, then ``iterations`` of
    :func:`.mesh.smooth_unknown` (``keep``) on the unknown rows."""
    solve = solvable_rows(g, unk)
    out = solve_fixed(bilaplacian(g), W, unk, solve)
    out = fill_orphans(g, out, unk, solve)
    return smooth_unknown(g, out, unk, iterations=iterations, keep=keep)

