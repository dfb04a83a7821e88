"""Operations: the actions of a config -> the output skeleton S_R with provenance, and the
characters moved into place (PIPELINE.md section 1; SkinMixer sec. 4).

Semantics, once:

* ``attach`` (X.a onto Y.b): joint ``a`` of X and joint ``b`` of Y are *fused* into one output
  joint; X contributes the subtree at ``a``, Y keeps everything. With ``keep_joint``, ``a`` is not
  fused: it stays a joint of its own, a child of ``b`` (an *attached* pair), with its bone and its
  motion.
* ``replace`` (X.a replaces Y.b): the same fusion, and Y's descendants of ``b`` are dropped.
  Replacing a joint by itself (same character, same joint) is the identity.
* ``remove`` (Y.b): Y's subtree at ``b``, ``b`` included, is dropped.

A character that is the source of no action (or the target of an action at a joint outside the
subtrees it gives) is a *body*: all its joints are candidates. A character that is only a source
gives just the subtrees at its source joints. Every input joint may appear at most once in the
output: to use a part twice, list the file under two ids.

The fused joint takes the target's name, rest transform and parent. Output joints are ordered
parents first; among the valid orders the one kept follows the body's own joint order, with a
grafted subtree placed where the joint it is fused with sits (a self-composition therefore
reproduces the input order exactly). Name collisions (:func:`output_joint_names`): a body's
joints keep their names, a grafted joint that collides is prefixed with its character id
(``rider_Chest``), numbered ``_2``, ``_3``... only if that is taken too.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..character import Anchor, Skeleton
from ..config import Config, closest_names
from ..errors import InputError
from ..rig import topological_order, unique_names
from ..transforms import matrix_to_trs, unit_scale
from .positioning import position_inputs

__all__ = ["FusedPair", "Plan", "ResolvedAction", "merged_sources", "plan_operations", "resolve_actions",
           "resolve_rotations"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ResolvedAction:
    """One action of the config with joint names resolved to indices.

    Attributes
    ----------
    index : int
        Position in ``config.actions``.
    op : {"attach", "replace", "remove"}
    target : str
        Character id receiving the action.
    target_joint : int
    source : str or None
        Character id giving a subtree (``None`` for ``remove``).
    source_joint : int
        ``-1`` for ``remove``.
    mode : {"blend", "union"} or None
        Surface operator of a ``replace`` (``"union"`` for ``attach``, ``None`` for ``remove``).
    fuse : bool
        Whether the two joints become one (False for an ``attach`` with ``keep_joint``: the source
        joint becomes a child of the target joint).
    """

    index: int
    op: str
    target: str
    target_joint: int
    source: str | None = None
    source_joint: int = -1
    mode: str | None = None
    fuse: bool = True

    @property
    def grafts(self) -> bool:
        """True for attach and replace (actions that graft a subtree)."""
        return self.op in ("attach", "replace")

    @property
    def fuses(self) -> bool:
        """True for the grafts that fuse their two joints into one."""
        return self.grafts and self.fuse

    @property
    def identity(self) -> bool:
        """A joint replaced by itself (same character, same joint): changes nothing."""
        return self.op == "replace" and self.source == self.target and self.source_joint == self.target_joint


@dataclass(frozen=True)
class FusedPair:
    """Two input joints where two parts meet: fused into one output joint, or attached (the
    source joint a child of the target joint, :attr:`ResolvedAction.fuse` False).

    Attributes
    ----------
    output : int
        The output joint (the fused one; the source joint's for an attached pair).
    target, source : str
        Character ids (the target stays in place, the source is moved onto it).
    target_joint, source_joint : int
        Input joint indices.
    action : int
        Index of the action in the config.
    """

    output: int
    target: str
    target_joint: int
    source: str
    source_joint: int
    action: int


@dataclass(frozen=True)
class Plan:
    """The output skeleton and everything later stages need to know about its origin.

    Attributes
    ----------
    skeleton : Skeleton
        S_R: unique names, parents before children, bind pose = rest pose
        (``inverse_binds`` are the inverses of its rest world matrices).
    provenance : tuple of tuple of (str, int), (J_R,)
        For each output joint, the input joints it copies (one) or fuses (several): character id
        and joint index; the first is the one whose name and rest transform it takes.
    used : dict of str -> (J_in,) bool array
        Joints of each input that survive in S_R.
    image : dict of str -> (J_in,) int64 array
        The output joint of each surviving input joint, ``-1`` for the others.
    fused_pairs : tuple of FusedPair
        Joints fused into one.
    actions : tuple of ResolvedAction
    positioned : dict of str -> Character
        Each input after scale, placement, rest-pose rotations and preliminary translation,
        rebased (mesh in world space at rest, bind = rest). Later stages start from these.
    scales : dict of str -> float
    transforms : dict of str -> (4, 4) float64 array
        The scale and rigid placement given to each input (input world -> composed world,
        ``placement @ diag(s, s, s, 1)``), before rest-pose rotations and translations.
    translations : dict of str -> (J_in, 3) float64 array
        The preliminary per-joint translations (world space, after scaling).
    report : dict
        JSON-ready summary: scales and how they were chosen, fused and attached pairs, renamed
        joints.
    attached_pairs : tuple of FusedPair
        Source joints of ``keep_joint`` attaches, each a child of its target joint (``output``:
        the source joint's output joint).
    """

    skeleton: Skeleton
    provenance: tuple
    used: dict
    image: dict
    fused_pairs: tuple
    actions: tuple
    positioned: dict
    scales: dict
    transforms: dict
    translations: dict
    report: dict = field(default_factory=dict)
    attached_pairs: tuple = ()

    @property
    def junction_pairs(self) -> tuple:
        """Every pair of joints where two parts meet: :attr:`fused_pairs`, then
        :attr:`attached_pairs` (a source joint kept as a child of its target joint)."""
        return self.fused_pairs + self.attached_pairs

    def output_index(self, cid: str, joint: int) -> int:
        """Output joint of input joint ``joint`` of character ``cid`` (``-1`` if dropped)."""
        return int(self.image[cid][joint])


# --------------------------------------------------------------------------------------------
# Resolving names
# --------------------------------------------------------------------------------------------


def _where(config: Config, cid: str, inputs) -> str:
    """A character in messages: its id and its file's name (never the folders it lives in)."""
    src = inputs[cid].label if inputs[cid].source else Path(config.characters[cid].path).name
    return f"{cid!r} ({src})"


def _joint(inputs, config, cid, name, key) -> int:
    names = inputs[cid].skeleton.names
    if name in names:
        return names.index(name)
    close = closest_names(name, names)
    hint = f"; closest: {', '.join(close)}" if close else f"; joints: {', '.join(names[:12])}..."
    raise InputError(f"config {config.source}: {key}: no joint {name!r} in character "
                     f"{_where(config, cid, inputs)}{hint}")


def resolve_actions(inputs, config: Config) -> tuple[ResolvedAction, ...]:
    """Resolve joint names and check each action on its own.

    Parameters
    ----------
    inputs : dict of str -> Character
        Loaded characters, by config id.
    config : Config

    Returns
    -------
    tuple of ResolvedAction

    Raises
    ------
    InputError
        An unknown joint (listing the closest names), or a subtree grafted onto itself.
    """
    out = []
    for i, a in enumerate(config.actions):
        tj = _joint(inputs, config, a.target, a.target_joint, f"actions[{i}].target_joint")
        if a.op == "remove":
            out.append(ResolvedAction(i, "remove", a.target, tj))
            continue
        sj = _joint(inputs, config, a.source, a.source_joint, f"actions[{i}].source_joint")
        mode = a.mode if a.op == "replace" else "union"
        r = ResolvedAction(i, a.op, a.target, tj, a.source, sj, mode, fuse=not getattr(a, "keep_joint", False))
        if a.source == a.target and not r.identity:
            sub = inputs[a.source].skeleton.subtree(sj)
            if sub[tj]:
                raise InputError(
                    f"config {config.source}: actions[{i}]: cannot {a.op} the subtree at "
                    f"{a.source_joint!r} onto {a.target_joint!r} of the same character {a.source!r}: "
                    f"the target is inside the subtree (a subtree cannot be grafted onto itself)")
        out.append(r)
    _check_one_replacement(out, inputs, config)
    return tuple(out)


def _check_one_replacement(actions, inputs, config: Config) -> None:
    """A target joint is replaced or removed by one action at most: two replacements of one
    shoulder would fuse three arms into one joint, and a replaced joint that is also removed
    has no meaning (``InputError`` naming both actions)."""
    seen = {}
    for a in actions:
        if a.identity:
            continue
        key = (a.target, a.target_joint)
        if key in seen and (a.op != "attach" or seen[key].op != "attach"):
            b = seen[key]
            name = inputs[a.target].skeleton.names[a.target_joint]
            raise InputError(
                f"config {config.source}: actions[{b.index}] ({b.op}) and actions[{a.index}] ({a.op}) both act on "
                f"joint {name!r} of {a.target!r}: a joint can be replaced or removed by one action only; "
                f"keep one of them (or attach the other part to another joint)")
        if key not in seen or a.op != "attach":
            seen[key] = a


def resolve_rotations(inputs, config: Config) -> dict:
    """The config's rest-pose rotations by joint index: ``{cid: {joint: (4,) quaternion xyzw}}``."""
    out = {}
    for cid, cc in config.characters.items():
        out[cid] = {_joint(inputs, config, cid, name, f"characters.{cid}.rotations"):
                    np.asarray(rot.as_quaternion(), dtype=np.float64) for name, rot in cc.rotations.items()}
    return out


# --------------------------------------------------------------------------------------------
# The output skeleton's structure (no geometry)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Structure:
    used: dict        # cid -> (J,) bool
    part: dict        # cid -> (J,) int: -1 body, k: given by action k, -2 unused
    members: tuple    # per node: tuple of (cid, j), primary first
    parent: np.ndarray  # per node: parent node or -1
    order: np.ndarray   # output index -> node
    body: dict        # cid -> bool
    level: np.ndarray   # per node: 0 in a body, 1 grafted, 2 grafted onto a graft...


def _structure(inputs, actions, config: Config) -> _Structure:
    """The output skeleton's structure: the input joints used, fused into nodes, in output order.

    The steps, in order: which characters are bodies and which subtrees each action gives
    (:func:`_bodies_and_parts`); the targets checked to be in the output
    (:func:`_check_targets`); the removals applied (:func:`_apply_removals`); the joints used,
    each once (:func:`_used_joints`); fused joints merged into nodes (:func:`_nodes`), without a
    cycle (:func:`_check_cycles`); the nodes ordered parents first (:func:`_order`).
    """
    ids = list(config.characters)
    sk = {cid: inputs[cid].skeleton for cid in ids}
    grafts = [a for a in actions if a.grafts and not a.identity]
    gives = {cid: [a for a in grafts if a.source == cid] for cid in ids}
    body, base, parts = _bodies_and_parts(ids, sk, actions, grafts, gives)
    _check_targets(actions, sk, gives, base, parts, config)
    base, parts = _apply_removals(actions, sk, gives, base, parts)
    used, part = _used_joints(ids, sk, actions, gives, base, parts, config)
    members, node_id, parent = _nodes(ids, sk, grafts, used, config)
    _check_cycles(parent, members, sk, config)
    order, level = _order(ids, actions, members, node_id, parent, part)
    return _Structure(used, part, tuple(members), parent, order, body, level)


def _bodies_and_parts(ids, sk, actions, grafts, gives):
    """Bodies and the parts each action gives, before removals.

    A character is a body when it gives no subtree, or when an action targets one of its joints
    outside the subtrees it gives.

    Returns
    -------
    body : dict of str -> bool
    base : dict of str -> (J,) bool
        Per character, its joints in the output as a body (all of a body's, none otherwise).
    parts : dict of int -> (J,) bool
        Per grafting action (by index), the subtree of its source that it gives.
    """
    given = {a.index: sk[a.source].subtree(a.source_joint) for a in grafts}

    def inside_given(cid, j):
        return any(given[a.index][j] for a in gives[cid])

    body = {}
    for cid in ids:
        targeted_outside = any(a.grafts and a.target == cid and not inside_given(cid, a.target_joint)
                               for a in actions)
        body[cid] = not gives[cid] or targeted_outside
    base = {cid: np.full(sk[cid].num_joints, body[cid]) for cid in ids}
    parts = {a.index: given[a.index].copy() for a in grafts}
    return body, base, parts


def _check_targets(actions, sk, gives, base, parts, config):
    """A target joint must exist in the output before the removals are applied: in its
    character's body or in a subtree that character gives (``InputError`` otherwise)."""

    def available(cid):
        m = base[cid].copy()
        for a in gives[cid]:
            m |= parts[a.index]
        return m

    for a in actions:
        if a.identity:
            continue
        if not available(a.target)[a.target_joint]:
            raise InputError(
                f"config {config.source}: actions[{a.index}].target_joint: joint "
                f"{sk[a.target].names[a.target_joint]!r} of {a.target!r} is not in the output: "
                f"{a.target!r} only gives the subtree(s) at "
                f"{', '.join(repr(sk[a.target].names[g.source_joint]) for g in gives[a.target])}")


def _apply_removals(actions, sk, gives, base, parts):
    """``base`` and ``parts`` without the joints that ``replace`` (below the target) and
    ``remove`` (the target's subtree) drop; new dicts of new arrays."""
    base = {cid: m.copy() for cid, m in base.items()}
    parts = {k: m.copy() for k, m in parts.items()}
    for a in actions:
        if a.op == "replace" and not a.identity:
            rm = sk[a.target].subtree(a.target_joint)
            rm[a.target_joint] = False
        elif a.op == "remove":
            rm = sk[a.target].subtree(a.target_joint)
        else:
            continue
        base[a.target] &= ~rm
        for g in gives[a.target]:
            if g.index != a.index:
                parts[g.index] &= ~rm
    return base, parts


def _used_joints(ids, sk, actions, gives, base, parts, config):
    """The joints of each character in the output, each at most once.

    Returns
    -------
    used : dict of str -> (J,) bool
    part : dict of str -> (J,) int
        ``-1`` in the body, ``k`` given by action ``k``, ``-2`` unused.

    Raises
    ------
    InputError
        A joint would appear twice, or an action's joint is removed by another action.
    """
    used, part = {}, {}
    for cid in ids:
        count = base[cid].astype(int)
        p = np.where(base[cid], -1, -2)
        for g in gives[cid]:
            twice = np.flatnonzero(parts[g.index] & (count > 0))
            if len(twice):
                j = twice[0]
                first = "the body" if base[cid][j] else "another action's subtree"
                raise InputError(
                    f"config {config.source}: actions[{g.index}]: joint {sk[cid].names[j]!r} of "
                    f"{cid!r} would appear twice in the output (in {first} and in the subtree at "
                    f"{sk[cid].names[g.source_joint]!r}); to use a part of a character twice, list its "
                    "file again under a second id")
            count += parts[g.index]
            p = np.where(parts[g.index], g.index, p)
        used[cid] = count > 0
        part[cid] = p
    for a in actions:
        if a.op == "remove":
            continue  # its own target is gone on purpose; availability was checked above
        for cid, j, key in ((a.target, a.target_joint, "target_joint"), (a.source, a.source_joint, "source_joint")):
            if cid is not None and not used[cid][j]:
                raise InputError(
                    f"config {config.source}: actions[{a.index}].{key}: joint {sk[cid].names[j]!r} of "
                    f"{cid!r} is removed by another action")
    return used, part


def _nodes(ids, sk, grafts, used, config):
    """Output nodes: the used joints, each fused pair merged into one (union-find).

    Returns
    -------
    members : list of tuple of (str, int)
        Per node, its ``(cid, joint)``: the one that keeps its parent first, then the fused
        ones in character order.
    node_id : dict of (str, int) -> int
    parent : (N,) int64
        Parent node, ``-1`` for a root.

    Raises
    ------
    InputError
        Joints fused that each keep their parent, or fused only onto each other.
    """
    rank = {cid: i for i, cid in enumerate(ids)}
    keys = [(cid, int(j)) for cid in ids for j in np.flatnonzero(used[cid])]
    node_of = {m: i for i, m in enumerate(keys)}
    uf = list(range(len(keys)))

    def find(x):
        while uf[x] != x:
            uf[x] = uf[uf[x]]
            x = uf[x]
        return x

    for a in grafts:
        if a.fuse:
            ra, rb = find(node_of[(a.source, a.source_joint)]), find(node_of[(a.target, a.target_joint)])
            uf[ra] = rb
    groups: dict[int, list] = {}
    for i, m in enumerate(keys):
        groups.setdefault(find(i), []).append(m)
    cut = {(a.source, a.source_joint) for a in grafts if a.fuse}
    members, node_id = [], {}
    for root in sorted(groups):
        ms = groups[root]
        uncut = [m for m in ms if m not in cut]
        if len(uncut) > 1:
            names = ", ".join(f"{c}:{sk[c].names[j]}" for c, j in uncut)
            raise InputError(f"config {config.source}: actions fuse joints that each keep their parent "
                             f"({names}): a joint can be fused with one target only")
        if not uncut:
            names = ", ".join(f"{c}:{sk[c].names[j]}" for c, j in ms)
            raise InputError(f"config {config.source}: the actions create a cycle: joints {names} are "
                             "only ever moved onto each other (every character is a source; one must stay)")
        primary = uncut[0]
        ordered = [primary] + sorted((m for m in ms if m != primary), key=lambda m: (rank[m[0]], m[1]))
        for m in ordered:
            node_id[m] = len(members)
        members.append(tuple(ordered))
    parent = np.full(len(members), -1, dtype=np.int64)
    for n, ms in enumerate(members):
        cid, j = ms[0]
        p = sk[cid].parents[j]
        if p >= 0 and used[cid][p]:
            parent[n] = node_id[(cid, int(p))]
    for a in grafts:  # a kept joint hangs from its target joint
        if not a.fuse:
            parent[node_id[(a.source, a.source_joint)]] = node_id[(a.target, a.target_joint)]
    return members, node_id, parent


def _check_cycles(parent, members, sk, config):
    """Every walk up the nodes' parents must end at a root (``InputError`` naming the cycle:
    a subtree grafted below itself)."""
    N = len(parent)
    state = np.zeros(N, dtype=np.int8)  # 0 new, 1 on the current walk, 2 done
    for n in range(N):
        path = []
        x = n
        while x >= 0 and state[x] == 0:
            state[x] = 1
            path.append(x)
            x = parent[x]
        if x >= 0 and state[x] == 1:
            cyc = []
            y = x
            while True:
                cyc.append(members[y][0])
                y = parent[y]
                if y == x:
                    break
            names = " -> ".join(f"{c}:{sk[c].names[j]}" for c, j in cyc)
            raise InputError(f"config {config.source}: the actions create a cycle in the output "
                             f"skeleton ({names} -> ...): a subtree is grafted below itself")
        for y in path:
            state[y] = 2


def _order(ids, actions, members, node_id, parent, part):
    """Output order of the nodes: parents first; preference keys keep a body's own order, and
    place grafts where they are fused.

    A body joint's key is ``(character rank, joint index, 0)``; a grafted joint takes the key of
    the joint its subtree's root is fused with (or, for a kept joint, hangs from), offset by its
    index from that root, and one level more (:func:`rigmix.rig.topological_order` picks the
    smallest ready key).

    Returns
    -------
    order : (N,) int64
        Output index -> node.
    level : (N,) int64
        Per node: 0 in a body, 1 grafted, 2 grafted onto a graft...
    """
    rank = {cid: i for i, cid in enumerate(ids)}
    key_cache: dict[int, tuple] = {}

    def key(n):
        if n in key_cache:
            return key_cache[n]
        cid, j = members[n][0]
        k = part[cid][j]
        if k == -1:
            out = (rank[cid], float(j), 0)
        else:
            a = actions[k]
            kb = key(node_id[(a.source, a.source_joint)] if a.fuse else node_id[(a.target, a.target_joint)])
            out = (kb[0], kb[1] + (j - a.source_joint), kb[2] + 1)
        key_cache[n] = out
        return out

    N = len(members)
    order = topological_order(range(N), lambda n: int(parent[n]), key)
    assert len(order) == N, "every node is reachable from a root once cycles are excluded"
    level = np.array([key(n)[2] for n in range(N)], dtype=np.int64)
    return np.asarray(order, dtype=np.int64), level


# --------------------------------------------------------------------------------------------
# The output skeleton
# --------------------------------------------------------------------------------------------


def output_joint_names(names, owners, level) -> list[str]:
    """Unique output joint names: a joint whose name is taken by one of higher priority (lower
    ``level``: the body's joints first, then each graft) is prefixed with its character id
    (``rider_Chest``), then numbered ``_2``, ``_3``... should that be taken too.

    Parameters
    ----------
    names : sequence of str
        The joints' names in their own files, in output order.
    owners : sequence of str
        The config id of the character each joint comes from.
    level : sequence of int
        Priority: smaller keeps its name first (ties in list order).
    """
    first = unique_names(names, priority=level)
    prefixed = [n if u == n else f"{cid}_{n}" for n, u, cid in zip(names, first, owners)]
    return unique_names(prefixed, suffix="_{}", start=2, priority=level)


#: A rest world matrix whose linear part ``L`` has ``|L^T L - I| <= UNIT_TOLERANCE`` (every entry) is
#: rigid already: its scale is 1 within about half that (float32 files store scales of 1 +- 4e-7).
UNIT_TOLERANCE = 2e-6


def rigid(M, tol=UNIT_TOLERANCE):
    """``(...,)`` bool: whether affine matrices ``(..., 4, 4)`` have a rotation as linear part
    (within ``tol``, see :data:`UNIT_TOLERANCE`)."""
    L = np.asarray(M, dtype=np.float64)[..., :3, :3]
    G = np.swapaxes(L, -1, -2) @ L - np.eye(3)
    return np.all(np.abs(G) <= tol, axis=(-2, -1)) & (np.linalg.det(L) > 0)


def _unit_anchors(anchors):
    """Anchors whose world matrices are rigid: a scaled anchor (the Quaternius armatures' x100)
    keeps its rotation and position, its scale goes into the joints below (baked by
    :func:`_build_skeleton`).

    Returns
    -------
    anchors : tuple of Anchor
    worlds : (A, 4, 4) float64
        Their world matrices.
    changed : (A,) bool
        Anchors whose world matrix changed.
    """
    if not anchors:
        return (), np.zeros((0, 4, 4)), np.zeros(0, dtype=bool)
    aw = np.zeros((len(anchors), 4, 4))
    for i, a in enumerate(anchors):  # parents first
        aw[i] = a.matrix if a.parent < 0 else aw[a.parent] @ a.matrix
    changed = ~rigid(aw)
    U = aw.copy()
    U[changed] = unit_scale(aw[changed])
    out = []
    for a, (i, anchor) in zip(U, enumerate(anchors)):
        if changed[i] or (anchor.parent >= 0 and changed[anchor.parent]):
            P = U[anchor.parent] if anchor.parent >= 0 else np.eye(4)
            anchor = Anchor(anchor.name, np.linalg.inv(P) @ a, anchor.parent)
        out.append(anchor)
    changed = changed | np.array([a.parent >= 0 and changed[a.parent] for a in anchors])
    return tuple(out), U, changed


def _build_skeleton(structure, positioned, config, at_source=frozenset()):
    """S_R from the positioned inputs: names made unique, rest locals, unit-scale frames.

    Every joint keeps its input's rest world position and orientation (a fused joint its
    primary member's, the target's; one fused with a member of ``at_source``, a set of
    ``(cid, joint)``, that member's: a detached part moved with its limb,
    :func:`rigmix.operations.positioning.limb_followers`); a world matrix with a
    scale (an armature scale, a composed ``scale``, a graft under a differently scaled parent)
    becomes rigid (:func:`rigmix.transforms.unit_scale`), and the locals of the joints concerned
    are recomputed, with scale exactly 1. The scale is then in the joints' rest translations
    (metres of the composed world) and, since bind = rest on the positioned meshes, in nothing
    else: the mesh is in world space and the inverse bind matrices invert the rigid frames.
    Blender's bones cannot hold a rest scale; a skeleton mixing world scales of 1 and 100
    imports with mesh parts scaled apart. Joints and anchors rigid already (within
    :data:`UNIT_TOLERANCE`) keep their input locals exactly.
    """
    order = structure.order
    N = len(order)
    out_of_node = np.empty(N, dtype=np.int64)
    out_of_node[order] = np.arange(N)
    worlds_in = {cid: c.skeleton.rest_worlds() for cid, c in positioned.items()}
    parents = np.where(structure.parent[order] >= 0, out_of_node[np.maximum(structure.parent[order], 0)], -1)
    names, worlds = [], np.zeros((N, 4, 4))
    T, R, S = np.zeros((N, 3)), np.zeros((N, 4)), np.zeros((N, 3))
    anchors, anchor_offset = [], {}
    root_anchor = np.full(N, -1, dtype=np.int64)
    computed = np.zeros(N, dtype=bool)
    for o, n in enumerate(order):
        cid, j = structure.members[n][0]
        sk = positioned[cid].skeleton
        names.append(sk.names[j])
        worlds[o] = worlds_in[cid][j]
        for m in structure.members[n][1:]:
            if m in at_source and not np.array_equal(worlds_in[m[0]][m[1]], worlds[o]):
                worlds[o] = worlds_in[m[0]][m[1]]  # where the part's skin is, with its limb
                computed[o] = True
        T[o], R[o], S[o] = sk.translations[j], sk.rotations[j], sk.scales[j]
        if parents[o] < 0:
            if sk.parents[j] >= 0:
                computed[o] = True  # a root here but not in its file: local = world
            elif sk.root_anchor[j] >= 0:
                if cid not in anchor_offset:
                    anchor_offset[cid] = len(anchors)
                    anchors.extend(Anchor(a.name, a.matrix, a.parent + anchor_offset[cid] if a.parent >= 0 else -1)
                                   for a in sk.anchors)
                root_anchor[o] = anchor_offset[cid] + sk.root_anchor[j]
        else:
            pcid, pj = structure.members[structure.parent[n]][0]
            if pcid != cid or sk.parents[j] != pj:
                computed[o] = True  # a grafted joint: its local is relative to a new parent
    anchors, anchor_worlds, anchor_changed = _unit_anchors(tuple(anchors))
    scaled = ~rigid(worlds)
    U = worlds.copy()
    U[scaled] = unit_scale(worlds[scaled])
    has_anchor = root_anchor >= 0
    P = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()  # each joint's parent frame (unit)
    P[parents >= 0] = U[parents[parents >= 0]]
    P[has_anchor] = anchor_worlds[root_anchor[has_anchor]]
    rebuilt = scaled.copy()  # new frames on both sides: rigid locals, scale exactly 1
    rebuilt[parents >= 0] |= scaled[parents[parents >= 0]]
    rebuilt[has_anchor] |= anchor_changed[root_anchor[has_anchor]]
    redo = np.flatnonzero(computed | rebuilt)
    if redo.size:
        t, r, s = matrix_to_trs(np.linalg.inv(P[redo]) @ U[redo])
        T[redo], R[redo], S[redo] = t, r, np.where(rebuilt[redo, None], 1.0, s)
    level = [structure.level[n] for n in order]
    unique = output_joint_names(names, [structure.members[n][0][0] for n in order], level)
    # in the order the names were made unique: a body's joints first (level 0), then grafts
    renamed = {unique[o]: names[o] for o in sorted(range(N), key=lambda o: (level[o], o)) if unique[o] != names[o]}
    skeleton = Skeleton(
        names=tuple(unique), parents=parents, translations=T, rotations=R, scales=S,
        inverse_binds=np.linalg.inv(U), anchors=anchors, root_anchor=root_anchor,
    )
    # bind = rest exactly for the skeleton as stored (TRS cannot hold the ~1e-7 shear of float32
    # input matrices, so the stored locals' forward kinematics is the reference)
    skeleton = replace(skeleton, inverse_binds=np.linalg.inv(skeleton.rest_worlds()))
    return skeleton, out_of_node, renamed


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def merged_sources(actions) -> dict:
    """Joints of one source fused to the same target joint by several actions (two wings attached
    at one chest joint): fused pairs become one output joint, so those joints become one and move
    as one (each part's own bone, and its motion in its clips, is lost).

    Returns
    -------
    dict of (source, target, target_joint) -> list of (action index, source joint)
        Only the groups of two or more.
    """
    groups: dict = {}
    for a in actions:
        if a.fuses and a.source != a.target:
            groups.setdefault((a.source, a.target, a.target_joint), []).append((a.index, a.source_joint))
    return {k: v for k, v in groups.items() if len({j for _, j in v}) > 1}


def _warn_merged_sources(actions, inputs, config) -> None:
    for (src, tgt, tj), members in merged_sources(actions).items():
        names = ", ".join(f"actions[{i}] '{inputs[src].skeleton.names[j]}'" for i, j in members)
        logger.warning("operations: config %s: %s of character %r are all fused to '%s' of %r, so they become that "
                       "one joint and move with it as one (their own bones and motion are lost); attach each at a "
                       "joint of its own, attach the joint they hang from, or set keep_joint = true on the "
                       "attaches", config.source, names, src,
                       inputs[tgt].skeleton.names[tj], tgt)


def plan_operations(inputs, config: Config) -> Plan:
    """Apply the config's actions: output skeleton, provenance, preliminary positioning.

    Parameters
    ----------
    inputs : dict of str -> Character
        Loaded characters, by config id (every id of ``config.characters``).
    config : Config

    Returns
    -------
    Plan

    Raises
    ------
    InputError
        Unknown joints (with the closest names), a subtree grafted onto itself, a joint used
        twice, an action on a removed joint, a cycle created by the actions.
    """
    missing = [cid for cid in config.characters if cid not in inputs]
    if missing:
        raise InputError(f"operations: characters {', '.join(missing)} of {config.source} are not loaded")
    for cid in config.characters:
        inputs[cid].require_skinned("operations")
    actions = resolve_actions(inputs, config)
    for a in actions:  # a character removed whole is a character that should not be in the config
        sk = inputs[a.target].skeleton
        if a.op == "remove" and np.all(sk.subtree(a.target_joint)):
            raise InputError(f"config {config.source}: actions[{a.index}] removes '{sk.names[a.target_joint]}', "
                             f"the root of every joint of character '{a.target}': nothing of it is left; remove "
                             f"a subtree below its root, or leave '{a.target}' out of [characters]")
    _warn_merged_sources(actions, inputs, config)
    rotations = resolve_rotations(inputs, config)
    structure = _structure(inputs, actions, config)
    if len(structure.order) == 0:
        removes = [f"actions[{a.index}]" for a in actions if a.op == "remove"]
        raise InputError(f"config {config.source}: the actions remove every joint ({', '.join(removes)}): nothing "
                         "is left to compose; remove a subtree below the root instead")
    positioned, scales, transforms, translations, info = position_inputs(
        inputs, actions, config, body=structure.body, part=structure.part, rotations=rotations)
    at_source = frozenset((cid, positioned[cid].skeleton.index(name))
                          for cid, entry in info.items() for name in entry["moved_with_limb"])
    skeleton, out_of_node, renamed = _build_skeleton(structure, positioned, config, at_source)

    provenance = tuple(structure.members[n] for n in structure.order)
    image = {cid: np.full(inputs[cid].skeleton.num_joints, -1, dtype=np.int64) for cid in config.characters}
    for o, ms in enumerate(provenance):
        for cid, j in ms:
            image[cid][j] = o
    for arr in image.values():
        arr.setflags(write=False)
    used = {cid: structure.used[cid].copy() for cid in config.characters}
    for arr in used.values():
        arr.setflags(write=False)
    fused = tuple(
        FusedPair(int(image[a.target][a.target_joint]), a.target, a.target_joint, a.source, a.source_joint, a.index)
        for a in actions if a.fuses
    )
    attached = tuple(
        FusedPair(int(image[a.source][a.source_joint]), a.target, a.target_joint, a.source, a.source_joint, a.index)
        for a in actions if a.grafts and not a.fuse
    )

    def jname(cid, j):
        return f"{cid}:{inputs[cid].skeleton.names[j]}"

    report = {
        "characters": info,
        "fused_pairs": [
            {"output": skeleton.names[f.output], "target": jname(f.target, f.target_joint),
             "source": jname(f.source, f.source_joint), "action": f.action}
            for f in fused
        ],
        "attached_joints": [
            {"output": skeleton.names[f.output], "parent": skeleton.names[skeleton.parents[f.output]],
             "target": jname(f.target, f.target_joint), "source": jname(f.source, f.source_joint), "action": f.action}
            for f in attached
        ],
        "output_joints": skeleton.num_joints,
        "renamed": {new: jname(*provenance[skeleton.names.index(new)][0]) for new in renamed},
    }
    logger.debug("operations: %d output joints, %d fused pairs", skeleton.num_joints, len(fused))
    return Plan(skeleton=skeleton, provenance=provenance, used=used, image=image, fused_pairs=fused,
                actions=actions, positioned=positioned, scales=scales, transforms=transforms,
                translations=translations, report=report, attached_pairs=attached)
