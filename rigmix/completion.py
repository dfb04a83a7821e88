"""Animation completion (SkinMixer section 8; PIPELINE.md section 5): the clips A_R of S_R.

Each selected clip of one input X drives the joints of S_R that come from X; the joints of the
other part(s) (the *completed part*) take the local transforms of frames chosen, per output
frame, among all frames of all clips of the other input(s) Y:

1. resample every clip to ``fps`` (30) with :func:`rigmix.animation.sample_clip`;
2. map every keyframe onto S_R through the bone maps (:func:`map_pose`): rest-relative local
   rotations, unmapped joints at rest (identity delta), several input joints on one output
   joint accumulate, confidence ``c < 1`` blends the delta toward identity by ``1 - c``;
3. global rotations and positions by forward kinematics on S_R;
4. score all pairs (query frame of X, candidate frame of Y) with one matrix product
   (:func:`keyframe_scores`), add the temporal continuity terms as shifted-diagonal sums
   (:func:`continuity_scores`), pick the frames (:func:`choose_frames`);
5. assemble; where the chosen frames jump (seams), fade the jump out over a few frames
   (:func:`blend_seams`) and smooth lightly around it (:func:`smooth_seams`).

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

Choices where the method leaves room (all options of :class:`CompletionOptions`)
-------------------------------------------------------------------------------
* Which joints come from which input: the plan's provenance when given, else the joints an
  input reaches with confidence 1.
* Joint weights: prototype hop weights from the merge joint(s) (the joints fused between the
  clip's input and the completing one) times the confidence masses of both sides.
* Frame choice: the paper takes the best frame per output frame (``jump_penalty=0``); a
  positive ``jump_penalty`` runs a Viterbi pass where continuing to the next frame of the same
  clip is free and any other jump costs the penalty (fewer seams, smoother completed part).
  Default 0.2 (scores are in [0, 1] per frame), measured on the pipeline's Horse + Knight
  centaur: mean angular acceleration of the completed joints over that of their source clips
  4.5 with the paper's rule, 2.4 with a penalty of 0.05, 0.65 with 0.2.
* Seams (jumps between non-consecutive source frames that make a real discontinuity): the jump
  fades out over ``blend_frames`` (inertial blending), then a Gaussian smoothing acts near the
  seam only, on the completed joints only; continuous playback of a source clip is left
  exactly as it was (self-composition reproduces the clips exactly).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Literal, Mapping, Sequence

import numpy as np

from .animation import clip_times, sample_clip
from .character import Character, Clip, Skeleton, Track
from .errors import InputError
from .transforms import (quat_angle, quat_conjugate, quat_multiply, quat_normalize, quat_slerp,
                         trs_to_matrix)

__all__ = [
    "FixedFrame",
    "CompletionOptions",
    "complete_clips",
    "map_pose",
    "global_rotations",
    "hop_weights",
    "rotation_features",
    "keyframe_scores",
    "continuity_scores",
    "choose_frames",
    "blend_seams",
    "smooth_seams",
    "angular_acceleration",
    "options_from_config",
    "completion_stage",
]

logger = logging.getLogger(__name__)

_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


# --------------------------------------------------------------------------------------------
# options


@dataclass(frozen=True)
class FixedFrame:
    """A user-pinned frame choice.

    Output frame ``frame`` of the completion of clip ``clip`` of input ``character`` takes the
    completed part from frame ``source_frame`` of clip ``source_clip`` of input ``source``.
    Frames count at the completion rate (``CompletionOptions.fps``) from each clip's start.
    The choice is pinned; the seam blending and smoothing still act around it (set
    ``blend_frames=0`` and ``smoothing=0`` to get that source frame exactly).
    """

    character: str
    clip: str
    frame: int
    source: str
    source_clip: str
    source_frame: int


@dataclass(frozen=True)
class CompletionOptions:
    """Parameters of animation completion (defaults: the published method and prototype).

    Attributes
    ----------
    clips : mapping of str to sequence of str, or None
        Clips to complete, per character id (``None``: every clip of every input; an id left
        out: none of its clips).
    sources : mapping of str to sequence of str, or None
        Clips whose frames may complete the others, per character id (``None``: all clips;
        an id left out: all its clips).
    fps : float
        Resampling rate, frames per second.
    rotation_weight, translation_weight : float
        Weights of the global-rotation and joint-position terms of the keyframe score
        (prototype: 0.8 and 0.2).
    continuity : tuple of float
        Weights of the neighbouring pairs at +-1, +-2, ... steps (paper: 0.2, 0.1).
    hops_full, hops_max : int
        Prototype joint weights by hops ``d`` from the merge joint: 1 up to ``hops_full``,
        ``2 ** -(d - hops_full)`` up to ``hops_max``, 0 beyond.
    metric : {"squared", "abs"}
        ``sum w <q_a, q_b>^2`` (one GEMM, default) or the paper's ``sum w |<q_a, q_b>|``.
    jump_penalty : float
        Score cost of a jump between non-consecutive source frames (0: best frame per output
        frame, the paper's rule).
    smoothing : float
        Standard deviation, in frames, of the Gaussian smoothing of the completed joints
        around seams (0: none).
    blend_frames : int
        Frames over which the jump at a seam fades out (inertial blending, 0: none) before the
        smoothing.
    confidence_blend : bool
        Blend mapped rotations toward identity (rest) by ``1 - confidence``.
    score_dtype : {"float32", "float64"}
        Precision of the score matrices (float32: half the time and memory; features are
        centred first, see :func:`keyframe_scores`).
    fixed_frames : tuple of FixedFrame
        User-pinned frame choices.
    """

    clips: Mapping[str, Sequence[str]] | None = None
    sources: Mapping[str, Sequence[str]] | None = None
    fps: float = 30.0
    rotation_weight: float = 0.8
    translation_weight: float = 0.2
    continuity: tuple[float, ...] = (0.2, 0.1)
    hops_full: int = 2
    hops_max: int = 8
    metric: Literal["squared", "abs"] = "squared"
    jump_penalty: float = 0.2
    smoothing: float = 1.5
    blend_frames: int = 8
    confidence_blend: bool = True
    score_dtype: Literal["float32", "float64"] = "float32"
    fixed_frames: tuple[FixedFrame, ...] = field(default_factory=tuple)

    def __post_init__(self):
        object.__setattr__(self, "continuity", tuple(float(c) for c in self.continuity))
        object.__setattr__(self, "fixed_frames", tuple(self.fixed_frames))
        if self.fps <= 0:
            raise InputError(f"completion: fps must be positive, got {self.fps}")
        if self.metric not in ("squared", "abs"):
            raise InputError(f"completion: metric must be 'squared' or 'abs', got {self.metric!r}")
        if self.score_dtype not in ("float32", "float64"):
            raise InputError(f"completion: score_dtype must be 'float32' or 'float64', got {self.score_dtype!r}")
        if self.hops_max < self.hops_full:
            raise InputError("completion: hops_max must be >= hops_full")


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
            if confidence[i] >= 1.0 - 1e-9 and a > 1e-9 and b > 1e-9:
                ratios.append(b / a)
    return float(np.median(ratios)) if ratios else 1.0


def map_pose(skeleton_out: Skeleton, skeleton_in: Skeleton, bone_map, T, R, S, *, blend=True):
    """Keyframes of one input expressed as local transforms of the output skeleton S_R.

    Rotations move as rest-relative deltas in the joint frame: an output joint ``o`` reached
    by input joints ``i_1 < ... < i_k`` gets ``R_o = rest_o * D`` with
    ``D = (rest_i1 ... rest_ik)^-1 (R_i1 ... R_ik)`` (exact for a chain), blended toward
    identity by ``1 - c`` (``c``: the largest confidence among them). Translations and scales
    come from the first of them with that confidence, as deltas from its rest value
    (translations rescaled by the bone-length ratio of the confidence-1 copies). Output joints
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
    k = _map_scale(skeleton_out, skeleton_in, contributors, conf)
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
    single = np.array([len(contributors[o]) == 1 for o in outs])
    first = np.array([contributors[o][0] for o in outs])
    delta[:, single] = quat_multiply(quat_conjugate(rest_in[first[single]]), R[:, first[single]])
    for k in np.flatnonzero(~single):
        ins = contributors[outs[k]]
        anim, rest = R[:, ins[0]], rest_in[ins[0]]
        for i in ins[1:]:
            anim = quat_multiply(anim, R[:, i])
            rest = quat_multiply(rest, rest_in[i])
        delta[:, k] = quat_multiply(quat_conjugate(rest), anim)
    cs = [conf[contributors[o]] for o in outs]
    mass[outs] = [min(1.0, float(c.sum())) for c in cs]
    cmax = np.array([float(c.max()) for c in cs])
    lead = np.array([contributors[o][int(np.argmax(c))] for o, c in zip(outs, cs)])
    f = cmax if blend else np.ones_like(cmax)
    if blend and np.any(cmax < 1.0):
        low = np.flatnonzero(cmax < 1.0)
        delta[:, low] = quat_slerp(delta[:, low], _IDENTITY, np.broadcast_to(1.0 - cmax[low], (F, low.size)))
    R_out[:, outs] = quat_multiply(rest_out[outs], delta)
    T_out[:, outs] += (f * k)[:, None] * (T[:, lead] - skeleton_in.translations[lead])
    s_rest = skeleton_in.scales[lead]
    s_rest = np.where(np.abs(s_rest) > 1e-12, s_rest, 1.0)
    S_out[:, outs] *= np.clip(S[:, lead] / s_rest, 1e-9, None) ** f[:, None]
    return T_out, quat_normalize(R_out), S_out, mass


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
    R = np.asarray(R, dtype=np.float64)
    G = np.empty_like(R)
    for j, p in enumerate(parents):
        G[:, j] = R[:, j] if p < 0 else quat_multiply(G[:, p], R[:, j])
    return quat_normalize(G)


def _quat_rotate(q, v):
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)`` xyzw."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _global_positions(skeleton, T, R, S):
    """World joint positions ``(F, J, 3)`` by quaternion forward kinematics.

    Scales accumulate per axis (exact for uniform scales, which is what rigs animate); the
    roots' anchor matrices are applied.
    """
    F, J = T.shape[:2]
    P = np.empty((F, J, 3))
    G = np.empty((F, J, 4))
    sw = np.empty((F, J, 3))
    for j, p in enumerate(skeleton.parents):
        if p < 0:
            G[:, j], sw[:, j], P[:, j] = R[:, j], S[:, j], T[:, j]
        else:
            G[:, j] = quat_multiply(G[:, p], R[:, j])
            sw[:, j] = sw[:, p] * S[:, j]
            P[:, j] = P[:, p] + _quat_rotate(G[:, p], sw[:, p] * T[:, j])
    A = skeleton.root_parent_worlds()  # (J, 4, 4), constant per joint
    return np.einsum("jkl,fjl->fjk", A[:, :3, :3], P) + A[:, :3, 3]


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


