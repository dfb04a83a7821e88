"""Animation completion (SkinMixer section 8; PIPELINE.md section 5): the clips A_R of S_R.

Each selected clip of one input X drives the joints of S_R that come from X; the joints of the
other part(s) (the *completed part*) take the local transforms of frames chosen, per output
frame, among all frames of all clips of the other input(s) Y:

1. resample every clip to ``fps`` (30) with :func:`rigmix.animation.sample_clip`;
2. map every keyframe onto S_R through the bone maps (:func:`map_pose`): rest-relative local
   rotations, unmapped joints at rest (identity delta), several input joints on one output
   joint accumulate (only its own where the joint is kept from that input), confidence
   ``c < 1`` blends the delta toward identity by ``1 - c``; translation keys through
   :func:`translation_maps` (composed scale, the input's own armature scale, S_R's unit-scale
   frames);
3. global rotations and positions by forward kinematics on S_R;
4. score all pairs (query frame of X, candidate frame of Y) with one matrix product
   (:func:`keyframe_scores`), add the temporal continuity terms as shifted-diagonal sums
   (:func:`continuity_scores`), pick the frames (:func:`choose_frames`);
5. assemble; where the chosen frames jump (seams), fade the jump out over a few frames
   (:func:`blend_seams`) and smooth lightly around it (:func:`smooth_seams`).

The kernels live in :mod:`rigmix.animation.keyframes` (mapping onto S_R, scoring, with the choice of
the rotation term explained there) and :mod:`rigmix.animation.transitions` (frame choice, seams).

Choices where the method leaves room (all options of :class:`CompletionOptions`)
-------------------------------------------------------------------------------
* Which joints come from which input: the plan's provenance when given, else the joints an
  input reaches with confidence 1. The pipeline's stage drops the target from a replaced
  limb's fused root when the two rest bones point more than ``rest_mismatch`` (60) degrees
  apart (:func:`limb_roots_to_complete`): a T-pose arm's walk would swing a hanging leg out.
  Measured rest angles: beast_arms arms 90 and neck 71, fox_arm 63 (completed); three_characters
  53 and 55, the centaurs 40 and 51 (kept). Completing beast_arms' arms keeps its junction stretch
  ratio at 0.96 (3.43 with the source's T-pose swing).
* Joint weights: prototype hop weights from the merge joint(s) (the joints fused between the
  clip's input and the completing one) times the confidence masses of both sides.
* A completing input that is the same asset as the clip's input in the same orientation (a
  file listed twice) has the clip itself: its joints replay it frame by frame (:func:`_own_clip`).
  A mirrored copy of the clip's input (:attr:`rigmix.character.Character.mirrored` differs) has
  the clip reflected, where each side moves as the other side does: its joints that a joint of
  the clip's input of the same name reaches (the joint each replaces, on the same side) keep
  the clip's own motion of that joint instead (:func:`_mirrored_copies`, :func:`_same_named`), so
  that a leg replaced by its mirrored partner steps as the leg it replaces, in phase with the
  body: the reflected clip would mix the two sides along the leg (the fused hip and foot moving
  with one side, the lower leg with the other) and stretch the junction.
* Detached parts (:attr:`rigmix.limbs.Limb.detached`: an IK foot under the armature root) of
  a limb moved to another body follow the limb's tip, last, in every clip
  (:mod:`rigmix.animation.detached`): at their offset to it in their input's own clip where
  that clip plays, else at their rest offset. A foot keyed root-relative would keep the donor
  body's motion while its leg hangs from the other body's hip, and stretch the foot's skin.
* Frame choice: the paper takes the best frame per output frame (``jump_penalty=0``); a
  positive ``jump_penalty`` runs a Viterbi pass where continuing to the next frame of the same
  clip is free and any other jump costs the penalty (fewer seams, smoother completed part).
  Default 0.2 (scores are in [0, 1] per frame). Measured (``benchmarks/completion_bench.py``:
  mean angular acceleration of the completed joints over that of their source clips) on the
  pipeline's Horse + Knight centaur, horse clips: 1.25 with the paper's rule, 2.41 with a
  penalty of 0.05, 0.65 with 0.2; every test config stays under 1.5 with 0.2.
* Translation term: ``exp(-weighted mean squared distance / extent^2)`` rather than a linear
  one, so that both terms lie in [0, 1]; a linear term let far-off positions mapped with low
  confidence dominate (CesiumMan + Fox arm: the path then looped over five frames, 20 times
  the source's acceleration; 0.04 with the bounded term).
* Seams (jumps between non-consecutive source frames that make a real discontinuity): the jump
  fades out over ``blend_frames`` (inertial blending), then a Gaussian smoothing acts near the
  seam only, on the completed joints only; continuous playback of a source clip is left
  exactly as it was (self-composition reproduces the clips exactly).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, Mapping, Sequence

import numpy as np

from ..character import Character, Clip, Skeleton, Track
from ..errors import InputError
from ..rig import unique_names
from ..transforms import quat_normalize
from .detached import Follower, follow_tips, source_offsets
from .keyframes import (
    KEPT_CONFIDENCE,
    Candidates,
    continuity_scores,
    forward_kinematics,
    global_rotations,
    hop_weights,
    keyframe_scores,
    map_pose,
    rotation_features,
)
from .sampling import clip_times, sample_clip
from .transitions import angular_acceleration, blend_seams, choose_frames, discontinuities, segments_next, smooth_seams

__all__ = [
    "FixedFrame",
    "CompletionOptions",
    "complete_clips",
    "selected_clips",
    "same_asset",
    "translation_maps",
    # the kernels, re-exported
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
]

logger = logging.getLogger(__name__)

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
        Clips to complete, per character id (``None``: every clip of every input, once: a
        file listed under two ids gives its clips under the first; an id left out: none of
        its clips).
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
    rest_mismatch : float
        Degrees. A fused joint whose children all come from the source (a replaced limb) and
        whose target bone points more than this away from the new limb in the rest pose is
        completed from the source in the target's clips too (:func:`limb_roots_to_complete`):
        the target's rest-relative rotation of that joint (a T-pose arm lowered by 72 degrees
        in a walk) would swing the new limb (a hanging leg) the same 72 degrees out of place.
        180: never.
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
    rest_mismatch: float = 60.0

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


def _sample_input(skeleton_out, character, bone_map, fps, blend, maps=None):
    """All clips of one input resampled at ``fps``, mapped onto S_R, with forward kinematics
    (``maps``: its translation maps, see :func:`translation_maps`)."""
    n = character.skeleton.num_joints
    times = tuple(clip_times(clip, fps) for clip in character.clips)
    sampled = [sample_clip(character.skeleton, clip, t) for clip, t in zip(character.clips, times)]
    if sampled:
        T, R, S = (np.concatenate([x[k] for x in sampled]) for k in range(3))
    else:
        T, R, S = np.zeros((0, n, 3)), np.zeros((0, n, 4)), np.zeros((0, n, 3))
    T, R, S, mass = map_pose(skeleton_out, character.skeleton, bone_map, T, R, S, blend=blend,
                             translation_maps=maps)
    start = np.concatenate([[0], np.cumsum([len(t) for t in times])]).astype(np.int64)
    G, P = forward_kinematics(skeleton_out, T, R, S)
    return _Frames(tuple(c.name for c in character.clips), start, times, T, R, S, G, P, mass)


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
    """Output clip names: the source names, prefixed ``<character id>:`` where they clash, then
    made unique with ``_2``, ``_3``... (:func:`rigmix.rig.unique_names`)."""
    count = {}
    for _, name in keys:
        count[name] = count.get(name, 0) + 1
    return unique_names([name if count[name] == 1 else f"{cid}:{name}" for cid, name in keys],
                        suffix="_{}", start=2)


def selected_clips(inputs, options, selection=None):
    """The input clips that :func:`complete_clips` completes, in the order of its output clips.

    Parameters
    ----------
    inputs : mapping of str to Character
    options : CompletionOptions
        Its ``clips`` selection applies when ``selection`` is None.
    selection : sequence of (character id, clip name), optional
        As :func:`complete_clips`' ``selection``.

    Returns
    -------
    list of (str, str)
        ``(character id, clip name)`` per output clip: the selection, else ``options.clips``, else
        every clip of every input in input order.

    Raises
    ------
    InputError
        A selection naming an unknown character or clip.
    """
    if selection is not None:
        keys = [(str(cid), str(name)) for cid, name in selection]
    elif options.clips is not None:
        keys = [(cid, name) for cid, names in options.clips.items() for name in names]
    else:
        # a file listed under two ids is one Character: its clips are completed once, under
        # the first id (a self-composition writes each clip once, not as body:/donor: copies)
        seen, keys = set(), []
        for cid, ch in inputs.items():
            for c in ch.clips:
                if id(c) not in seen:
                    seen.add(id(c))
                    keys.append((cid, c.name))
    for cid, name in keys:
        if cid not in inputs:
            raise InputError(f"completion: clip selection names character {cid!r}, inputs are {sorted(inputs)}")
        if name not in {c.name for c in inputs[cid].clips}:
            raise InputError(f"completion: {inputs[cid].label} (character {cid!r}): no clip {name!r} to complete; "
                             f"its clips: {', '.join(repr(c.name) for c in inputs[cid].clips) or 'none'}")
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
        cand = Candidates.build(fy.G[pool_rows], Pb, w, options.rotation_weight,
                                 options.translation_weight, length, np.dtype(options.score_dtype))
    return w, anchor, cand


def complete_clips(skeleton_out: Skeleton, inputs: Mapping[str, Character], maps: Mapping, *,
                   selection: Sequence[tuple[str, str]] | None = None,
                   options: CompletionOptions | None = None,
                   provenance: Sequence[Sequence[tuple[str, int]]] | None = None,
                   translations: Mapping[str, np.ndarray] | None = None,
                   followers: Sequence[Follower] = ()) -> tuple[Clip, ...]:
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
        The clips to complete (overrides ``options.clips``; default every clip of every input,
        once).
    options : CompletionOptions, optional
    provenance : sequence of sequence of (str, int), optional
        Per output joint, the (character id, input joint) it comes from (the plan's); without
        it, a joint comes from the inputs that reach it with confidence 1.
    translations : mapping of str to (J_in, 3, 3) float array, optional
        Per id, the translation maps of :func:`translation_maps` (the plan's scales and frames);
        without them translation keys are rescaled by a bone-length ratio
        (:func:`rigmix.animation.keyframes.map_pose`).
    followers : sequence of Follower, optional
        Detached parts of moved limbs (:func:`rigmix.animation.detached.detached_followers`):
        in each clip, last, each is placed at its limb tip (:func:`_follow`).

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
                f"{inputs[cid].label} has {nin} joints")
    keys = selected_clips(inputs, options, selection)
    _check_fixed_frames(options.fixed_frames, inputs)
    if not keys:
        return ()
    J = skeleton_out.num_joints
    parents = skeleton_out.parents
    owners = _owners(skeleton_out, maps, ids, provenance)
    frames = {cid: _sample_input(skeleton_out, inputs[cid], maps[cid], options.fps, options.confidence_blend,
                                 None if translations is None else translations[cid]) for cid in ids}
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
        completed = np.flatnonzero([bool(ow) and cid not in ow for ow in owners])
        seams = []
        for y, joints in _completing_inputs(completed, owners, frames).items():
            if _mirrored_copies(inputs[cid], inputs[y]):
                # the clip's own joints of the same names drive them
                named = _same_named(inputs[cid], inputs[y], maps[cid], maps[y], J)[joints]
                own = _clip_pose(skeleton_out, inputs[cid], maps[cid], inputs[cid].clip(clip_name), options.fps,
                                 None if translations is None else translations[cid])
                for full, part in zip((T, R, S), own):
                    full[:, joints[named]] = part[:, joints[named]]
                joints = joints[~named]
                if joints.size == 0:
                    continue
            fy = frames[y]
            pool_rows, seg = _pool(fy, None if options.sources is None else options.sources.get(y))
            if pool_rows.size == 0:
                logger.warning("completion: character %r has no clip to complete %r of %r; its "
                               "joints keep that clip's mapped pose (rest where unmapped)", y, clip_name, cid)
                continue
            fixed = _fixed_rows(fixed_by_clip.get((cid, clip_name), ()), inputs, y, fy, seg, options.fps,
                                rows.stop - rows.start)
            choice = None if fixed else _own_clip(inputs[cid], inputs[y], fy, clip_name, seg, rows)
            if choice is None:
                if (cid, y) not in pairs:
                    pairs[(cid, y)] = _pair(fx, fy, pool_rows, parents, owners, cid, y, options, length)
                choice = _choose(fx, rows, fy, pool_rows, seg, pairs[(cid, y)], options, length, fixed)
            ix = np.ix_(pool_rows[choice], joints)
            T[:, joints], R[:, joints], S[:, joints] = fy.T[ix], fy.R[ix], fy.S[ix]
            jumps = np.flatnonzero(segments_next(seg)[choice[:-1]] != choice[1:])
            seams.append(discontinuities(R[:, joints], jumps))
            logger.debug("completion: %r of %r from %r: %d seams", clip_name, cid, y, seams[-1].size)
        if seams:
            s = np.unique(np.concatenate(seams))
            Rc, Tc = blend_seams(R[:, completed], T[:, completed], s, options.blend_frames)
            R[:, completed], T[:, completed] = smooth_seams(Rc, Tc, s, options.smoothing)
        T, R, S = _follow(skeleton_out, inputs, cid, clip_name, fx.times[c], T, R, S, followers)
        out.append(_to_clip(out_name, fx.times[c], T, R, S))
    return tuple(out)


def _follow(skeleton_out, inputs, cid, clip_name, times, T, R, S, followers):
    """``T, R, S`` of the clip ``clip_name`` of input ``cid`` with the detached parts placed at
    their limb tips (:func:`rigmix.animation.detached.follow_tips`).

    A part of the clip's own input keeps the offset to the tip it has in that clip, frame by
    frame; a part of another input, whose limb plays frames chosen from its clips (or a blend
    toward rest), keeps its rest offset. Where the part, its limb and the joints between them
    all come from the clip's asset or its mirrored copy (a self-composition), the clip drives
    them with one motion (:func:`_own_clip`, :func:`_same_named`): left as it is.
    """
    x = inputs[cid]
    mine = [f for f in followers
            if not all(same_asset(x, inputs[y]) or _mirrored_copies(x, inputs[y]) for y in (f.source, *f.between))]
    if not mine:
        return T, R, S
    own = [f for f in mine if f.source == cid]
    sampled = iter(source_offsets(inputs[cid], clip_name, times, own) if own else ())
    return follow_tips(skeleton_out, T, R, S, mine, [next(sampled) if f.source == cid else None for f in mine])


def _completing_inputs(completed, owners, frames):
    """Completed joints by the input that completes them (the owner with the most mass)."""
    by_owner = {}
    for o in completed:
        best = max(owners[o], key=lambda y: frames[y].mass[o])
        by_owner.setdefault(best, []).append(int(o))
    return {y: np.asarray(j, dtype=np.int64) for y, j in by_owner.items()}


def same_asset(x: Character, y: Character) -> bool:
    """Whether two inputs are one asset in one orientation: the same file or built-in listed
    twice, both mirrored or neither (a clip of one is the same motion of the other's joints)."""
    return (x.source, x.name) == (y.source, y.name) and x.mirrored == y.mirrored


def _mirrored_copies(x: Character, y: Character) -> bool:
    """Whether two inputs are one asset, one of them mirrored (:attr:`Character.mirrored`): a clip
    of one is, for the other, the reflected motion of the other side."""
    return (x.source, x.name) == (y.source, y.name) and x.mirrored != y.mirrored


def _same_named(x: Character, y: Character, map_x, map_y, J: int) -> np.ndarray:
    """``(J,)`` bool: output joints that ``y`` keeps (an input joint of confidence 1 maps there)
    and that a joint of ``x`` of the same name maps to, whatever its confidence.

    For a mirrored copy the names are the correspondence (:func:`rigmix.operations.mirror.
    mirror_character` swaps the sides in them, so a name stays on its side); the bone map's
    confidence only reflects where the positioning moved the dropped joints (0.97 to 1 measured
    on the Wasp), so the clip drives these joints without the blend toward rest (:func:`_clip_pose`).
    """
    kept = [set() for _ in range(J)]
    for j, (o, c) in enumerate(zip(map_y.target, map_y.confidence)):
        if 0 <= o < J and c >= KEPT_CONFIDENCE:
            kept[o].add(y.skeleton.names[j])
    out = np.zeros(J, dtype=bool)
    for i, o in enumerate(map_x.target):
        if 0 <= o < J and x.skeleton.names[i] in kept[o]:
            out[o] = True
    return out


def _clip_pose(skeleton_out, character, bone_map, clip, fps, maps=None):
    """One clip of an input resampled at ``fps`` and mapped onto S_R without the confidence blend.

    Returns
    -------
    T, R, S : (F, J, 3), (F, J, 4) xyzw, (F, J, 3) float64
        Local transforms of S_R, at the times of :func:`_sample_input` for that clip.
    """
    T, R, S = sample_clip(character.skeleton, clip, clip_times(clip, fps))
    T, R, S, _ = map_pose(skeleton_out, character.skeleton, bone_map, T, R, S, blend=False, translation_maps=maps)
    return T, R, S


def _own_clip(x, y, fy, clip_name, seg, rows):
    """Candidate columns that replay ``y``'s own clip ``clip_name`` frame by frame, or None.

    When ``y`` is the asset ``x`` is (:func:`same_asset`), the clip being completed exists for
    ``y``'s joints too: they take it as it is rather than frames scored from other clips. Other
    characters' clips of the same name are not the same motion, nor is a mirrored copy's (the
    other side's motion reflected; :func:`_same_named`).
    """
    if not same_asset(x, y) or clip_name not in fy.names:
        return None
    cols = np.flatnonzero(seg == fy.names.index(clip_name))
    n = rows.stop - rows.start
    return cols if cols.size == n else None


def _check_fixed_frames(fixed_frames, inputs):
    """Refuse a fixed frame naming a character id or a clip that the inputs do not have."""
    for ff in fixed_frames:
        for cid, clip in ((ff.character, ff.clip), (ff.source, ff.source_clip)):
            if cid not in inputs:
                raise InputError(f"completion: a fixed frame names character {cid!r}; inputs are {sorted(inputs)}")
            names = [c.name for c in inputs[cid].clips]
            if clip not in names:
                raise InputError(f"completion: {inputs[cid].label} (character {cid!r}): no clip {clip!r}, which a "
                                 f"fixed frame names; its clips: {', '.join(map(repr, names)) or 'none'}")


def _fixed_rows(fixed_frames, inputs, y, fy, seg, fps, frames):
    """Pinned frames of one completion by input ``y``: output frame -> candidate column.

    ``fixed_frames`` are those of one clip (``frames`` long at ``fps``); messages name each
    clip's file (:attr:`rigmix.character.Character.label`) and character id.
    """
    fixed = {}
    for ff in fixed_frames:
        if ff.source != y:
            continue
        query = f"completion: {inputs[ff.character].label} (character {ff.character!r}): clip {ff.clip!r}"
        if not 0 <= ff.frame < frames:
            raise InputError(f"{query}: fixed frame {ff.frame} is outside the clip ({frames} frames at {fps:g} fps)")
        cols = np.flatnonzero(seg == fy.names.index(ff.source_clip))  # named clips exist: _check_fixed_frames
        source = f"completion: {inputs[y].label} (character {y!r}): clip {ff.source_clip!r}"
        if cols.size == 0:
            raise InputError(f"{source}: a fixed frame takes frames from it, but [animation] sources leaves it out")
        if not 0 <= ff.source_frame < cols.size:
            raise InputError(f"{source}: fixed frame source_frame {ff.source_frame} is outside the clip "
                             f"({cols.size} frames at {fps:g} fps)")
        fixed[int(ff.frame)] = int(cols[ff.source_frame])
    return fixed


def _choose(fx, rows, fy, pool_rows, seg, pair, options, length, fixed):
    """Candidate column per frame of the query clip: scores, continuity, frame choice."""
    w, anchor, cand = pair
    Pa = fx.P[rows] - fx.P[rows][:, anchor:anchor + 1]  # positions relative to the merge joint
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
    return choose_frames(score, seg, jump_penalty=options.jump_penalty, fixed=fixed)


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


def _bone_direction(skeleton: Skeleton, j: int):
    """Unit rest direction from joint ``j`` to the mean of its children (world), or None."""
    kids = np.flatnonzero(np.asarray(skeleton.parents) == j)
    if not len(kids):
        return None
    P = skeleton.rest_worlds()[:, :3, 3]
    d = P[kids].mean(axis=0) - P[j]
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-12 else None


def limb_roots_to_complete(plan, max_angle=60.0):
    """Fused joints whose target rotation would misplace the new limb in the target's clips.

    A replace fuses the target's joint with the source's subtree root: the output joint keeps
    the target's place and rest rotation, its children are the source's. The target's clips
    rotate it by rest-relative deltas, which carry over only where the two rest bones point
    alike: a humanoid's T-pose arm is lowered by about 72 degrees in its walk, and the same
    delta swings a quadruped's hanging front leg, put in its place, 72 degrees out (junction
    stretch 3.4 times the sources'). Such a joint is completed from the source's frames in the
    target's clips, like the rest of the limb.

    Parameters
    ----------
    plan : rigmix.operations.Plan
    max_angle : float
        Degrees between the target's rest bone (to the mean of its children, positioned) and
        the output's; 180 disables.

    Returns
    -------
    list of (int, str)
        ``(output joint, target id)`` pairs: drop the target from the joint's provenance.
    """
    S = plan.skeleton
    parents = np.asarray(S.parents)
    out = []
    for p in plan.fused_pairs:
        kids = np.flatnonzero(parents == p.output)
        if not len(kids) or any(cid == p.target for k in kids for cid, _ in plan.provenance[k]):
            continue  # the target keeps children there (an attach): its rotation stays meaningful
        d_out = _bone_direction(S, p.output)
        d_tgt = _bone_direction(plan.positioned[p.target].skeleton, p.target_joint)
        if d_out is None or d_tgt is None:
            continue
        if np.degrees(np.arccos(np.clip(float(d_out @ d_tgt), -1.0, 1.0))) > max_angle:
            out.append((int(p.output), p.target))
    return out


def completion_provenance(plan, rest_mismatch=60.0):
    """The plan's provenance, less the targets of :func:`limb_roots_to_complete` (what
    :func:`rigmix.pipeline.completion_stage` passes to :func:`complete_clips`)."""
    provenance = [list(p) for p in plan.provenance]
    for o, target in limb_roots_to_complete(plan, rest_mismatch):
        provenance[o] = [(cid, j) for cid, j in provenance[o] if cid != target]
    return provenance


def translation_maps(plan, maps, inputs) -> dict:
    """Per input, the linear map of each joint's translation keys onto S_R.

    A translation key of input joint ``i`` is a displacement in its parent's frame (its anchor's
    for a root), in the input's units. As composed it is ``E_i`` times that in the positioned
    parent frame (``E_i``: the composed scale ``s``; for a root, the scale and placement seen
    from its anchor, as :func:`rigmix.operations.positioning.position_character` moves root
    keys). The positioned parent frame ``P_i`` carries the input's own scale (an armature's
    x100); S_R's joints are rigid (unit scale), so in the frame ``Q_o`` of the parent of the
    output joint ``o`` it maps to, the same displacement is ``Q_o^-1 P_i E_i`` (linear parts).
    For a joint copied with its parent that is ``s`` times the parent's world scale; for a
    grafted root it also turns the key from the source parent's orientation to the target's.

    Parameters
    ----------
    plan : rigmix.operations.Plan
    maps : mapping of str -> BoneMap
    inputs : mapping of str -> Character
        The inputs as loaded (the skeletons the clips are keyed on).

    Returns
    -------
    dict of str -> (J_in, 3, 3) float64
        Identity rows for unmapped joints.
    """
    S = plan.skeleton
    Q = S.root_parent_worlds()
    worlds = S.rest_worlds()
    has = S.parents >= 0
    Q[has] = worlds[S.parents[has]]
    Qinv = np.linalg.inv(Q[:, :3, :3])
    out = {}
    for cid, ch in inputs.items():
        sk = ch.skeleton
        ps = plan.positioned[cid].skeleton
        P = ps.root_parent_worlds()
        pw = ps.rest_worlds()
        inner = ps.parents >= 0
        P[inner] = pw[ps.parents[inner]]
        G = np.asarray(plan.transforms[cid], dtype=np.float64)
        E = np.broadcast_to(plan.scales[cid] * np.eye(3), (sk.num_joints, 3, 3)).copy()
        anchor = sk.root_parent_worlds()
        for r in sk.roots:
            E[r] = (np.linalg.inv(anchor[r]) @ G @ anchor[r])[:3, :3]
        target = np.asarray(maps[cid].target)
        L = np.broadcast_to(np.eye(3), (sk.num_joints, 3, 3)).copy()
        ok = target >= 0
        L[ok] = Qinv[target[ok]] @ P[ok, :3, :3] @ E[ok]
        out[cid] = L
    return out
