"""Detached parts that follow their limb's tip in completed clips.

A Quaternius rig's IK foot carries the foot's skin but hangs from the armature root, not from
the leg (:attr:`rigmix.limbs.Limb.detached`); its clip keys it root-relative, where the IK solve
put it at the end of the leg. Moved with its leg to another body (a ``replace`` of the leg and
one of the foot), the leg hangs from the other body's hip while the foot keeps the donor's
root-relative motion: the distance from the lower leg to the foot swings far from its rest
length (and the foot's skin stretches with it), where in the donor's own clips it stays near it.

:func:`detached_followers` finds, per input, the top joint of each detached part of a limb that
the composition moved (the S_R path between the part and its limb tip runs through a joint the
input does not own); :func:`follow_tips` then sets, in each completed clip, the part's world
transform to the limb tip's times the part's offset to it: S_R's rest offset, moved as the part
moves about its rest offset in the input's own clip at the same frame when the clip playing is
the input's own (a rest-relative delta in the part's frame, as :func:`rigmix.animation.keyframes.
map_pose` carries local rotations), else the rest offset alone. Where the part, the limb and the
joints between them all come from the clip's asset or its mirrored copy (a self-composition),
the clip drives them with one motion already: nothing changes there
(:func:`rigmix.animation.completion._follow`).

Conventions (:mod:`rigmix.character`): 4x4 matrices act on column vectors (``p' = M @ p``), world
matrices include the roots' anchors; local transforms are a joint's in its parent's frame;
quaternions xyzw.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..character import Character, Skeleton
from ..transforms import matrix_to_trs, trs_to_matrix

__all__ = ["Follower", "detached_followers", "follow_tips", "source_offsets"]


@dataclass(frozen=True)
class Follower:
    """A detached part's top joint that follows a limb tip of S_R.

    Attributes
    ----------
    source : str
        Id of the input whose limb and part they are.
    joint, tip : int
        Output joints: the part's top, and the limb joint it follows.
    source_joint, source_tip : int
        The same joints in the input's skeleton.
    rest_offset : (4, 4) float64
        ``O_rest = W_in[source_tip]^-1 @ W_in[source_joint]``: the part's rest offset to the tip
        in the input (rest world matrices ``W_in``).
    between : tuple of str
        Ids of the inputs owning the S_R joints between the part and the tip (up to, not
        including, their common ancestor): whose clips move one relative to the other.
    joint_map : (4, 4) float64
        ``B``: the linear part of ``(G @ W_in[source_joint])^-1 @ W_out[joint]`` (``G``: the
        input's placement, :attr:`rigmix.operations.Plan.transforms`; ``W_out``: S_R's rest world
        matrices), no translation: the part's local frame in S_R expressed in the input's (its
        orientation and scale; the limb and the part are placed apart, so positions do not carry).
        A part at offset ``O = O_rest @ D`` to its tip in the input (``D``: its motion in its own
        rest frame) is at ``O_rest_out @ B^-1 @ D @ B`` in S_R, ``O_rest_out`` S_R's rest offset.
    """

    source: str
    joint: int
    tip: int
    source_joint: int
    source_tip: int
    rest_offset: np.ndarray
    joint_map: np.ndarray
    between: tuple[str, ...] = ()


def _tip_of(P, limb_joints: Sequence[int], top: int) -> int:
    """The limb joint nearest the part's top joint at rest (``P`` ``(J, 3)``: rest world
    positions): the tip it hangs at (an IK foot's top joint sits at the ankle, the lower leg's end)."""
    d = np.linalg.norm(P[list(limb_joints)] - P[top], axis=1)
    return int(limb_joints[int(np.argmin(d))])


def _ancestors(parents, j) -> list[int]:
    out = []
    while j >= 0:
        out.append(int(j))
        j = int(parents[j])
    return out


def detached_followers(skeleton_out: Skeleton, inputs: Mapping[str, Character], maps: Mapping,
                       provenance: Sequence[Sequence[tuple[str, int]]],
                       transforms: Mapping[str, np.ndarray]) -> tuple[Follower, ...]:
    """The detached parts that the composition took away from their limb's chain.

    Parameters
    ----------
    skeleton_out : Skeleton
        S_R.
    inputs : mapping of str to Character
        The inputs as loaded (their clips are keyed on these skeletons).
    maps : mapping of str to BoneMap
        ``target (J_in,)``: output joint per input joint, or -1.
    provenance : sequence of sequence of (str, int)
        Per output joint, the (character id, input joint) it comes from.
    transforms : mapping of str to (4, 4) float array
        Per id, the placement of the input (column vectors).

    Returns
    -------
    tuple of Follower
        One per detached top joint (a part's joint whose parent is not in the part) that S_R
        keeps from its input along with its limb's tip, where the S_R path from the lower of the
        two up to their common ancestor passes a joint the input does not own (a limb moved to
        another body or grafted); a part still hanging where it hung follows its own clip.
    """
    from ..limbs import classify_limbs

    parents = np.asarray(skeleton_out.parents)
    owned = [set(cid for cid, _ in prov) for prov in provenance]
    W_out = skeleton_out.rest_worlds()
    out = []
    for cid, ch in inputs.items():
        sk = ch.skeleton
        target = np.asarray(maps[cid].target)
        limbs = [lb for lb in classify_limbs(ch).limbs if lb.detached]
        if not limbs:
            continue
        G = np.asarray(transforms[cid], dtype=np.float64)
        W_in = sk.rest_worlds()
        for lb in limbs:
            part = set(lb.detached)
            chain = [sk.names.index(n) for n in lb.joints]
            for name in lb.detached:
                j = sk.names.index(name)
                if sk.parents[j] >= 0 and sk.names[sk.parents[j]] in part:
                    continue
                t = _tip_of(W_in[:, :3, 3], chain, j)
                o, ot = int(target[j]), int(target[t])
                if o < 0 or ot < 0 or cid not in owned[o] or cid not in owned[ot]:
                    continue
                up_o, up_t = _ancestors(parents, o), _ancestors(parents, ot)
                if o in up_t or ot in up_o:
                    continue  # one hangs from the other in S_R: forward kinematics carries it
                common = set(up_o) & set(up_t)
                path = [k for k in up_o + up_t if k not in common]
                if all(cid in owned[k] for k in path):
                    continue  # still hangs as it hung in its input
                B = np.linalg.solve(G @ W_in[j], W_out[o])
                B[:3, 3] = 0.0
                between = tuple(sorted({y for k in path for y in owned[k]}))
                out.append(Follower(cid, o, ot, j, t, np.linalg.solve(W_in[t], W_in[j]), B, between))
    return tuple(out)


def follow_tips(skeleton_out: Skeleton, T, R, S, followers: Sequence[Follower],
                offsets: Sequence[np.ndarray | None]):
    """Local transforms of S_R with each follower's joint placed at its offset from its tip.

    Parameters
    ----------
    skeleton_out : Skeleton
        S_R, ``J`` joints.
    T, R, S : (F, J, 3), (F, J, 4) xyzw, (F, J, 3) float arrays
        Local transforms of one clip on S_R (not modified).
    followers : sequence of Follower
    offsets : sequence of (F, 4, 4) float array or None
        Per follower, the input's offset ``O_in`` of the part to the tip per frame (column
        vectors, the input's own frames), or None: S_R's rest offset.

    Returns
    -------
    T, R, S : new arrays
        Only the followers' joints change: world ``W[tip] @ O_rest_out @ B^-1 @ D @ B`` with
        ``D = rest_offset^-1 @ O_in`` (:class:`Follower`; without ``O_in``, ``D = I``: ``W[tip] @
        O_rest_out``, ``O_rest_out = W_rest[tip]^-1 @ W_rest[joint]`` of S_R), as a local transform
        of their parents' frames; the joints below them keep their local transforms and follow.
    """
    T, R, S = T.copy(), R.copy(), S.copy()
    if not followers:
        return T, R, S
    rest = skeleton_out.rest_worlds()
    base = skeleton_out.root_parent_worlds()
    parents = skeleton_out.parents
    # one follower at a time, parents first: a part's placement may move a later tip
    for f, off in sorted(zip(followers, offsets), key=lambda x: x[0].joint):
        W = skeleton_out.world_matrices(trs_to_matrix(T, R, S))  # (F, J, 4, 4)
        rel = np.linalg.solve(rest[f.tip], rest[f.joint])[None]
        if off is not None:
            rel = rel @ np.linalg.solve(f.joint_map, np.linalg.solve(f.rest_offset, off)) @ f.joint_map
        world = W[:, f.tip] @ rel
        p = parents[f.joint]
        local = np.linalg.solve(W[:, p] if p >= 0 else base[f.joint][None], world)
        T[:, f.joint], R[:, f.joint], S[:, f.joint] = matrix_to_trs(local)
    return T, R, S


def source_offsets(character: Character, clip_name: str, times, followers: Sequence[Follower]) -> list:
    """Per follower (all of ``character``), ``O_in = W[tip]^-1 @ W[joint]`` in the character's
    own clip ``clip_name`` sampled at ``times`` (seconds): ``(F, 4, 4)`` float64 arrays."""
    from .sampling import sample_clip

    sk = character.skeleton
    Tl, Rl, Sl = sample_clip(sk, character.clip(clip_name), times)
    W = sk.world_matrices(trs_to_matrix(Tl, Rl, Sl))
    return [np.linalg.solve(W[:, f.source_tip], W[:, f.source_joint]) for f in followers]