def _score_features(G, P, w, rotation_weight, translation_weight, length):
    """Features ``X`` and offsets ``c`` with ``score[a, b] = X_a . X_b - c_a - c_b + tw``.

    Rotation features of the kept joints (weight > 0) scaled by ``sqrt(rotation_weight w /
    sum w)``, then weighted positions scaled by ``sqrt(2 ct)``; ``c = ct sum_j w_j |p_j|^2``
    with ``ct = translation_weight / (sum w length^2)``.
    """
    keep = np.flatnonzero(w > 0)
    wk = w[keep]
    total = wk.sum()
    cr = rotation_weight / total
    ct = translation_weight / (total * max(length, 1e-12) ** 2)
    p = (np.asarray(P, dtype=np.float64)[:, keep] * np.sqrt(wk)[:, None]).reshape(len(P), -1)
    X = np.concatenate([np.sqrt(cr) * rotation_features(np.asarray(G)[:, keep], wk),
                        np.sqrt(2 * ct) * p], axis=1)
    return X, ct * np.einsum("ij,ij->i", p, p)


def keyframe_scores(Ga, Pa, Gb, Pb, w, *, rotation_weight=0.8, translation_weight=0.2,
                    length=1.0, metric="squared", dtype=np.float64) -> np.ndarray:
    """Similarity of every pair of keyframes (higher is more alike), one matrix product.

    ``score[a, b] = rotation_weight * sum_j w_j r(Ga_aj, Gb_bj) / sum w
    + translation_weight * (1 - sum_j w_j |Pa_aj - Pb_bj|^2 / (sum w * length^2))``, with
    ``r = <q_a, q_b>^2`` (``metric="squared"``) or ``|<q_a, q_b>|`` (``"abs"``).

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
        Of the matrix product and the result. ``float32`` halves time and memory: the features
        are centred on the candidates' mean first, so rounding scales with the spread of the
        poses rather than with the scores themselves (about 1e-7 absolute).

    Returns
    -------
    (Fa, Fb) array of ``dtype``, at most ``rotation_weight + translation_weight``.
    """
    w = np.asarray(w, dtype=np.float64)
    Fa, Fb = len(Ga), len(Gb)
    if not np.any(w > 0):
        return np.full((Fa, Fb), rotation_weight + translation_weight, dtype=dtype)
    Ga, Gb = quat_normalize(Ga), quat_normalize(Gb)
    if metric == "squared":
        cand = _Candidates.build(Gb, Pb, w, rotation_weight, translation_weight, length, dtype)
        return cand.scores(Ga, Pa)
    if metric != "abs":
        raise InputError(f"completion: metric must be 'squared' or 'abs', got {metric!r}")
    # the paper's |<q_a, q_b>|: one (Fa, 4) @ (4, Fb) product per joint, no loop on pairs
    Xa, ca = _score_features(Ga, Pa, w, 0.0, translation_weight, length)
    Xb, cb = _score_features(Gb, Pb, w, 0.0, translation_weight, length)
    score = Xa @ Xb.T
    keep = np.flatnonzero(w > 0)
    cr = rotation_weight / w[keep].sum()
    for j in keep:
        score += (cr * w[j]) * np.abs(Ga[:, j] @ Gb[:, j].T)
    score -= ca[:, None]
    score -= cb[None, :]
    score += translation_weight
    return score.astype(dtype, copy=False)


