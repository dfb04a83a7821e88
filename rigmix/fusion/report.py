"""Quality figures of a fused surface (the ``mesh`` part of the composition report)."""

from __future__ import annotations

import numpy as np

from ..geometry import weld
from .meshutil import edge_counts, intersecting_face_pairs, triangle_min_angles

__all__ = ["mesh_report", "edge_keys"]


def edge_keys(V, E):
    """Order-independent keys of edges given by their endpoint positions (bit-exact).

    Parameters
    ----------
    V : (n, 3) float array
    E : (k, 2) int array

    Returns
    -------
    (k,) numpy void array: equal keys for edges with the same two endpoint positions.
    """
    V = np.ascontiguousarray(V, dtype=np.float64)
    A, B = V[E[:, 0]], V[E[:, 1]]
    # order the two endpoints lexicographically so (a, b) and (b, a) give the same key
    less = (A[:, 0] < B[:, 0]) | (
        (A[:, 0] == B[:, 0]) & ((A[:, 1] < B[:, 1]) | ((A[:, 1] == B[:, 1]) & (A[:, 2] <= B[:, 2]))))
    lo = np.where(less[:, None], A, B)
    hi = np.where(less[:, None], B, A)
    K = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    return K.view(np.dtype((np.void, K.dtype.itemsize * 6))).ravel()


def _edges_with_count(V, F, which):
    Vw, _, Fw = weld(V, F)
    uE, cnt = edge_counts(Fw)
    sel = cnt == 1 if which == "boundary" else cnt > 2
    return edge_keys(Vw, uE[sel])


def mesh_report(V, F, junction, inputs_VF, *, inherited=None):
    """Counts and quality on the mesh welded by position.

    Parameters
    ----------
    V : (N, 3), F : (M, 3)
        The fused surface.
    junction : (M,) bool
        Junction faces.
    inputs_VF : sequence of (V_i, F_i)
        The inputs (positioned); their boundary and non-manifold edges are not "new".

    Returns
    -------
    dict
        ``vertices``, ``faces``, ``welded_vertices``, ``boundary_edges``, ``non_manifold_edges``,
        ``new_non_manifold_edges``, ``junction_boundary_edges`` (boundary edges of the output
        that were not boundary edges of an input), ``junction_faces``,
        ``junction_min_angle_p05`` and ``junction_min_angle_min`` (degrees),
        ``junction_self_intersections`` (pairs of faces, at least one of them a junction face,
        that cross each other without sharing a corner of the welded mesh: a fold through the
        surface that shading, collision and boolean tools all trip on); with ``inherited``,
        ``junction_crossings_inherited``: ``inherited(pairs)`` of those pairs ``(p, 2)`` (face
        indices, the same welded or split).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    Vw, _, Fw = weld(V, F)
    uE, cnt = edge_counts(Fw)
    bkeys = edge_keys(Vw, uE[cnt == 1])
    nkeys = edge_keys(Vw, uE[cnt > 2])
    in_b = [np.zeros(0, bkeys.dtype)]
    in_n = [np.zeros(0, nkeys.dtype)]
    for Vi, Fi in inputs_VF:
        in_b.append(_edges_with_count(Vi, Fi, "boundary"))
        in_n.append(_edges_with_count(Vi, Fi, "nonmanifold"))
    in_b = np.concatenate(in_b)
    in_n = np.concatenate(in_n)
    new_b = ~np.isin(bkeys, in_b)
    new_n = ~np.isin(nkeys, in_n)
    ang = triangle_min_angles(V, F[np.asarray(junction, bool)])
    pairs = intersecting_face_pairs(Vw, Fw, np.flatnonzero(junction))
    out = {
        "vertices": int(len(V)),
        "faces": int(len(F)),
        "welded_vertices": int(len(Vw)),
        "boundary_edges": int((cnt == 1).sum()),
        "non_manifold_edges": int((cnt > 2).sum()),
        "new_non_manifold_edges": int(new_n.sum()),
        "junction_boundary_edges": int(new_b.sum()),
        "junction_faces": int(np.count_nonzero(junction)),
        "junction_min_angle_p05": float(np.percentile(ang, 5)) if len(ang) else None,
        "junction_min_angle_min": float(ang.min()) if len(ang) else None,
        "junction_self_intersections": int(len(pairs)),
    }
    if inherited is not None:
        out["junction_crossings_inherited"] = int(inherited(pairs)) if len(pairs) else 0
    return out
