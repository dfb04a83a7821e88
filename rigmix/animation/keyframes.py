"""Keyframes on the output skeleton, and their similarity (SkinMixer section 8, the scoring).

* :func:`map_pose`: keyframes of one input as local transforms of S_R through its bone map
  (rest-relative deltas, accumulated along chains, blended toward identity by ``1 - c``);
* :func:`global_rotations` and world positions by forward kinematics on S_R;
* :func:`keyframe_scores`: the similarity of every pair of keyframes as one matrix product;
* :func:`continuity_scores`: the temporal continuity terms as shifted-diagonal sums.

The rotation term
-----------------
The paper sums ``c_j |<q_a_j, q_b_j>|`` over joints (``|.|`` makes ``q`` and ``-q`` equal).
The absolute value does not factor into one matrix product, its square does:
``<q_a, q_b>^2 = <vec(q_a q_a^T), vec(q_b q_b^T)>``, with the 10 unique entries of the
symmetric outer product as features (off-diagonal ones scaled by sqrt 2). So
``sum_j w_j <q_a_j, q_b_j>^2`` over all pairs of frames is a single GEMM
``(F_a, 10 J) @ (10 J, F_b)``, and the translation term (weighted squared distances of joint
positions, expanded as ``|a|^2 + |b|^2 - 2 a.b``) joins the same GEMM. ``<q_a, q_b>^2 =
cos^2(theta / 2) = (1 + cos theta) / 2`` is the chordal distance between rotation matrices,
as sign-invariant as ``|.|`` and, per joint, a monotone function of it. That is the default
(``metric="squared"``); ``metric="abs"`` computes the paper's ``|.|`` exactly with one small
GEMM per joint (about ``J`` times the memory traffic; still no loop over pairs).

Thread-count independence
-------------------------
A BLAS product's rounding depends on its blocking, and the blocking on the thread count
(OpenBLAS: from ``K`` of about 450 in single precision, earlier in double): argmax and Viterbi
decisions over near-tied scores (duplicate or held frames) then flipped with
``OMP_NUM_THREADS``, and whole tracks with them. Every product of the scores is therefore
exact (:func:`exact_products`): the features are rounded to a grid of integers small enough
that no partial sum rounds, so any blocking, thread count or BLAS gives the same bits, and the
GEMMs still run multi-threaded. The rank-one terms are ``einsum`` reductions (numpy's own
loops, never threaded).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..character import Skeleton
from ..errors import InputError
from ..transforms import quat_conjugate, quat_multiply, quat_normalize, quat_slerp

__all__ = [
    "KEPT_CONFIDENCE",
    "map_pose",
    "forward_kinematics",
    "global_rotations",
    "global_positions",
    "hop_weights",
    "rotation_features",
    "keyframe_scores",
    "Candidates",
    "continuity_scores",
    "exact_products",
]

logger = logging.getLogger(__name__)

_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])
#: Confidence of an input joint kept in S_R (copied or fused), up to rounding.
KEPT_CONFIDENCE = 1.0 - 1e-9


# --------------------------------------------------------------------------------------------
# mapping keyframes onto S_R


def _contributors(bone_map, num_out):
    """For each output joint, the input joints mapped onto it (ascending = topological)."""
    target = np.asarray(bone_map.target, dtype=np.int64)
    out = [[] for _ in range(num_out)]
    for i, o in enumerate(target):
        if 0 <= o < num_out:
            out[o].append(i)
    return out


def _map_scale(skeleton_out, skeleton_in, contributors, confidence):
    """Ratio of output to input bone lengths over the confidence-1 copies (1 if none)."""
    ratios = []
    for o, ins in enumerate(contributors):
        for i in ins:
            a = np.linalg.norm(skeleton_in.translations[i])
            b = np.linalg.norm(skeleton_out.translations[o])
            if confidence[i] >= KEPT_CONFIDENCE and a > 1e-9 and b > 1e-9:
                ratios.append(b / a)
    return float(np.median(ratios)) if ratios else 1.0


def map_pose(skeleton_out: Skeleton, skeleton_in: Skeleton, bone_map, T, R, S, *, blend=True,
             translation_maps=None):
    """Keyframes of one input expressed as local transforms of the output skeleton S_R.

    Rotations move as rest-relative deltas in the joint frame: an output joint ``o`` reached
    by input joints ``i_1 < ... < i_k`` gets ``R_o = rest_o * D`` with
    ``D = (rest_i1 ... rest_ik)^-1 (R_i1 ... R_ik)`` (exact for a chain), blended toward
    identity by ``1 - c`` (``c``: the largest confidence among them). When some of them have
    confidence 1 (the joint is kept from this input) only those form the chain: the joint
    replays its own animation. Translations and scales
    come from the first of them with that confidence, as deltas from its rest value; a
    translation delta goes through that input joint's ``translation_maps`` entry (its parent's
    frame in the input -> the output joint's parent frame: the composed scale, the input's own
    armature scale, the placement), or without maps is rescaled by the median bone-length ratio
    of the confidence-1 copies. Scale keys act as ratios to the rest scale. Output joints
    reached by nothing stay at rest.

    Parameters
    ----------
    skeleton_out : Skeleton
        S_R, ``J`` joints.
    skeleton_in : Skeleton
        The input's skeleton, ``J_in`` joints.
    bone_map : BoneMap
        ``target (J_in,)`` output joint or -1, ``confidence (J_in,)``.
    T : (F, J_in, 3) float array
        Local translations of the input.
    R : (F, J_in, 4) float array
        Local rotations, xyzw.
    S : (F, J_in, 3) float array
        Local scales.
    blend : bool
        Apply the confidence blend toward identity.
    translation_maps : (J_in, 3, 3) float array, optional
        Per input joint, the linear map of its local translation deltas into the local frame of
        the output joint it maps to (:func:`rigmix.animation.completion.translation_maps`).

    Returns
    -------
    T_out : (F, J, 3) float64
    R_out : (F, J, 4) float64
    S_out : (F, J, 3) float64
        Local transforms of S_R.
    mass : (J,) float64
        Confidence mass per output joint, ``min(1, sum of confidences)``, 0 where unreached.
    """
    J = skeleton_out.num_joints
    T = np.asarray(T, dtype=np.float64)
    R = quat_normalize(R)
    S = np.asarray(S, dtype=np.float64)
    F = T.shape[0]
    conf = np.clip(np.asarray(bone_map.confidence, dtype=np.float64), 0.0, 1.0)
    contributors = _contributors(bone_map, J)
    if translation_maps is None:
        L = np.broadcast_to(_map_scale(skeleton_out, skeleton_in, contributors, conf) * np.eye(3),
                            (skeleton_in.num_joints, 3, 3))
    else:
        L = np.asarray(translation_maps, dtype=np.float64).reshape(skeleton_in.num_joints, 3, 3)
    rest_in = quat_normalize(skeleton_in.rotations)
    rest_out = quat_normalize(skeleton_out.rotations)

    T_out = np.broadcast_to(skeleton_out.translations, (F, J, 3)).copy()
    R_out = np.broadcast_to(rest_out, (F, J, 4)).copy()
    S_out = np.broadcast_to(skeleton_out.scales, (F, J, 3)).copy()
    mass = np.zeros(J)
    outs = np.array([o for o, ins in enumerate(contributors) if ins], dtype=np.int64)
    if outs.size == 0:
        return T_out, R_out, S_out, mass
    # per output joint: the delta of its chain of input joints (vectorized for single ones)
    delta = np.empty((F, outs.size, 4))
    # a joint kept from this input (a confidence-1 contributor) replays that joint alone: the
    # dropped joints that propagation also put there (a removed thumb on the palm) must not twist it
    chains = [[i for i in contributors[o] if conf[i] >= KEPT_CONFIDENCE] or contributors[o] for o in outs]
    single = np.array([len(c) == 1 for c in chains])
    first = np.array([c[0] for c in chains])
    delta[:, single] = quat_multiply(quat_conjugate(rest_in[first[single]]), R[:, first[single]])
    for m in np.flatnonzero(~single):
        ins = chains[m]
        anim, rest = R[:, ins[0]], rest_in[ins[0]]
        for i in ins[1:]:
            anim = quat_multiply(anim, R[:, i])
            rest = quat_multiply(rest, rest_in[i])
        delta[:, m] = quat_multiply(quat_conjugate(rest), anim)
    cs = [conf[contributors[o]] for o in outs]
    mass[outs] = [min(1.0, float(c.sum())) for c in cs]
    cmax = np.array([float(c.max()) for c in cs])
    lead = np.array([contributors[o][int(np.argmax(c))] for o, c in zip(outs, cs)])
    f = cmax if blend else np.ones_like(cmax)
    if blend and np.any(cmax < 1.0):
        low = np.flatnonzero(cmax < 1.0)
        delta[:, low] = quat_slerp(delta[:, low], _IDENTITY, np.broadcast_to(1.0 - cmax[low], (F, low.size)))
    R_out[:, outs] = quat_multiply(rest_out[outs], delta)
    T_out[:, outs] += f[:, None] * np.einsum("jab,fjb->fja", L[lead], T[:, lead] - skeleton_in.translations[lead])
    s_rest = skeleton_in.scales[lead]
    s_rest = np.where(np.abs(s_rest) > 1e-12, s_rest, 1.0)
    # a key may scale through zero (a blink squashes an eye to a negative scale): keep the sign
    ratio = S[:, lead] / s_rest
    S_out[:, outs] *= np.sign(ratio) * np.abs(ratio) ** f[:, None]
    return T_out, quat_normalize(R_out), S_out, mass


def _qmul(a, b):
    """Hamilton product of quaternions stored component-first, ``(4, ...)`` xyzw."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _qrot(q, v):
    """Rotate vectors ``v (3, ...)`` by unit quaternions ``q (4, ...)``, component-first."""
    x, y, z, w = q
    vx, vy, vz = v
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return np.stack([vx + w * tx + y * tz - z * ty,
                     vy + w * ty + z * tx - x * tz,
                     vz + w * tz + x * ty - y * tx])