@dataclass(frozen=True)
class _Candidates:
    """The candidate side of :func:`keyframe_scores` (``metric="squared"``), built once.

    ``score = (X_a - m)(X_b - m)^T + (X_a m - c_a) + (X_b m - c_b - m.m + tw)``: the product
    of centred features in ``dtype``, the rank-one terms in float64.
    """

    w: np.ndarray
    weights: tuple
    mean: np.ndarray  # (K,)
    Xc: np.ndarray  # (Fb, K) centred, dtype
    col: np.ndarray  # (Fb,) dtype

    @classmethod
    def build(cls, Gb, Pb, w, rotation_weight, translation_weight, length, dtype):
        weights = (rotation_weight, translation_weight, length)
        Xb, cb = _score_features(Gb, Pb, w, *weights)
        m = Xb.mean(axis=0)
        col = Xb @ m - cb - m @ m + translation_weight
        return cls(w, weights, m, (Xb - m).astype(dtype), col.astype(dtype))

    def scores(self, Ga, Pa):
        Xa, ca = _score_features(Ga, Pa, self.w, *self.weights)
        row = (Xa @ self.mean - ca).astype(self.Xc.dtype)
        score = (Xa - self.mean).astype(self.Xc.dtype) @ self.Xc.T  # (Fa, Fb)
        score += row[:, None]
        score += self.col[None, :]
        return score


