"""Geodesic locality: filled weights keep only the joints that drive the surface nearby.

A fill that reads weights from far away (a prior from a look-alike part, an inpainting that
spreads a joint across a wide band) can give a vertex a joint whose own surface is elsewhere:
the other hand, another leg. The locality attenuates each filled joint with the graph distance
to the nearest vertex the joint is known to drive, its witnesses: the known vertices where it
weighs at least ``support`` and, where a fill has a trusted prior (the dfd mirror prior), the
filled vertices whose prior gives it that much.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra

from dfd.mesh import welded_graph

__all__ = ["geodesic_locality", "locality_radius"]


def locality_radius(V, F, unknown, radius):
    """``radius``, raised to twice the farthest unknown vertex's graph distance from a known one.

    A band wider than the radius would otherwise lose, in its middle, every joint of its border.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    unknown : (n,) bool array
    radius : float
        Same units as ``V``.

    Returns
    -------
    float
    """
    _, index, G = welded_graph(V, F)
    return max(float(radius), 2.0 * _reach(index, G, np.asarray(unknown, bool)))


def _welded_masks(index, k, unknown):
    """``(unknown, known)`` masks ``(k,)`` over the welded vertices: a welded vertex is unknown
    when any of its split copies is, known when all are."""
    unk_w = np.zeros(k, bool)
    unk_w[index[unknown]] = True
    known_w = np.zeros(k, bool)
    known_w[index[~unknown]] = True
    return unk_w, known_w & ~unk_w


def _reach(index, G, unknown):
    """Largest graph distance from an unknown vertex to the nearest known one (welded graph ``G``)."""
    unk_w, known_w = _welded_masks(index, G.shape[0], unknown)
    src = np.flatnonzero(known_w)
    if not len(src) or not unk_w.any():
        return 0.0
    d = dijkstra(G, directed=False, indices=src, min_only=True)
    fin = d[unk_w][np.isfinite(d[unk_w])]
    return float(fin.max()) if len(fin) else 0.0


def geodesic_locality(V, F, W, unknown, *, radius, power=1.0, support=0.05, witness=None, reach=0.0,
                      deforming_joints=None):
    """Restrict filled weights to joints that drive vertices geodesically nearby.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
    W : (n, J) float array
        Filled weights (known rows as given).
    unknown : (n,) bool array
        Rows to restrict.
    radius : float
        Geodesic radius (graph distance over welded edges, same units as ``V``).
    power : float
        ``w_j(v) <- w_j(v) (1 - d_j(v) / radius)^power``, ``d_j(v)`` the graph distance from
        ``v`` to the nearest witness of joint ``j``.
    support : float
        A known vertex witnesses joint ``j`` where ``W[:, j] >= support``.
    witness : (n, J) float array, optional
        Further evidence on unknown rows (a trusted prior): an unknown vertex witnesses joint
        ``j`` where ``witness[:, j] >= support``.
    reach : float
        The radius is raised to ``reach`` times the farthest unknown vertex's graph distance
        from a known one (:func:`locality_radius` with 2).
    deforming_joints : (J,) bool array, optional
        Joints that deform the source characters. One of them with no witness at all has its
        whole surface unknown (a head swallowed by a junction band) and keeps its filled
        weights; any other joint with no witness drives no surface (a root, an IK target, a
        prop's bone) and is removed from the unknown rows. Default: every joint with no witness
        is removed.

    Returns
    -------
    W : (n, J) float64
        Unknown rows attenuated and renormalized; a row left empty keeps its input value.
    """
    W = np.asarray(W, np.float64).copy()
    unknown = np.asarray(unknown, bool)
    if not unknown.any():
        return W
    Vw, index, G = welded_graph(V, F)
    if reach > 0:
        radius = max(float(radius), reach * _reach(index, G, unknown))
    k = len(Vw)
    unk_w, known_w = _welded_masks(index, k, unknown)
    Wk = np.zeros((k, W.shape[1]))
    Wk[index[~unknown]] = W[~unknown]
    seen = known_w[:, None] & (Wk >= support)
    if witness is not None:
        Xk = np.zeros((k, W.shape[1]))
        Xk[index[unknown]] = np.asarray(witness, np.float64)[unknown]
        seen |= unk_w[:, None] & (Xk >= support)
    rows_u = np.flatnonzero(unknown)
    joints = np.flatnonzero(W[rows_u].max(axis=0) > 0)
    atten = np.ones((len(rows_u), W.shape[1]))
    for j in joints:
        src = np.flatnonzero(seen[:, j])
        if not len(src):
            atten[:, j] = 1.0 if deforming_joints is not None and deforming_joints[j] else 0.0
            continue
        d = dijkstra(G, directed=False, indices=src, min_only=True, limit=radius)
        dj = d[index[rows_u]]
        atten[:, j] = np.clip(1.0 - dj / radius, 0.0, 1.0) ** power
    Wu = W[rows_u] * atten
    s = Wu.sum(axis=1)
    ok = s > 1e-9
    W[rows_u[ok]] = Wu[ok] / s[ok, None]
    return W