def forward_kinematics(skeleton, T, R, S):
    """Global rotations and world positions of every joint, by quaternion forward kinematics.

    Scales accumulate per axis (exact for uniform scales, which is what rigs animate). Global
    rotations leave out the anchors (a constant left factor that no score sees); positions
    include them.

    Parameters
    ----------
    skeleton : Skeleton
        ``J`` joints (parents and anchors are used).
    T : (F, J, 3) float array
        Local translations.
    R : (F, J, 4) float array
        Local rotations, unit quaternions xyzw.
    S : (F, J, 3) float array
        Local scales.

    Returns
    -------
    G : (F, J, 4) float64
        Global rotations (without anchors).
    P : (F, J, 3) float64
        World positions.
    """
    # component-first, joint-major copies: each joint's frames are contiguous
    Tc = np.ascontiguousarray(np.transpose(T, (2, 1, 0)), dtype=np.float64)  # (3, J, F)
    Rc = np.ascontiguousarray(np.transpose(R, (2, 1, 0)), dtype=np.float64)  # (4, J, F)
    Sc = np.ascontiguousarray(np.transpose(S, (2, 1, 0)), dtype=np.float64)
    G, P, W = np.empty_like(Rc), np.empty_like(Tc), np.empty_like(Sc)
    for j, p in enumerate(skeleton.parents):
        if p < 0:
            G[:, j], W[:, j], P[:, j] = Rc[:, j], Sc[:, j], Tc[:, j]
        else:
            G[:, j] = _qmul(G[:, p], Rc[:, j])
            W[:, j] = W[:, p] * Sc[:, j]
            P[:, j] = P[:, p] + _qrot(G[:, p], W[:, p] * Tc[:, j])
    A = skeleton.root_parent_worlds()  # (J, 4, 4), constant per joint
    P = np.einsum("jkl,ljf->fjk", A[:, :3, :3], P) + A[:, :3, 3]
    return quat_normalize(np.transpose(G, (2, 1, 0))), P


