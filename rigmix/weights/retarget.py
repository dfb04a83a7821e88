"""Retargeting: input weights onto the output joints, and the closest-point transfer.

The first steps of :func:`rigmix.weights.blend_weights`: each input's weights re-indexed through
its bone map (:func:`retarget_weights`), the paper's closest-point weights of a junction vertex
(:func:`closest_point_weights`, blended by :func:`blend_parts`), and the conversion of dense
weights to the glTF's per-vertex influences (:func:`to_influences`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..geometry import bounding_box_diagonal
from ..sparse_weights import dense_rows, row_blocks, row_sums

__all__ = ["retarget_weights", "retarget_inputs", "closest_point_weights", "blend_parts", "to_influences"]


def retarget_weights(W, target, num_output_joints, *, confidence=None):
    """W' = B(W): input weights re-indexed onto the output joints.

    Parameters
    ----------
    W : (n, J_in) float array or scipy.sparse matrix
        Input weights (``FusionInput.W``).
    target : (J_in,) int array
        Output joint of each input joint (``BoneMap.target``), ``-1`` when unmapped.
    num_output_joints : int
    confidence : (J_in,) float array, optional
        Mapping confidence per input joint.

    Returns
    -------
    Wr : (n, J_R) scipy.sparse.csr_matrix, float64
        Weights of input joints mapped to the same output joint summed; rows renormalized
        (mass on unmapped joints dropped); a row left empty stays all zero. Held per influence:
        the values (and row sums) are those of the dense product bit for bit.
    c : (n,) float64
        Confidence of each row: ``sum_j W[:, j] confidence[j]`` (1 without ``confidence``), the
        same float for a row whatever the other rows and the thread count.
    """
    W = W if sp.issparse(W) else np.asarray(W, dtype=np.float64)
    target = np.asarray(target, dtype=np.int64)
    ok = target >= 0
    B = sp.csr_matrix((np.ones(int(ok.sum())), (np.flatnonzero(ok), target[ok])),
                      shape=(len(target), num_output_joints))
    Wr = sp.csr_matrix(sp.csr_matrix(W) @ B)
    Wr.sum_duplicates()
    Wr.eliminate_zeros()
    s = row_sums(Wr)
    nz = s > 0
    # leave rows whose sum is already 1 bit-identical (preserved vertices copy them exactly)
    off = nz & (np.abs(s - 1.0) > 1e-12)
    row = np.repeat(np.arange(Wr.shape[0]), np.diff(Wr.indptr))
    scaled = off[row]
    Wr.data[scaled] /= s[row[scaled]]
    n = W.shape[0]
    c = np.ones(n)
    if confidence is not None:
        conf = np.asarray(confidence, dtype=np.float64)
        # numpy's own row sums, not a BLAS product: a BLAS sum depends on the row's place in the
        # block and on the thread count, and the output must not
        for rows in row_blocks(n, W.shape[1]):
            c[rows] = (dense_rows(W, rows) * conf).sum(axis=1)
    return Wr, np.clip(c, 0.0, 1.0)


def cut_joints_to_nearest_kept(target, confidence, used, parents, positions, output_positions, *, reach):
    """The bone map with each joint the input does not keep, and whose image lies farther than
    ``reach`` from it at rest (or that has none), sent to the output joint of its nearest kept
    joint (fewest bones away in the input skeleton, ties: the lower index; a joint with no bone
    path to a kept one: the nearest kept joint at rest), with that joint's confidence.

    Parameters
    ----------
    target, confidence : (J,) arrays
        The bone map (``BoneMap.target``, ``-1`` unmapped, and ``BoneMap.confidence``).
    used : (J,) bool array
        Joints the input keeps.
    parents : (J,) int array
        The input skeleton's parents (``-1`` for roots).
    positions : (J, 3) float array
        The input's joints at rest, composed world space.
    output_positions : (J_R, 3) float array
        The output's joints at rest, same space.
    reach : float
        Same unit.

    Returns
    -------
    target, confidence : new (J,) arrays

    The weights of a cut-off part count only at the junction, where the part was cut: there
    they follow what it was cut from, not a joint the mapping chose elsewhere for animation (a
    rider's hips mapped onto a horse's hips, at the other end of the horse).
    """
    from scipy.sparse.csgraph import shortest_path

    target = np.array(target, np.int64)
    confidence = np.array(confidence, np.float64)
    used = np.asarray(used, bool)
    parents = np.asarray(parents, np.int64)
    far = np.zeros(len(target), bool)
    ok = target >= 0
    far[ok] = np.linalg.norm(np.asarray(positions)[ok] - np.asarray(output_positions)[target[ok]], axis=1) > reach
    cut = np.flatnonzero(~used & (far | ~ok))
    kept = np.flatnonzero(used)
    if not len(cut) or not len(kept):
        return target, confidence
    J = len(parents)
    child = np.flatnonzero(parents >= 0)
    A = sp.csr_matrix((np.ones(len(child)), (child, parents[child])), shape=(J, J))
    hops = shortest_path(A, directed=False, unweighted=True, indices=cut)[:, kept]  # (c, k)
    linked = np.isfinite(hops).any(axis=1)
    nearest = kept[np.argmin(np.where(np.isfinite(hops), hops, np.inf), axis=1)]
    # a joint of another root's tree (modular rigs hang the head or the wings from a root of
    # their own) has no bone path to a kept joint: the nearest one at rest
    P = np.asarray(positions, np.float64)
    apart = np.linalg.norm(P[cut[~linked], None, :] - P[None, kept, :], axis=2)
    nearest[~linked] = kept[np.argmin(apart, axis=1)] if len(apart) else nearest[~linked]
    target[cut] = target[nearest]
    confidence[cut] = confidence[nearest]
    return target, confidence


def retarget_inputs(inputs, maps, num_output_joints, *, skeleton=None, cut_reach=0.0):
    """Every input's weights retargeted through its bone map (:func:`retarget_weights`).

    Parameters
    ----------
    inputs : sequence of rigmix.fusion.FusionInput
        Their ``W`` ``(n_i, J_i)`` on the input joints.
    maps : sequence of rigmix.mapping.BoneMap
        B_i per input, same order (``target`` and ``confidence``).
    num_output_joints : int
    skeleton : rigmix.character.Skeleton, optional
        The output skeleton, rest pose in the inputs' (composed) space.
    cut_reach : float
        With ``skeleton``: a joint an input does not keep, whose image lies farther than this
        fraction of the input's bounding-box diagonal from it, takes its nearest kept joint's
        image (:func:`cut_joints_to_nearest_kept`; 0: the maps as they are).

    Returns
    -------
    retargeted : list of (n_i, J_R) scipy.sparse.csr_matrix
    confidence : list of (n_i,) float64 arrays
        Mapping confidence of each row.
    """
    retargeted, confidence = [], []
    cutting = cut_reach > 0 and skeleton is not None
    output_positions = skeleton.rest_worlds()[:, :3, 3] if cutting else None
    for x, bm in zip(inputs, maps):
        target, conf = bm.target, bm.confidence
        if cutting and x.parents is not None and len(x.V):
            target, conf = cut_joints_to_nearest_kept(bm.target, bm.confidence, x.used, x.parents, x.joint_positions,
                                                      output_positions, reach=cut_reach * bounding_box_diagonal(x.V))
        Wr, c = retarget_weights(x.W, target, num_output_joints, confidence=conf)
        retargeted.append(Wr)
        confidence.append(c)
    return retargeted, confidence


def closest_point_weights(sources, retargeted, faces, *, tolerance, return_parts=False):
    """The paper's junction weights: closest points of the inputs, blended.

    Parameters
    ----------
    sources : sequence of dict
        Per input, ``FusedSurface.junction_sources[i]``: ``face`` (q,), ``bary`` (q, 3),
        ``distance`` (q,), ``presence`` (q,).
    retargeted : sequence of (n_i, J_R) float arrays or scipy.sparse matrices
        Retargeted weights of each input, per split vertex.
    faces : sequence of (m_i, 3) int arrays
        Faces of each input.
    tolerance : float
        Inputs farther than the closest one by more than this do not contribute (a far input
        with presence 1, e.g. the other end of a three-character composition, must not).

    Returns
    -------
    W : (q, J_R) float64
        ``sum_i t_i w_i / sum_i t_i`` with ``t_i = p_i / (d_i + eps)`` over the near inputs,
        ``w_i`` the barycentric interpolation of the retargeted weights at the closest point.
    t : (q, I) float64
        The normalized blend factors.
    parts : (I, q, J_R) float64
        Only with ``return_parts``: the ``w_i``, to blend with other factors (:func:`blend_parts`).
    """
    D = np.stack([np.asarray(s["distance"], np.float64) for s in sources], axis=1)  # (q, I)
    P = np.stack([np.asarray(s["presence"], np.float64) for s in sources], axis=1)
    near = D <= D.min(axis=1, keepdims=True) + tolerance
    eps = 1e-3 * tolerance + 1e-12
    t = np.where(near, np.clip(P, 0.0, 1.0) / (D + eps), 0.0)
    none = t.sum(axis=1) <= 0  # no near input is present there: the closest one decides
    t[none] = np.where(near[none], 1.0 / (D[none] + eps), 0.0)
    t /= t.sum(axis=1, keepdims=True)
    parts = np.stack([
        np.einsum("qk,qkj->qj", np.asarray(s["bary"], np.float64),
                  dense_rows(retargeted[i], np.asarray(faces[i], np.int64)[np.asarray(s["face"], np.int64)]))
        for i, s in enumerate(sources)])
    out, _ = blend_parts(t, parts)
    return (out, t, parts) if return_parts else (out, t)


def blend_parts(t, parts):
    """Blend per-input weights by blend factors, and measure how much the inputs disagree.

    Parameters
    ----------
    t : (q, I) float array
        Blend factors, rows summing to 1.
    parts : (I, q, J) float array (or a sequence of I ``(q, J)`` arrays)
        Each input's weights at the ``q`` points.

    Returns
    -------
    W : (q, J) float64
        ``sum_i t_i w_i``.
    spread : (q,) float64
        ``sum_i t_i |w_i - W|_1``: 0 where one input decides or where the inputs agree (as in a
        self-composition).
    """
    W = np.einsum("qi,iqj->qj", t, parts)
    spread = np.einsum("qi,iq->q", t, np.abs(parts - W[None]).sum(axis=2))
    return W, spread


def to_influences(W, k=4):
    """The ``k`` largest influences of each row of a weight matrix, largest first.

    Parameters
    ----------
    W : (n, J) float array or scipy.sparse matrix
        (Sparse: taken a dense block of rows at a time, :func:`rigmix.sparse_weights.row_blocks`,
        with the same result.)
    k : int
        Influences per vertex (at most ``J``).

    Returns
    -------
    joints : (n, k) int64
        Joint indices; 0 in unused slots.
    weights : (n, k) float64
        Their weights; 0 in unused slots.
    """
    n, J = W.shape
    k = min(k, J)
    joints, weights = np.zeros((n, k), np.int64), np.zeros((n, k))
    for rows in row_blocks(n, J):
        block = dense_rows(W, rows)
        idx = np.argsort(-block, axis=1, kind="stable")[:, :k]
        w = np.take_along_axis(block, idx, axis=1)
        joints[rows], weights[rows] = np.where(w > 0, idx, 0), w
    return joints, weights