def _segments_next(segment):
    """``succ[b]``: the next frame of the same clip, -1 at a clip's last frame."""
    segment = np.asarray(segment)
    succ = np.arange(1, len(segment) + 1)
    last = np.ones(len(segment), dtype=bool)
    last[:-1] = segment[1:] != segment[:-1]
    succ[last] = -1
    return succ


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
    buf = np.empty_like(score)
    for step, wk in enumerate(weights, start=1):
        if wk == 0:
            continue
        for k in (-step, step):
            a0, a1 = max(0, -k), min(Fa, Fa - k)
            b0, b1 = max(0, -k), min(Fb, Fb - k)
            if a1 <= a0 or b1 <= b0:
                continue
            same = np.zeros(Fb, dtype=score.dtype)
            same[b0:b1] = seg[b0 + k:b1 + k] == seg[b0:b1]
            rv = np.zeros(Fa, dtype=score.dtype)
            rv[a0:a1] = wk
            rows.append(rv)
            cols.append(same)
            view = buf[a0:a1, b0:b1]
            np.multiply(score[a0 + k:a1 + k, b0 + k:b1 + k], same[b0:b1] * score.dtype.type(wk), out=view)
            out[a0:a1, b0:b1] += view
    if rows:
        norm = np.stack(rows, axis=1) @ np.stack(cols, axis=0)  # (Fa, Fb), rank <= 2 * steps
        norm += 1.0
        out /= norm
    return out


def choose_frames(score, segment_b, *, jump_penalty=0.0, fixed=None) -> np.ndarray:
    """Candidate frame per query frame, maximizing the total score (Viterbi over frames).

    Continuing from candidate ``b`` to ``b + 1`` of the same clip is free; any other step
    costs ``jump_penalty``. With ``jump_penalty=0`` this is the best frame per row.

    Parameters
    ----------
    score : (Fa, Fb) float array
    segment_b : (Fb,) int array
        Candidate clip of each column.
    jump_penalty : float
    fixed : mapping of int to int, optional
        Query frame -> pinned candidate frame.

    Returns
    -------
    (Fa,) int64 column per row.
    """
    score = np.asarray(score)
    Fa, Fb = score.shape
    if fixed:
        score = score.copy()
    for a, b in (fixed or {}).items():
        if not (0 <= a < Fa and 0 <= b < Fb):
            raise InputError(f"completion: fixed frame {a} -> {b} outside ({Fa}, {Fb})")
        row = np.full(Fb, -np.inf)
        row[b] = score[a, b]
        score[a] = row
    if jump_penalty <= 0:
        return np.argmax(score, axis=1).astype(np.int64)
    succ = _segments_next(segment_b)
    index = np.int32 if Fb < 2**31 - 1 else np.int64
    pred = np.full(Fb, Fb, dtype=index)  # index Fb reads the -inf padding: no predecessor
    has = succ >= 0
    pred[succ[has]] = np.flatnonzero(has)
    back = np.empty((Fa, Fb), dtype=index)
    Vp = np.empty(Fb + 1)
    Vp[Fb] = -np.inf
    Vp[:Fb] = score[0]
    for a in range(1, Fa):  # a loop over query frames; each step is vectorized over Fb
        best = int(np.argmax(Vp[:Fb]))
        jump = Vp[best] - jump_penalty
        stay = Vp[pred]
        take_stay = stay >= jump
        back[a] = np.where(take_stay, pred, index(best))
        np.maximum(stay, jump, out=stay)
        np.add(score[a], stay, out=Vp[:Fb])
    V = Vp[:Fb]
    path = np.empty(Fa, dtype=np.int64)
    path[-1] = int(np.argmax(V))
    for a in range(Fa - 1, 0, -1):
        path[a - 1] = back[a, path[a]]
    return path