def global_rotations(parents, R):
    """Global joint rotations by forward kinematics (anchors ignored: a constant left factor).

    Parameters
    ----------
    parents : (J,) int array
        Topological order, roots -1.
    R : (F, J, 4) float array
        Local rotations, xyzw.

    Returns
    -------
    (F, J, 4) float64 global rotations.
    """
    Rc = np.ascontiguousarray(np.transpose(np.asarray(R, dtype=np.float64), (2, 1, 0)))
    G = np.empty_like(Rc)
    for j, p in enumerate(parents):
        G[:, j] = Rc[:, j] if p < 0 else _qmul(G[:, p], Rc[:, j])
    return quat_normalize(np.transpose(G, (2, 1, 0)))


def global_positions(skeleton, T, R, S):
    """World joint positions ``(F, J, 3)`` (see :func:`forward_kinematics`)."""
    return forward_kinematics(skeleton, T, R, S)[1]


# --------------------------------------------------------------------------------------------
# scoring


def hop_weights(parents, seeds, *, full=2, cutoff=8) -> np.ndarray:
    """Prototype joint weights by hops from the merge joint(s).

    Parameters
    ----------
    parents : (J,) int array
        Joint forest (roots -1).
    seeds : (s,) int array
        Merge joints (hop 0).
    full, cutoff : int
        Weight 1 up to ``full`` hops, ``2 ** -(d - full)`` up to ``cutoff``, 0 beyond (and for
        joints not connected to any seed).

    Returns
    -------
    (J,) float64 weights.
    """
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    adj = [[] for _ in range(J)]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].append(int(p))
            adj[int(p)].append(j)
    hops = np.full(J, -1)
    frontier = [int(s) for s in np.unique(np.asarray(seeds, dtype=np.int64))]
    for s in frontier:
        hops[s] = 0
    while frontier:
        nxt = []
        for u in frontier:
            for v in adj[u]:
                if hops[v] < 0:
                    hops[v] = hops[u] + 1
                    nxt.append(v)
        frontier = nxt
    d = hops.astype(np.float64)
    w = np.where(d <= full, 1.0, 2.0 ** -(d - full))
    w[(hops < 0) | (d > cutoff)] = 0.0
    return w


