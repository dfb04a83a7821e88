"""Skin weight repairs applied on load (the rules are listed in :mod:`rigmix.io.gltf`).

Real files carry NaN weights, negative or unnormalized rows and joints listed twice in one row
(the shared Wasp has all of these): :func:`repair_weights` cleans the rows it can, and
:func:`fill_empty_rows` gives the rows left without any weight the weights of a co-located
vertex, else the nearest joint.
"""

from __future__ import annotations

import numpy as np

from ..character import Skeleton

__all__ = ["repair_weights", "fill_empty_rows", "SUM_TOLERANCE", "COLOCATED"]

#: Weight rows whose sum is off by more than this are reported (all rows are renormalized).
SUM_TOLERANCE = 1e-3
#: A vertex within this fraction of the bind-pose bounding-box diagonal counts as co-located.
COLOCATED = 1e-6


def repair_weights(joints, weights):
    """Clean skin weights (the rules of :mod:`rigmix.io.gltf`), except rows left without weight.

    Parameters
    ----------
    joints : (n, K) int array
    weights : (n, K) float array, may hold NaN, inf, negatives and duplicate joint slots.

    Returns
    -------
    joints : (n, K) int64
        Unused slots (weight 0) set to joint 0.
    weights : (n, K) float64
        Non-negative rows summing to 1, or all zero for the rows in ``empty``.
    empty : (n,) bool
        Rows with no finite positive weight (to be filled by the caller).
    counts : dict
        Rows affected: ``nonfinite``, ``negative``, ``duplicate``, ``unnormalized``.
    """
    J = np.array(joints, dtype=np.int64)
    W = np.array(weights, dtype=np.float64)
    bad = ~np.isfinite(W)
    counts = {"nonfinite": int(bad.any(axis=1).sum())}
    W[bad] = 0.0
    neg = W < 0
    counts["negative"] = int(neg.any(axis=1).sum())
    W[neg] = 0.0
    dup = np.zeros(len(W), dtype=bool)
    K = W.shape[1]
    for b in range(1, K):
        for a in range(b):
            same = (J[:, a] == J[:, b]) & (W[:, b] > 0)
            dup |= same & (W[:, a] > 0)
            W[same, a] += W[same, b]
            W[same, b] = 0.0
    counts["duplicate"] = int(dup.sum())
    s = W.sum(axis=1)
    empty = s <= 0
    counts["unnormalized"] = int((~empty & (np.abs(s - 1.0) > SUM_TOLERANCE)).sum())
    W[~empty] /= s[~empty, None]
    J[W == 0] = 0
    return J, W, empty, counts


def fill_empty_rows(parts, skeleton: Skeleton, log):
    """Give rows without weight the weights of a co-located vertex, else the nearest joint.

    Parameters
    ----------
    parts : list of dict
        The skinned primitives of one skin, each with ``name``, ``positions`` (n, 3) in bind
        space, ``joints`` (n, K) and ``weights`` (n, K) as returned by :func:`repair_weights`,
        ``empty`` (n,) bool and ``nonfinite`` (n,) bool (for the messages). ``joints`` and
        ``weights`` are filled in place.
    skeleton : Skeleton
        Its inverse binds give the joints' bind positions.
    log : callable
        Receives one message per mesh and kind of repair.

    Notes
    -----
    A donor is a vertex with weights, of any primitive of the skin, within ``COLOCATED`` x the
    bind bounding-box diagonal (seams split vertices, so a defective vertex often has a healthy
    twin). Without one the row gets weight 1 on the joint whose bind position is nearest.
    """
    if not any(p["empty"].any() for p in parts):
        return
    from scipy.spatial import cKDTree

    allV = np.concatenate([p["positions"] for p in parts])
    diag = float(np.linalg.norm(allV.max(0) - allV.min(0))) if len(allV) else 1.0
    donors = [(p, np.flatnonzero(~p["empty"])) for p in parts]
    dV = np.concatenate([p["positions"][i] for p, i in donors])
    dJ = [p["joints"][i] for p, i in donors]
    K = max(p["joints"].shape[1] for p in parts)
    dJ = np.concatenate([np.pad(j, ((0, 0), (0, K - j.shape[1]))) for j in dJ])
    dW = np.concatenate([np.pad(p["weights"][i], ((0, 0), (0, K - p["weights"].shape[1]))) for p, i in donors])
    tree = cKDTree(dV) if len(dV) else None
    bind_pos = np.linalg.inv(skeleton.inverse_binds)[:, :3, 3]
    for p in parts:
        rows = np.flatnonzero(p["empty"])
        if not len(rows):
            continue
        P = p["positions"][rows]
        copied = np.zeros(len(rows), dtype=bool)
        if tree is not None:
            d, k = tree.query(P)
            copied = d <= COLOCATED * diag
            Kp = p["joints"].shape[1]
            for r, src in zip(rows[copied], k[copied]):
                order = np.argsort(-dW[src], kind="stable")[:Kp]
                w = dW[src, order]
                p["joints"][r] = dJ[src, order]
                p["weights"][r] = w / w.sum()
        # a k-d tree, not an (empty rows x joints) distance matrix: memory stays linear
        near = cKDTree(bind_pos).query(P[~copied])[1] if (~copied).any() else np.zeros(0, dtype=np.int64)
        p["joints"][rows[~copied]] = 0
        p["weights"][rows[~copied]] = 0.0
        p["joints"][rows[~copied], 0] = near
        p["weights"][rows[~copied], 0] = 1.0
        nonfinite = p["nonfinite"][rows]
        for mask, how in ((copied, "given the weights of a vertex at the same position"),
                          (~copied, "bound with weight 1 to the joint nearest in the bind pose")):
            for bad, what in ((nonfinite, "NaN or infinite"), (~nonfinite, "zero or negative")):
                if (mask & bad).any():
                    log(f"mesh '{p['name']}': {int((mask & bad).sum())} vertices with {what} weights {how}")