def blend_seams(R, T, seams, frames) -> tuple[np.ndarray, np.ndarray]:
    """Remove the jumps at seams with offsets that fade out (inertial blending).

    At a seam ``t -> t + 1`` the pose the old frames were heading to (constant-velocity
    extrapolation of frames ``t - 1, t``) replaces frame ``t + 1``; the offset between the two
    fades to zero over ``frames`` frames with a smoothstep (zero slope at both ends), so the
    new frames take over without a jump. Seams are processed in order, each from the frames
    already corrected.

    Parameters
    ----------
    R : (F, J, 4) float array
        Local rotations, xyzw.
    T : (F, J, 3) float array
        Local translations.
    seams : (s,) int array
        Frames ``t`` such that ``t -> t + 1`` jumps.
    frames : int
        Length of the fade (0: none).

    Returns
    -------
    R : (F, J, 4) float64, T : (F, J, 3) float64
    """
    R = quat_normalize(R).copy()
    T = np.asarray(T, dtype=np.float64).copy()
    F = len(R)
    if frames <= 0:
        return R, T
    for t in np.unique(np.asarray(seams, dtype=np.int64)):
        if not 0 <= t < F - 1:
            continue
        if t >= 1:
            vel = quat_multiply(quat_conjugate(R[t - 1]), R[t])
            r_ext = quat_multiply(R[t], vel)
            t_ext = 2 * T[t] - T[t - 1]
        else:
            r_ext, t_ext = R[t], T[t]
        off_r = quat_multiply(r_ext, quat_conjugate(R[t + 1]))  # (J, 4), left offset
        off_r = np.where(off_r[..., 3:4] < 0, -off_r, off_r)
        off_t = t_ext - T[t + 1]
        n = min(int(frames), F - 1 - t)
        x = np.arange(n) / float(frames)
        fade = 1.0 - (3 * x**2 - 2 * x**3)  # 1 at the seam, 0 after `frames`
        span = slice(t + 1, t + 1 + n)
        off = quat_slerp(np.broadcast_to(_IDENTITY, (n,) + off_r.shape),
                         np.broadcast_to(off_r, (n,) + off_r.shape), fade[:, None])
        R[span] = quat_multiply(off, R[span])
        T[span] += fade[:, None, None] * off_t
    return R, T