_IU = np.triu_indices(4)
_SCALE10 = np.where(_IU[0] == _IU[1], 1.0, np.sqrt(2.0))


def rotation_features(Q, w=None) -> np.ndarray:
    """Features whose inner products are weighted squared quaternion dot products.

    ``rotation_features(Qa, w) @ rotation_features(Qb, w).T == sum_j w_j <Qa_j, Qb_j>^2``,
    via the 10 unique entries of the outer products ``q q^T`` (off-diagonals times sqrt 2).

    Parameters
    ----------
    Q : (F, J, 4) float array
        Unit quaternions (sign irrelevant).
    w : (J,) float array, optional
        Non-negative joint weights (default 1).

    Returns
    -------
    (F, 10 J) float64
    """
    Q = np.asarray(Q, dtype=np.float64)
    phi = Q[..., _IU[0]] * Q[..., _IU[1]] * _SCALE10  # (F, J, 10)
    if w is not None:
        phi = phi * np.sqrt(np.asarray(w, dtype=np.float64))[:, None]
    return phi.reshape(Q.shape[0], -1)


def _grid_slices(X, slices, bits):
    """``X ~ sum_s ldexp(I_s, -e_s)``: up to ``slices`` integer-valued float64 arrays with
    ``|G_s| <= 2 ** bits``, each slice rounding the residual of the ones before."""
    out = []
    for _ in range(slices):
        m = float(np.max(np.abs(X))) if X.size else 0.0
        if not m > 0.0:
            break
        e = bits - int(np.frexp(m)[1])  # |X| * 2 ** e < 2 ** bits
        grid = np.rint(np.ldexp(X, e))
        out.append((grid, e))
        X = X - np.ldexp(grid, -e)
    return out


