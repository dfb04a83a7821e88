"""Clip fidelity: how closely the output clips replay the motion of each input's own joints.

For every clip of an input X that the completion writes, the joints of S_R that X keeps (X is in
their provenance: the clip drives them, nothing completes them) must move as they move in X's
own clip, once X is scaled, placed and posed as composed. A clip written once for an asset listed
twice (a self-composition) counts for both ids: the other id's joints replay the same clip. Not
for a mirrored copy (:func:`rigmix.animation.completion.same_asset`): its joints follow the clip's
own joints that they replace, not its reflected clip of the other side.
Positions are compared relative to the joint's *fused ancestor* (the nearest ancestor-or-self
fused with another input, or whose parent is not X's), in that ancestor's frame brought back to
its rest orientation: the fused joint's parent is another input's joint, moved by another clip,
so only the motion below it is X's. Joints above every fused joint are compared in world space
(root motion included).

The reference is X's clip on X's positioned skeleton (:attr:`rigmix.operations.Plan.positioned`),
as rest-relative deltas: local rotation ``rest_pos @ rest_in^-1 @ R(t)`` (the clip itself where
no rest-pose rotation was given), translation ``rest_pos + E (T(t) - rest_in)`` with ``E`` the
composed scale (and, for a root, the placement about its anchor), scale ``rest_pos * S(t) /
rest_in``. The output side is S_R driven by the output clip. Both by matrix forward kinematics.

Output joints that X's clip drives only through a mapping of confidence < 1 (no input that owns
them has a clip to complete them: the completion's confidence blend toward rest) are not
measured; they are counted in ``blended_joints``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..transforms import polar_decomposition, quat_conjugate, quat_multiply, trs_to_matrix
from .completion import same_asset
from .sampling import clip_times, sample_clip

__all__ = ["FIDELITY_FPS", "SourceFidelity", "fused_ancestors", "reference_pose", "clip_fidelity"]

#: Frames per second at which fidelity is measured (the issue's protocol; the completion's own
#: default rate, so every output key is a measured frame).
FIDELITY_FPS = 30.0


@dataclass(frozen=True)
class SourceFidelity:
    """Fidelity of one input's clips in the output.

    Attributes
    ----------
    max : float
        Largest distance over every measured joint and frame of every clip of the input,
        divided by the output's bounding-box diagonal (0 when nothing is measured).
    clip, joint : str or None
        Where the largest distance is (output clip name, output joint name).
    frame : int
        Its frame (at :data:`FIDELITY_FPS` from the clip's start).
    measured_joints : int
        Output joints the input keeps (compared).
    blended_joints : int
        Output joints its clips drive by a confidence blend (not compared).
    """

    max: float
    clip: str | None
    joint: str | None
    frame: int
    measured_joints: int
    blended_joints: int


def fused_ancestors(parents, owned, fused):
    """Per output joint, its fused ancestor for one input (``-1``: none, compare in world space).

    Parameters
    ----------
    parents : (J,) int array
        S_R's parents.
    owned : (J,) bool array
        Joints the input keeps.
    fused : (J,) bool array
        Joints with members of several inputs in their provenance.

    Returns
    -------
    (J,) int64
        The nearest ancestor-or-self ``b`` that is fused or whose parent is not owned (for
        owned joints; ``-1`` for the others and for joints with no such ancestor).
    """
    parents = np.asarray(parents, dtype=np.int64)
    out = np.full(len(parents), -1, dtype=np.int64)
    for j, p in enumerate(parents):  # topological order: the parent is already done
        if not owned[j]:
            continue
        if fused[j] or (p >= 0 and not owned[p]):
            out[j] = j
        elif p >= 0:
            out[j] = out[p]
    return out


def reference_pose(character, positioned, clip, times, transform):
    """Local poses of X's clip on X's positioned skeleton (see the module docstring).

    Parameters
    ----------
    character : Character
        X as loaded (its skeleton's rest is what the clip is relative to).
    positioned : Character
        X as composed (same joints).
    clip : Clip
        A clip of ``character``.
    times : (F,) float array
        Seconds.
    transform : (4, 4) float array
        The composed scale and placement of X (world -> composed world).

    Returns
    -------
    T : (F, J_in, 3), R : (F, J_in, 4), S : (F, J_in, 3) float64
        Local translations, rotations (xyzw), scales of the positioned skeleton.
    """
    sk, ps = character.skeleton, positioned.skeleton
    T, R, S = sample_clip(sk, clip, times)
    G = np.asarray(transform, dtype=np.float64)
    s = float(np.cbrt(abs(np.linalg.det(G[:3, :3]))))
    E = np.broadcast_to(s * np.eye(3), (sk.num_joints, 3, 3)).copy()
    base = sk.root_parent_worlds()
    for r in sk.roots:  # a root's keys are in its anchor's frame: the placement acts there
        E[r] = (np.linalg.inv(base[r]) @ G @ base[r])[:3, :3]
    T_ref = ps.translations + np.einsum("jab,fjb->fja", E, T - sk.translations)
    R_ref = quat_multiply(quat_multiply(ps.rotations, quat_conjugate(sk.rotations)), R)
    S0 = np.where(np.abs(sk.scales) > 1e-12, sk.scales, 1.0)
    S_ref = ps.scales * S / S0
    return T_ref, R_ref, S_ref


def _relative(worlds, rest, anchor):
    """Positions ``(F, J, 3)`` relative to each joint's ``anchor`` joint, in the anchor's frame
    turned back to its rest orientation (world positions where ``anchor`` is -1)."""
    P = worlds[..., :3, 3]
    has = anchor >= 0
    a = np.where(has, anchor, 0)
    Q = polar_decomposition(worlds[:, a, :3, :3])[0]  # (F, J, 3, 3)
    Q0 = polar_decomposition(rest[a, :3, :3])[0]  # (J, 3, 3)
    d = P - P[:, a]
    local = np.einsum("fjba,fjb->fja", Q, d)  # Q^T d
    rel = np.einsum("jab,fjb->fja", Q0, local)
    return np.where(has[None, :, None], rel, P)


def clip_fidelity(skeleton, clips, keys, inputs, positioned, transforms, provenance, maps, *, diagonal,
                  fps=FIDELITY_FPS):
    """Clip fidelity of every input (see the module docstring).

    Parameters
    ----------
    skeleton : Skeleton
        S_R.
    clips : sequence of Clip
        The output clips, one per ``keys`` entry.
    keys : sequence of (str, str)
        ``(input id, clip name)`` each output clip completes
        (:func:`rigmix.animation.completion.selected_clips`).
    inputs, positioned : mapping of str -> Character
        The inputs as loaded and as composed.
    transforms : mapping of str -> (4, 4) float array
        Each input's composed scale and placement.
    provenance : sequence of sequence of (str, int)
        Per output joint, the input joints it keeps (the completion's provenance).
    maps : mapping of str -> BoneMap
    diagonal : float
        The output's bounding-box diagonal (distances are divided by it).
    fps : float

    Returns
    -------
    dict of str -> SourceFidelity
        Per input id, in ``inputs`` order (inputs without an output clip included, measuring 0).
    """
    J = skeleton.num_joints
    parents = np.asarray(skeleton.parents)
    rest_out = skeleton.rest_worlds()
    fused = np.array([len({cid for cid, _ in prov}) > 1 for prov in provenance])
    owners = [{cid for cid, _ in prov} for prov in provenance]
    has_clips = {cid: bool(ch.clips) for cid, ch in inputs.items()}
    diag = diagonal if diagonal > 0 else 1.0
    out = {}
    for cid, ch in inputs.items():
        owned = np.array([cid in ow for ow in owners])
        member = np.full(J, -1, dtype=np.int64)
        for o, prov in enumerate(provenance):
            for c, j in prov:
                if c == cid and member[o] < 0:
                    member[o] = j
        anchor = fused_ancestors(parents, owned, fused)
        target = np.asarray(maps[cid].target)
        reached = np.zeros(J, dtype=bool)
        reached[target[(target >= 0) & (target < J)]] = True
        completed = np.array([bool(ow) and any(has_clips[y] for y in ow) for ow in owners])
        blended = int(np.sum(~owned & ~completed & reached))
        best, where = 0.0, (None, None, 0)
        sel = np.flatnonzero(owned)
        if sel.size:
            ps = positioned[cid].skeleton
            rest_in = ps.rest_worlds()
            loc = _local_index(anchor[sel], sel)  # the fused ancestors, as positions in sel
            for (kc, name), clip in zip(keys, clips):
                if kc != cid and not same_asset(inputs[kc], ch):
                    continue
                src = ch.clip(name)
                t = clip_times(src, fps)
                Tr, Rr, Sr = reference_pose(ch, positioned[cid], src, t, transforms[cid])
                ref = ps.world_matrices(trs_to_matrix(Tr, Rr, Sr))
                To, Ro, So = sample_clip(skeleton, clip, t)
                got = skeleton.world_matrices(trs_to_matrix(To, Ro, So))
                v_ref = _relative(ref[:, member[sel]], rest_in[member[sel]], loc)
                v_out = _relative(got[:, sel], rest_out[sel], loc)
                err = np.linalg.norm(v_out - v_ref, axis=-1) / diag  # (F, n)
                if err.size and float(err.max()) > best:
                    f, k = np.unravel_index(int(np.argmax(err)), err.shape)
                    best, where = float(err.max()), (clip.name, skeleton.names[sel[k]], int(f))
        out[cid] = SourceFidelity(best, where[0], where[1], where[2], int(sel.size), blended)
    return out


def _local_index(anchor, sel):
    """Anchors given as joint indices, re-expressed as positions in ``sel`` (-1 kept)."""
    pos = {int(j): k for k, j in enumerate(sel)}
    return np.array([pos[int(a)] if a >= 0 else -1 for a in anchor], dtype=np.int64)