def smooth_seams(R, T, seams, sigma) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing of rotation and translation tracks near seams only.

    Each frame is blended toward its Gaussian-smoothed value with weight
    ``exp(-d^2 / (2 (2 sigma)^2))``, ``d`` its distance to the nearest seam: far from seams
    the tracks are unchanged.

    Parameters
    ----------
    R : (F, J, 4) float array
        Local rotations, xyzw.
    T : (F, J, 3) float array
        Local translations.
    seams : (s,) int array
        Frames ``t`` such that ``t -> t + 1`` jumps.
    sigma : float
        Standard deviation in frames (0: no smoothing).

    Returns
    -------
    R : (F, J, 4) float64, T : (F, J, 3) float64
    """
    from scipy.ndimage import gaussian_filter1d

    R = quat_normalize(R)
    T = np.asarray(T, dtype=np.float64).copy()
    seams = np.asarray(seams, dtype=np.float64).reshape(-1)
    F = len(R)
    if sigma <= 0 or seams.size == 0 or F < 3:
        return R, T
    dots = np.sum(R[1:] * R[:-1], axis=-1)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    R = R.copy()
    R[1:] *= flips[..., None]  # hemisphere-continuous before averaging
    Rs = quat_normalize(gaussian_filter1d(R, sigma, axis=0, mode="nearest"))
    Ts = gaussian_filter1d(T, sigma, axis=0, mode="nearest")
    d = np.min(np.abs(np.arange(F)[:, None] - (seams[None, :] + 0.5)), axis=1) - 0.5
    alpha = np.exp(-0.5 * (d / (2.0 * sigma)) ** 2)[:, None, None]
    R = quat_normalize((1 - alpha) * R + alpha * Rs)
    T = (1 - alpha) * T + alpha * Ts
    return R, T


def angular_acceleration(R, fps=30.0) -> np.ndarray:
    """Magnitude of the angular acceleration of local rotation tracks.

    Angular velocity between consecutive frames is the rotation vector of
    ``q_t^-1 q_{t+1}`` times ``fps``; acceleration is its finite difference times ``fps``.

    Parameters
    ----------
    R : (F, J, 4) float array
        Rotations at a fixed rate, xyzw.
    fps : float

    Returns
    -------
    (F - 2, J) float64, radians per second squared.
    """
    R = quat_normalize(R)
    rel = quat_multiply(quat_conjugate(R[:-1]), R[1:])  # (F-1, J, 4)
    rel = np.where(rel[..., 3:4] < 0, -rel, rel)
    s = np.linalg.norm(rel[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, rel[..., 3:4])
    omega = np.where(s > 1e-12, rel[..., :3] / np.where(s > 1e-12, s, 1.0) * angle, 2 * rel[..., :3])
    omega = omega * fps
    return np.linalg.norm(np.diff(omega, axis=0), axis=-1) * fps


# --------------------------------------------------------------------------------------------
# the stage


@dataclass(frozen=True)
class _Frames:
    """Every clip of one input, resampled and mapped onto S_R, clips concatenated."""

    names: tuple[str, ...]
    start: np.ndarray  # (C + 1,) frame offsets of the clips
    times: tuple[np.ndarray, ...]  # per clip, seconds
    T: np.ndarray  # (F, J, 3) local on S_R
    R: np.ndarray  # (F, J, 4)
    S: np.ndarray  # (F, J, 3)
    G: np.ndarray  # (F, J, 4) global rotations on S_R
    P: np.ndarray  # (F, J, 3) world positions on S_R
    mass: np.ndarray  # (J,)

    def rows(self, c):
        return slice(int(self.start[c]), int(self.start[c + 1]))


def _sample_input(skeleton_out, character, bone_map, fps, blend):
    names, times, Ts, Rs, Ss = [], [], [], [], []
    J = skeleton_out.num_joints
    mass = np.zeros(J)
    for clip in character.clips:
        t = clip_times(clip, fps)
        T, R, S = sample_clip(character.skeleton, clip, t)
        To, Ro, So, mass = map_pose(skeleton_out, character.skeleton, bone_map, T, R, S, blend=blend)
        names.append(clip.name)
        times.append(t)
        Ts.append(To)
        Rs.append(Ro)
        Ss.append(So)
    if not names:
        empty = np.zeros((0, J, 3))
        return _Frames((), np.zeros(1, dtype=np.int64), (), empty, np.zeros((0, J, 4)), empty,
                       np.zeros((0, J, 4)), empty, mass)
    T, R, S = np.concatenate(Ts), np.concatenate(Rs), np.concatenate(Ss)
    start = np.concatenate([[0], np.cumsum([len(t) for t in times])]).astype(np.int64)
    G = global_rotations(skeleton_out.parents, R)
    P = _global_positions(skeleton_out, T, R, S)
    return _Frames(tuple(names), start, tuple(times), T, R, S, G, P, mass)


def _owners(skeleton_out, maps, ids, provenance):
    """``(J,)`` list of the input ids each output joint comes from."""
    J = skeleton_out.num_joints
    if provenance is not None:
        if len(provenance) != J:
            raise InputError(f"completion: provenance has {len(provenance)} entries, S_R has {J} joints")
        return [tuple(dict.fromkeys(cid for cid, _ in prov if cid in ids)) for prov in provenance]
    owners = [[] for _ in range(J)]
    for cid in ids:
        m = maps[cid]
        for i, (o, c) in enumerate(zip(np.asarray(m.target), np.asarray(m.confidence))):
            if 0 <= o < J and c >= 1.0 - 1e-9 and cid not in owners[o]:
                owners[o].append(cid)
    return [tuple(o) for o in owners]


def _unique_names(keys):
    """Output clip names: the source names, prefixed ``<character id>:`` where they clash."""
    count = {}
    for _, name in keys:
        count[name] = count.get(name, 0) + 1
    out, used = [], set()
    for cid, name in keys:
        base = name if count[name] == 1 else f"{cid}:{name}"
        cand, n = base, 2
        while cand in used:
            cand, n = f"{base}_{n}", n + 1
        used.add(cand)
        out.append(cand)
    return out


def _selected(inputs, options, selection):
    if selection is not None:
        keys = [(str(cid), str(name)) for cid, name in selection]
    elif options.clips is not None:
        keys = [(cid, name) for cid, names in options.clips.items() for name in names]
    else:
        keys = [(cid, c.name) for cid, ch in inputs.items() for c in ch.clips]
    for cid, name in keys:
        if cid not in inputs:
            raise InputError(f"completion: clip selection names character {cid!r}, inputs are {sorted(inputs)}")
        if name not in {c.name for c in inputs[cid].clips}:
            where = inputs[cid].source or inputs[cid].name
            raise InputError(f"completion: {where} (character {cid!r}) has no clip {name!r}")
    return keys


def _pool(frames, names):
    """Rows of the candidate clips ``names`` (all when None) and their clip index per row."""
    idx = [c for c, n in enumerate(frames.names) if names is None or n in set(names)]
    rows = np.concatenate([np.arange(frames.start[c], frames.start[c + 1]) for c in idx]) if idx else np.zeros(0, int)
    seg = np.concatenate([np.full(frames.start[c + 1] - frames.start[c], c) for c in idx]) if idx else np.zeros(0, int)
    return rows.astype(np.int64), seg.astype(np.int64)


def _merge_joints(parents, owners, x, y):
    """Joints fused between x and y, else the boundary of y's part."""
    fused = [o for o, ow in enumerate(owners) if x in ow and y in ow]
    if fused:
        return np.asarray(fused)
    part = np.array([y in ow for ow in owners])
    bound = [j for j, p in enumerate(parents) if p >= 0 and part[j] != part[p]]
    bound = [j if part[j] else int(parents[j]) for j in bound]
    return np.asarray(sorted(set(bound)) or np.flatnonzero(part)[:1], dtype=np.int64)


def _pair(fx, fy, pool_rows, parents, owners, x, y, options, length):
    """Joint weights, position anchor and (squared metric) candidate features of a pair."""
    merge = _merge_joints(parents, owners, x, y)
    hop = hop_weights(parents, merge, full=options.hops_full, cutoff=options.hops_max)
    w = hop * fx.mass * fy.mass
    if w.sum() <= 0:
        logger.warning("completion: no joint of S_R is mapped from both %r and %r near the "
                       "merge joint; scoring with hop weights only", x, y)
        w = hop
    anchor = int(merge[0])
    cand = None
    if options.metric == "squared" and np.any(w > 0):
        Pb = fy.P[pool_rows] - fy.P[pool_rows][:, anchor:anchor + 1]
        cand = _Candidates.build(fy.G[pool_rows], Pb, w, options.rotation_weight,
                                 options.translation_weight, length, np.dtype(options.score_dtype))
    return w, anchor, cand