def exact_products(A, B, *, slices=1, block=1 << 22) -> np.ndarray:
    """``A @ B.T`` with the same bits whatever the BLAS, its blocking and its thread count.

    Each operand is rounded to ``slices`` slices of integers of at most ``bits`` bits,
    ``K * 2 ** (2 bits) <= 2 ** 53``, so every product of slices is an integer-valued GEMM
    whose partial sums are all exact in float64 (run by BLAS, threads and all); the slice
    products (``i + j < slices``) are scaled by exact powers of two and added in a fixed
    order. One slice keeps about ``(53 - log2 K) / 2`` bits of each operand (22 for
    ``K = 450``, finer than float32 scores), two about twice that (float64 scores).

    Parameters
    ----------
    A : (Fa, K) float array
    B : (Fb, K) float array
    slices : int
        1 or 2 (precision, see above).
    block : int
        Largest float64 temporary, in elements (rows of ``A`` are done in blocks).

    Returns
    -------
    (Fa, Fb) float64
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    bits = (53 - max(A.shape[1], 1).bit_length()) // 2
    sb = _grid_slices(B, slices, bits)
    out = np.zeros((len(A), len(B)))
    rows = max(1, block // max(len(B), 1))
    for r0 in range(0, len(A), rows):
        sa = _grid_slices(A[r0:r0 + rows], slices, bits)
        pairs = [(i, j) for i in range(len(sa)) for j in range(len(sb)) if i + j < slices]
        for i, j in sorted(pairs, key=lambda p: -(p[0] + p[1])):  # smallest terms first
            (Ia, ea), (Ib, eb) = sa[i], sb[j]
            out[r0:r0 + rows] += np.ldexp(Ia @ Ib.T, -(ea + eb))
    return out


def _slices(dtype) -> int:
    """Grid slices of :func:`exact_products` for scores of ``dtype``."""
    return 1 if np.dtype(dtype) == np.float32 else 2


def _score_features(G, P, w, length):
    """Weighted rotation and position features of keyframes (kept joints: weight > 0).

    Returns ``Xr (F, 10 Jk)`` with ``Xr_a . Xr_b = sum_j w_j <q_a, q_b>^2 / sum w`` and
    ``Xp (F, 3 Jk)`` with ``|Xp_a - Xp_b|^2 = sum_j w_j |p_a - p_b|^2 / (sum w length^2)``.
    """
    keep = np.flatnonzero(w > 0)
    wk = w[keep] / w[keep].sum()
    Xr = rotation_features(np.asarray(G)[:, keep], wk)
    scale = np.sqrt(wk)[:, None] / max(length, 1e-12)
    Xp = (np.asarray(P, dtype=np.float64)[:, keep] * scale).reshape(len(P), -1)
    return Xr, Xp


def keyframe_scores(Ga, Pa, Gb, Pb, w, *, rotation_weight=0.8, translation_weight=0.2,
                    length=1.0, metric="squared", dtype=np.float64) -> np.ndarray:
    """Similarity of every pair of keyframes (higher is more alike) by matrix products.

    ``score[a, b] = rotation_weight * sum_j w_j r(Ga_aj, Gb_bj) / sum w
    + translation_weight * exp(-sum_j w_j |Pa_aj - Pb_bj|^2 / (sum w * length^2))``, with
    ``r = <q_a, q_b>^2`` (``metric="squared"``) or ``|<q_a, q_b>|`` (``"abs"``). Both terms
    lie in [0, 1]: the exponential keeps a far-off translation (e.g. a root moved through a
    weak mapping) from outweighing the rotations.

    Parameters
    ----------
    Ga : (Fa, J, 4) float array
        Global rotations of the query keyframes on S_R.
    Pa : (Fa, J, 3) float array
        Joint positions (relative to the merge joint) of the query keyframes.
    Gb : (Fb, J, 4) float array
    Pb : (Fb, J, 3) float array
        The same for the candidate keyframes.
    w : (J,) float array
        Non-negative joint weights (zero-weight joints are skipped).
    rotation_weight, translation_weight : float
    length : float
        Length scale of the positions (e.g. the skeleton's extent).
    metric : {"squared", "abs"}
    dtype : numpy dtype
        Of the result, and the precision of the products (:func:`exact_products`: one grid
        slice for ``float32``, two for ``float64``). The features are centred on the
        candidates' mean first, so rounding scales with the spread of the poses rather than
        with the scores themselves (about 1e-7 absolute in ``float32``).

    Returns
    -------
    (Fa, Fb) array of ``dtype``, at most ``rotation_weight + translation_weight``.
    """
    w = np.asarray(w, dtype=np.float64)
    Fa, Fb = len(Ga), len(Gb)
    if not np.any(w > 0):
        return np.full((Fa, Fb), rotation_weight + translation_weight, dtype=dtype)
    Ga, Gb = quat_normalize(Ga), quat_normalize(Gb)
    if metric not in ("squared", "abs"):
        raise InputError(f"completion: metric must be 'squared' or 'abs', got {metric!r}")
    cand = Candidates.build(Gb, Pb, w, 0.0 if metric == "abs" else rotation_weight,
                            translation_weight, length, dtype)
    score = cand.scores(Ga, Pa)
    if metric == "abs":  # the paper's |<q_a, q_b>|: one (Fa, 4) @ (4, Fb) product per joint
        keep = np.flatnonzero(w > 0)
        cr = rotation_weight / w[keep].sum()
        for j in keep:
            score += (cr * w[j]) * np.abs(exact_products(Ga[:, j], Gb[:, j], slices=_slices(dtype)))
    return score


@dataclass(frozen=True)
class Candidates:
    """The candidate side of :func:`keyframe_scores`, built once and scored against any
    number of query clips.

    Rotation term: ``rotation_weight * (Xr_a - m)(Xr_b - m)^T + row_a + col_b`` (the rank-one
    terms put the centring back). Translation term: ``translation_weight * exp(-|Xp_a - Xp_b|^2)``
    with ``|Xp_a - Xp_b|^2`` expanded around the candidates' mean position feature. Products
    of centred features exact (:func:`exact_products`, precision by ``dtype``), rank-one terms
    in float64, sums in ``dtype``.

    Attributes
    ----------
    w : (J,) float64
        Joint weights.
    weights : tuple of float
        ``(rotation_weight, translation_weight, length)``.
    mean_r, mean_p : (Kr,), (Kp,) float64
        Mean candidate rotation and position features.
    Xr, Xp : (Fb, Kr), (Fb, Kp) float64
        Centred candidate features (rotation ones scaled by ``rotation_weight``, position ones
        by -2).
    dtype : numpy dtype
        Of the scores.
    col_r, col_p : (Fb,) arrays of ``dtype``
        Per-candidate terms: ``rotation_weight (Xr_b . m - m . m)`` and ``|Xp_b - m|^2``.
    """

    w: np.ndarray
    weights: tuple
    mean_r: np.ndarray
    mean_p: np.ndarray
    Xr: np.ndarray
    Xp: np.ndarray
    col_r: np.ndarray
    col_p: np.ndarray
    dtype: np.dtype = np.dtype(np.float64)

    @classmethod
    def build(cls, Gb, Pb, w, rotation_weight, translation_weight, length, dtype) -> "Candidates":
        """From global rotations ``Gb (Fb, J, 4)`` and positions ``Pb (Fb, J, 3)`` of the
        candidate keyframes (the other arguments as :func:`keyframe_scores`)."""
        w = np.asarray(w, dtype=np.float64)
        Xr, Xp = _score_features(Gb, Pb, w, length)
        mr, mp = Xr.mean(axis=0), Xp.mean(axis=0)
        Xp = Xp - mp
        col_r = rotation_weight * (np.einsum("ij,j->i", Xr, mr) - np.einsum("i,i->", mr, mr))
        col_p = np.einsum("ij,ij->i", Xp, Xp)
        return cls(w, (rotation_weight, translation_weight, length), mr, mp,
                   rotation_weight * (Xr - mr), -2.0 * Xp, col_r.astype(dtype), col_p.astype(dtype),
                   np.dtype(dtype))

    def scores(self, Ga, Pa) -> np.ndarray:
        """``(Fa, Fb)`` scores of query keyframes ``Ga (Fa, J, 4)``, ``Pa (Fa, J, 3)``."""
        rw, tw, length = self.weights
        dtype, slices = self.dtype, _slices(self.dtype)
        Xr, Xp = _score_features(Ga, Pa, self.w, length)
        if rw > 0:
            score = exact_products(Xr - self.mean_r, self.Xr, slices=slices).astype(dtype)  # (Fa, Fb)
            score += (rw * np.einsum("ij,j->i", Xr, self.mean_r)).astype(dtype)[:, None]
            score += self.col_r[None, :]
        else:  # the rotation term is computed elsewhere (metric="abs")
            score = np.zeros((len(Xr), len(self.Xr)), dtype=dtype)
        if tw > 0:
            Xp = Xp - self.mean_p
            d = exact_products(Xp, self.Xp, slices=slices).astype(dtype)  # -2 pa.pb, + |pa|^2 + |pb|^2 - log tw
            d += (np.einsum("ij,ij->i", Xp, Xp) - np.log(tw)).astype(dtype)[:, None]
            d += self.col_p[None, :]
            np.negative(d, out=d)
            np.exp(d, out=d)  # tw exp(-distance)
            score += d
        return score


def continuity_scores(score, segment_b, weights=(0.2, 0.1)) -> np.ndarray:
    """Add the scores of neighbouring pairs: shifted-diagonal sums of the score matrix.

    ``out[a, b] = (score[a, b] + sum_k weights[k-1] * (score[a-k, b-k] + score[a+k, b+k]))
    / (1 + sum of the weights of the terms that exist)``: a neighbour exists when ``a +- k``
    is a frame of the query clip and ``b +- k`` a frame of the same candidate clip as ``b``.

    Parameters
    ----------
    score : (Fa, Fb) float array
        Keyframe scores of one query clip (rows: its consecutive frames) against candidate
        frames (columns), candidate clips concatenated.
    segment_b : (Fb,) int array
        Candidate clip of each column (consecutive columns of one clip are consecutive frames).
    weights : sequence of float
        Weight of the neighbours at +-1, +-2, ... steps.

    Returns
    -------
    (Fa, Fb) float64
    """
    score = np.asarray(score)
    if score.dtype not in (np.float32, np.float64):
        score = score.astype(np.float64)
    seg = np.asarray(segment_b)
    Fa, Fb = score.shape
    out = score.copy()
    rows, cols = [], []  # the existence of each neighbour term is separable: row x column
    for step, wk in enumerate(weights, start=1):
        if wk == 0:
            continue
        scaled = score * score.dtype.type(wk)  # one scaled copy per step, added twice
        for k in (-step, step):
            a0, a1 = max(0, -k), min(Fa, Fa - k)
            b0, b1 = max(0, -k), min(Fb, Fb - k)
            if a1 <= a0 or b1 <= b0:
                continue
            same = np.zeros(Fb, dtype=bool)
            same[b0:b1] = seg[b0 + k:b1 + k] == seg[b0:b1]
            rv = np.zeros(Fa)
            rv[a0:a1] = wk
            rows.append(rv)
            cols.append(same)
            out[a0:a1, b0:b1] += scaled[a0 + k:a1 + k, b0 + k:b1 + k]
            bad = np.flatnonzero(~same[b0:b1]) + b0  # neighbours in another clip: take back
            if bad.size:
                out[a0:a1, bad] -= scaled[a0 + k:a1 + k, bad + k]
    if rows:
        # divide by 1 + the weights of the existing terms: a constant except on the first and
        # last rows and next to clip boundaries, which are corrected afterwards
        R, C = np.stack(rows, axis=1), np.stack(cols, axis=0).astype(np.float64)  # (Fa, n), (n, Fb)
        full = 1.0 + float(R.max(axis=0).sum())
        out *= score.dtype.type(1.0 / full)
        edge_rows = np.flatnonzero(np.any(R != R.max(axis=0), axis=1))
        edge_cols = np.flatnonzero(~np.all(C > 0, axis=0))
        if edge_rows.size:
            out[edge_rows] *= (full / (1.0 + _sum_products(R[edge_rows], C))).astype(score.dtype)
        if edge_cols.size:
            inner = np.setdiff1d(np.arange(Fa), edge_rows)
            fix = (full / (1.0 + _sum_products(R[inner], C[:, edge_cols]))).astype(score.dtype)
            out[np.ix_(inner, edge_cols)] *= fix
    return out


def _sum_products(R, C):
    """``R @ C`` for a short inner dimension, in a fixed order (no BLAS blocking)."""
    out = np.zeros((R.shape[0], C.shape[1]))
    for k in range(R.shape[1]):
        out += R[:, k, None] * C[k]
    return out