def complete_clips(skeleton_out: Skeleton, inputs: Mapping[str, Character], maps: Mapping, *,
                   selection: Sequence[tuple[str, str]] | None = None,
                   options: CompletionOptions | None = None,
                   provenance: Sequence[Sequence[tuple[str, int]]] | None = None) -> tuple[Clip, ...]:
    """Complete the selected clips of every input on the output skeleton S_R.

    Parameters
    ----------
    skeleton_out : Skeleton
        S_R, ``J`` joints.
    inputs : mapping of str to Character
        The input characters by id (the ids of the bone maps and provenance).
    maps : mapping of str to BoneMap
        Per id: ``target (J_in,)`` output joint or -1 and ``confidence (J_in,)``.
    selection : sequence of (character id, clip name), optional
        The clips to complete (overrides ``options.clips``; default every clip of every input).
    options : CompletionOptions, optional
    provenance : sequence of sequence of (str, int), optional
        Per output joint, the (character id, input joint) it comes from (the plan's); without
        it, a joint comes from the inputs that reach it with confidence 1.

    Returns
    -------
    tuple of Clip
        One per selected clip, on S_R, named after the source clip (``"<id>:<name>"`` where two
        inputs share a name); ``LINEAR`` translation, rotation and scale tracks on every joint,
        keys at ``options.fps`` from the source clip's start.
    """
    options = options or CompletionOptions()
    ids = list(inputs)
    for cid in ids:
        if cid not in maps:
            raise InputError(f"completion: no bone map for character {cid!r}")
        nin = inputs[cid].skeleton.num_joints
        if len(maps[cid].target) != nin:
            raise InputError(
                f"completion: bone map of {cid!r} has {len(maps[cid].target)} entries, "
                f"{inputs[cid].source or inputs[cid].name} has {nin} joints")
    keys = _selected(inputs, options, selection)
    if not keys:
        return ()
    J = skeleton_out.num_joints
    parents = skeleton_out.parents
    owners = _owners(skeleton_out, maps, ids, provenance)
    frames = {cid: _sample_input(skeleton_out, inputs[cid], maps[cid], options.fps,
                                 options.confidence_blend) for cid in ids}
    rest_world = skeleton_out.rest_worlds()[:, :3, 3]
    length = float(np.linalg.norm(rest_world.max(0) - rest_world.min(0))) if J else 1.0
    length = length if length > 1e-9 else 1.0
    names = _unique_names(keys)
    pairs = {}  # (clip's input, completing input) -> joint weights, anchor, candidate features
    fixed_by_clip = {}
    for ff in options.fixed_frames:
        fixed_by_clip.setdefault((ff.character, ff.clip), []).append(ff)

    out = []
    for (cid, clip_name), out_name in zip(keys, names):
        fx = frames[cid]
        c = fx.names.index(clip_name)
        rows = fx.rows(c)
        T, R, S = fx.T[rows].copy(), fx.R[rows].copy(), fx.S[rows].copy()
        Fa = len(T)
        completed = np.array([bool(ow) and cid not in ow for ow in owners])
        completed_joints = np.flatnonzero(completed)
        seams = []
        # each other input completes the joints it owns (the first owner listed)
        by_owner = {}
        for o in completed_joints:
            ow = owners[o]
            best = max(ow, key=lambda y: frames[y].mass[o])
            by_owner.setdefault(best, []).append(o)
        for y, joints in by_owner.items():
            fy = frames[y]
            src_names = None if options.sources is None else options.sources.get(y)
            pool_rows, seg = _pool(fy, src_names)
            if pool_rows.size == 0:
                logger.warning("completion: character %r has no clip to complete %r of %r; "
                               "its joints stay at rest", y, clip_name, cid)
                continue
            if (cid, y) not in pairs:
                pairs[(cid, y)] = _pair(fx, fy, pool_rows, parents, owners, cid, y, options, length)
            w, anchor, cand = pairs[(cid, y)]
            Pa = fx.P[rows] - fx.P[rows][:, anchor:anchor + 1]
            if cand is None:  # the paper's |.| metric: exact, no precomputation
                Pb = fy.P[pool_rows] - fy.P[pool_rows][:, anchor:anchor + 1]
                score = keyframe_scores(fx.G[rows], Pa, fy.G[pool_rows], Pb, w,
                                        rotation_weight=options.rotation_weight,
                                        translation_weight=options.translation_weight,
                                        length=length, metric=options.metric,
                                        dtype=np.dtype(options.score_dtype))
            else:
                score = cand.scores(fx.G[rows], Pa)
            score = continuity_scores(score, seg, options.continuity)
            fixed = {}
            for ff in fixed_by_clip.get((cid, clip_name), ()):
                if ff.source != y:
                    continue
                if ff.source_clip not in fy.names:
                    raise InputError(f"completion: fixed frame names clip {ff.source_clip!r}, "
                                     f"character {y!r} has {list(fy.names)}")
                sc = fy.names.index(ff.source_clip)
                hit = np.flatnonzero((seg == sc))
                if not 0 <= ff.source_frame < hit.size:
                    raise InputError(f"completion: fixed frame {ff.source_frame} outside clip "
                                     f"{ff.source_clip!r} ({hit.size} frames at {options.fps} fps)")
                fixed[int(ff.frame)] = int(hit[ff.source_frame])
            choice = choose_frames(score, seg, jump_penalty=options.jump_penalty, fixed=fixed)
            src = pool_rows[choice]
            joints = np.asarray(joints)
            ix = np.ix_(src, joints)
            T[:, joints] = fy.T[ix]
            R[:, joints] = fy.R[ix]
            S[:, joints] = fy.S[ix]
            succ = _segments_next(seg)
            jumps = np.flatnonzero(succ[choice[:-1]] != choice[1:])
            jumps = _discontinuities(R[:, joints], jumps)
            seams.append(jumps)
            logger.debug("completion: %r of %r from %r: %d seams", clip_name, cid, y, jumps.size)
        if completed_joints.size and seams:
            s = np.unique(np.concatenate(seams))
            Rc, Tc = blend_seams(R[:, completed_joints], T[:, completed_joints], s, options.blend_frames)
            Rc, Tc = smooth_seams(Rc, Tc, s, options.smoothing)
            R[:, completed_joints] = Rc
            T[:, completed_joints] = Tc
        out.append(_to_clip(out_name, fx.times[c], T, R, S))
    return tuple(out)


def _discontinuities(R, jumps, *, ratio=2.0, floor=1e-3):
    """The jumps that are real discontinuities of the rotation tracks ``R (F, J, 4)``.

    A jump ``t -> t + 1`` between non-consecutive source frames (e.g. the end of a looping
    clip back to its start) is a seam only if its largest joint rotation step exceeds
    ``floor`` radians and ``ratio`` times the steps just before and after it.
    """
    if len(jumps) == 0 or len(R) < 2:
        return np.asarray(jumps, dtype=np.int64)
    step = np.max(quat_angle(R[:-1], R[1:]), axis=1)  # (F - 1,)
    before = np.where(jumps > 0, step[np.maximum(jumps - 1, 0)], 0.0)
    after = np.where(jumps + 1 < len(step), step[np.minimum(jumps + 1, len(step) - 1)], 0.0)
    real = step[jumps] > np.maximum(floor, ratio * np.maximum(before, after))
    return np.asarray(jumps, dtype=np.int64)[real]


def _to_clip(name, times, T, R, S):
    R = quat_normalize(R)
    if len(R) > 1:
        dots = np.sum(R[1:] * R[:-1], axis=-1)
        flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
        R = R.copy()
        R[1:] *= flips[..., None]
    tracks = []
    for j in range(T.shape[1]):
        tracks.append(Track(j, "translation", times, T[:, j], "LINEAR"))
        tracks.append(Track(j, "rotation", times, R[:, j], "LINEAR"))
        tracks.append(Track(j, "scale", times, S[:, j], "LINEAR"))
    return Clip(name, tuple(tracks))


def options_from_config(section) -> CompletionOptions:
    """:class:`CompletionOptions` from a config section (pydantic model, mapping or None).

    Unknown keys are an :class:`InputError` naming them and the known ones; fixed frames may
    be given as mappings with the fields of :class:`FixedFrame`.
    """
    if section is None:
        return CompletionOptions()
    if isinstance(section, CompletionOptions):
        return section
    data = section.model_dump() if hasattr(section, "model_dump") else dict(section)
    known = {f.name for f in dataclasses.fields(CompletionOptions)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise InputError(f"completion: unknown animation option(s) {unknown}; known: {sorted(known)}")
    if "fixed_frames" in data:
        data["fixed_frames"] = tuple(ff if isinstance(ff, FixedFrame) else FixedFrame(**dict(ff))
                                     for ff in data["fixed_frames"] or ())
    if "continuity" in data and data["continuity"] is not None:
        data["continuity"] = tuple(data["continuity"])
    return CompletionOptions(**{k: v for k, v in data.items() if v is not None or k in ("clips", "sources")})


def completion_stage(composition, progress=None):
    """The animation stage of :func:`rigmix.pipeline.compose`: A_R from the plan and the maps.

    Reads the options from ``composition.config.animation`` when the config has that section;
    completes the clips of the inputs as loaded (rest-relative deltas carry them onto S_R,
    whatever scale and rest pose the positioning chose).

    Returns
    -------
    Composition
        With ``stages["clips"]`` (tuple of Clip on S_R) and ``report["animation"]``.
    """
    from dataclasses import replace

    options = options_from_config(getattr(composition.config, "animation", None))
    plan = composition.plan
    clips = complete_clips(plan.skeleton, composition.inputs, composition.maps,
                           options=options, provenance=plan.provenance)
    report = {"clips": [c.name for c in clips], "fps": options.fps,
              "frames": [int(len(c.tracks[0].times)) if c.tracks else 0 for c in clips],
              "jump_penalty": options.jump_penalty, "metric": options.metric}
    return replace(composition, stages={**composition.stages, "clips": clips},
                   report={**composition.report, "animation": report})
