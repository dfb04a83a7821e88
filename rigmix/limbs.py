"""Limbs of any rig: arms, legs, head, tail and wings found from the skeleton and the skin.

:func:`classify_limbs` reads a :class:`~rigmix.character.Character` and returns its
:class:`BodyPlan`: the trunk joints, one :class:`Limb` per chain that leaves the trunk, and the
joints that deform nothing (IK and pole targets). :func:`limbs_summary` is the same as JSON-ready
rows (what ``rigmix inspect`` can print, and what a composition matrix enumerates).

How it works
------------
1. **Deforming joints.** A joint deforms when it or a descendant carries vertex weight (or holds
   a rigid prop). The others (IK targets, pole targets, a weightless ``Gun`` socket) are
   reported in ``BodyPlan.excluded`` and take no part.
2. **Mirror pairs.** Two deforming joints off the symmetry plane
   (:func:`rigmix.operations.mirror.mirror_plane`), on opposite sides, are candidates when one's
   reflected rest position lands near the other (within ``2 * PAIR_TOL`` of the width) or when
   their names differ only by side (:func:`rigmix.rig.swap_side`; a posed rig's feet). A
   candidate costs the reflection distance plus that of the two parents (whole chains pair with
   the chain whose shape mirrors theirs), plus a little when the names do not pair: pairs are
   taken by increasing cost, each joint once. Positions win over names; names break ties.
3. **Detached parts.** Subtrees hanging from a skinless armature root (or roots of their own)
   whose skin touches the tip of another chain, beyond that chain's end, belong to that chain's
   limb (``Limb.detached``): the Quaternius IK feet, the Snake's head mesh on a ``Mouth`` bone.
   "Touches" is the joint owning most of the skin next to the part's top joint
   (:func:`_contact`, within ``CONTACT`` of the diagonal).
4. **Trunk and chains.** The trunk runs from the main root to the last unpaired joint with two
   heavy unpaired branches. Each unpaired chain beyond it (following its heaviest unpaired child)
   is a head, tail or other candidate; a chain holding under 5 % of the skin is body (a belly
   bone) unless nothing heavier leaves the trunk. The topmost paired joints start the paired
   limbs; along a paired chain, clavicle and hip joints still blended with the body are skipped
   (the same number of joints on both sides of a pair). An unpaired chain starts after the last
   joint a paired limb hangs from; small paired parts starting inside the skin of the chain's
   heaviest joint (ears on a head) belong to the chain. A joint named like a neck (``tail`` for
   a tail) settles where it starts when the chain holds one.
5. **Kinds**, by geometry first (+Y up, glTF's convention):

   * *leg*: a paired limb whose skin reaches the ground (within ``GROUND`` of the height). A
     ground-reaching pair hanging from well above the lowest-hanging pair, and above rather than
     ahead of it, is a pair of long arms. When no limb reaches the ground (a flying wasp), the
     paired limbs that hang down from where they start are legs.
   * *wing*: a paired limb whose skin is a thin, wide plate (smallest principal extent under
     ``WING_FLATNESS`` of the largest, the middle one over ``WING_WIDTH`` of it); a name holding
     ``wing`` settles a borderline case.
   * *arm*: any other paired limb. Both limbs of a pair get the kind of the surer side.
   * a pair whose skin stays inside the bounding box of the skin it hangs from (eyebrows on a
     shell) is a feature of the body, no limb.
   * *head*: the unpaired chain whose tip skin reaches highest plus the largest tip volume
     (relative to the other chains'); a chain holding a joint named ``head`` wins within
     ``HEAD_TIE``. *tail*: a chain whose skin lies behind where the head leaves the body and
     which does not rise more than it goes back; other chains are *other*.
6. **Facing and sides.** Forward is the horizontal axis across the mirror plane's normal, its
   sign voted by the head (its tip ahead of where it leaves the body, when clearly so) and the
   feet (toes ahead of the hips, when at least two stand and agree), glTF's +Z breaking a tie.
   A limb's side is the side of the plane its root lies on, seen facing forward.

Names are only ever a tie-breaker: a rig whose bones are called ``Bone.012`` classifies the same
way, with a lower confidence where a name would have settled a borderline case.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import numpy as np

from .character import Character
from .rig import swap_side
from .sparse_weights import influence_matrix, row_blocks

__all__ = ["Limb", "BodyPlan", "classify_limbs", "limbs_summary", "KINDS"]

log = logging.getLogger(__name__)

#: the limb kinds, in the order a summary lists them
KINDS = ("head", "arm", "leg", "wing", "tail", "other")

#: a limb whose skin comes this close to the ground (fraction of the height) stands on it
GROUND = 0.1
#: a joint whose own weight lies less than this on vertices its subtree owns is still body
SEPARATION = 0.75
#: a wing's skin: smallest principal extent below this fraction of the largest ...
WING_FLATNESS = 0.12
#: ... and the middle one above this fraction of the largest
WING_WIDTH = 0.35
#: two joints pair when one's reflection lands within this fraction of the character's width
PAIR_TOL = 0.08
#: a detached part's skin touches its host's within this fraction of the bounding-box diagonal
CONTACT = 0.05
#: a T-posed clavicle is shorter than this fraction of the upper arm after it (human clavicles
#: are about half the upper arm's length at most; the Quaternius rigs' about a third).
CLAVICLE_LENGTH = 0.5
#: a chain holding a joint named head wins the head over one scoring at most this much more
HEAD_TIE = 0.3


@dataclass(frozen=True)
class Limb:
    """One chain leaving the trunk.

    Attributes
    ----------
    kind : {"arm", "leg", "head", "tail", "wing", "other"}
    side : {"L", "R"} or None
        The character's own left or right (from the rest geometry and the facing direction);
        ``None`` for an unpaired chain.
    root : str
        The joint whose subtree is the limb (what a ``replace`` action names).
    joints : tuple of str
        The deforming joints of the root's subtree, parents first.
    partner : str or None
        Root of the mirror limb on the other side.
    detached : tuple of str
        Deforming joints outside the root's subtree that belong to the limb: IK feet that carry
        the foot's skin but hang from the armature root.
    confidence : float
        0 to 1: how clearly the geometry (and, as tie-breaker, the names) supports ``kind``.
    """

    kind: str
    side: str | None
    root: str
    joints: tuple[str, ...]
    partner: str | None = None
    detached: tuple[str, ...] = ()
    confidence: float = 1.0

    @property
    def label(self) -> str:
        """``arm.L``, ``leg.R``, ``head``, ... (not unique: a wasp has three ``leg.L``)."""
        return f"{self.kind}.{self.side}" if self.side else self.kind


@dataclass(frozen=True)
class BodyPlan:
    """What :func:`classify_limbs` finds.

    Attributes
    ----------
    limbs : tuple of Limb
        Ordered by kind (:data:`KINDS`), then side, then joint order.
    trunk : tuple of str
        Deforming joints that belong to no limb (spine, pelvis, armature root).
    excluded : tuple of str
        Joints that deform nothing: no weight on them or below them (IK and pole targets).
    symmetry_axis : int
        0, 1 or 2: the axis the mirror plane is perpendicular to.
    counts : dict of str -> int
        Limbs of each kind.
    forward : (3,) tuple of float
        The direction the character faces at rest, world space: a unit horizontal axis (the
        glTF frame, +Y up), its sign from the head and the feet (step 7 above).
    """

    limbs: tuple[Limb, ...]
    trunk: tuple[str, ...]
    excluded: tuple[str, ...]
    symmetry_axis: int = 0
    counts: dict = field(default_factory=dict)
    forward: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def of_kind(self, kind: str) -> tuple[Limb, ...]:
        """The limbs of one kind."""
        return tuple(limb for limb in self.limbs if limb.kind == kind)

    def limb(self, root: str) -> Limb:
        """The limb whose root joint is ``root`` (``KeyError`` if none)."""
        for limb in self.limbs:
            if limb.root == root:
                return limb
        raise KeyError(root)


_NECK = re.compile(r"neck", re.I)
_TAIL = re.compile(r"tail", re.I)
_ARM = re.compile(r"arm|hand|fist|palm|finger", re.I)
_LEG = re.compile(r"leg|foot|feet|thigh|shin|knee|toe", re.I)
_WING = re.compile(r"wing", re.I)


class _Rig:
    """The arrays the classifier reads, computed once."""

    def __init__(self, character: Character):
        from .operations.mirror import mirror_plane
        from .skinning import rest_pose

        sk = character.skeleton
        self.sk = sk
        self.names = sk.names
        J = sk.num_joints
        self.J = J
        self.parents = np.asarray(sk.parents)
        self.P = sk.rest_worlds()[:, :3, 3] if J else np.zeros((0, 3))
        skinned = [m for m in character.meshes if m.skinned]
        parts = rest_pose(character) if character.meshes else []
        V = [v for m, v in zip(character.meshes, parts) if m.skinned]
        self.V = np.concatenate(V) if V else np.zeros((0, 3))
        # per influence (memory O(n k), not O(n J)); the figures below are the dense matrix's, bit for bit
        base = np.cumsum([0] + [len(m.positions) for m in skinned])
        self.W = influence_matrix(
            np.concatenate([b + np.repeat(np.arange(len(m.positions)), m.joints.shape[1])
                            for b, m in zip(base, skinned)]) if skinned else [],
            np.concatenate([m.joints.ravel() for m in skinned]) if skinned else [],
            np.concatenate([m.weights.ravel() for m in skinned]) if skinned else [], (int(base[-1]), J))
        mass = np.bincount(self.W.indices, weights=self.W.data, minlength=J)  # column sums in row order
        for prop in character.props:
            if 0 <= prop.joint < J:
                mass[prop.joint] += len(prop.mesh.positions)
        self.mass = mass
        self.children = [[] for _ in range(J)]
        for j in range(J):
            if self.parents[j] >= 0:
                self.children[self.parents[j]].append(j)
        sub = mass.copy()
        for j in range(J - 1, -1, -1):
            if self.parents[j] >= 0:
                sub[self.parents[j]] += sub[j]
        self.subtree_mass = sub
        self.deforms = sub > 0
        self.owner = (np.asarray(self.W.argmax(axis=1)).ravel().astype(np.int64) if self.W.shape[0] and J
                      else np.zeros(self.W.shape[0], dtype=np.int64))
        allpts = np.concatenate([self.V, self.P]) if len(self.V) else self.P
        lo, hi = (allpts.min(axis=0), allpts.max(axis=0)) if len(allpts) else (np.zeros(3), np.ones(3))
        self.lo, self.hi = lo, hi
        self.height = float(hi[1] - lo[1]) or 1.0
        self.plane = mirror_plane(character)
        a = self.plane.axis
        self.axis = a
        self.width = float(hi[a] - lo[a]) or float(np.linalg.norm(hi - lo)) or 1.0
        self.partner = self._pairs()

    def dchildren(self, j: int) -> list[int]:
        return [c for c in self.children[j] if self.deforms[c]]

    def subtree(self, j: int) -> list[int]:
        """The deforming joints of ``j``'s subtree (``j`` first), parents before children."""
        out, seen = [j], {j}
        for k in range(j + 1, self.J):
            if self.parents[k] in seen and self.deforms[k]:
                out.append(k)
                seen.add(k)
        return out

    def offset(self, j: int) -> float:
        return float(self.P[j, self.axis] - self.plane.offset)

    def _pairs(self) -> np.ndarray:
        """``(J,)`` mirror partner of each deforming joint, ``-1`` for none.

        Every two deforming joints off the plane, on opposite sides, whose reflected rest positions
        land within ``2 * PAIR_TOL`` of the width are candidates. The cost of a candidate is the
        distance between one joint's reflection and the other, plus the same distance for their
        parents (so a chain pairs with the chain whose whole shape mirrors it, and a joint at the
        same place as another, like an IK foot beside the foot bone, pairs with the joint of the
        mirrored chain), plus a small term when the names do not differ by side only (names break
        ties, never override positions). Pairs are taken greedily by increasing cost, each joint
        once: a mutual-best assignment.
        """
        partner = np.full(self.J, -1)
        tol = PAIR_TOL * self.width
        a = self.axis
        off = self.P[:, a] - self.plane.offset
        dj = [j for j in np.flatnonzero(self.deforms) if abs(off[j]) > tol / 4]
        if len(dj) < 2:
            return partner
        R = self.P.copy()
        R[:, a] = 2 * self.plane.offset - R[:, a]
        index = {n: i for i, n in enumerate(self.names)}
        dj = np.asarray(dj)
        D = np.linalg.norm(R[dj][:, None, :] - self.P[dj][None, :, :], axis=2)
        cands = []
        for x, i in enumerate(dj):
            named = index.get(swap_side(self.names[i]), -1)
            for y in np.flatnonzero((D[x] <= 2 * tol) | (dj == named)):
                k = int(dj[y])
                if k <= i or off[i] * off[k] >= 0:
                    continue
                pi, pk = self.parents[i], self.parents[k]
                if pi >= 0 and pk >= 0:
                    dp = 0.0 if pi == pk else float(np.linalg.norm(R[pi] - self.P[pk]))
                else:
                    dp = 0.0 if pi == pk else tol
                cands.append((float(D[x, y]) + min(dp, 2 * tol) + (0.0 if named == k else 0.05 * tol), int(i), k))
        for _, i, k in sorted(cands):
            if partner[i] < 0 and partner[k] < 0:
                partner[i], partner[k] = k, i
        return partner

    def region(self, joints) -> np.ndarray:
        """Rest vertices whose largest weight is on one of ``joints``."""
        if not len(self.V):
            return np.zeros((0, 3))
        return self.V[np.isin(self.owner, list(joints))]

    def separation(self, j: int) -> float:
        """The fraction of joint ``j``'s own weight on vertices whose weight stays in its subtree."""
        n = self.W.shape[0]
        if self.mass[j] <= 0 or not n:
            return 1.0
        sub = self.subtree(j)
        w, inside = np.zeros(n), np.zeros(n)
        for rows in row_blocks(n, self.J):  # dense rows a block at a time: each row's sums as dense
            block = self.W[rows].toarray()
            w[rows] = block[:, j]
            inside[rows] = block[:, sub].sum(axis=1)
        return float((w * inside).sum() / w.sum())


def _contact(rig: _Rig, own: set, top: int) -> int:
    """The joint outside ``own`` that owns most of the skin next to ``top``'s skin (``-1``: none).

    Each vertex owned by ``top`` (a joint of ``own``) votes for the owner of its nearest vertex owned elsewhere, when
    that vertex lies within ``CONTACT`` of the bounding-box diagonal; a subtree with no skin, or
    touching nothing, falls back to the joint nearest its top joint.
    """
    mine = np.isin(rig.owner, list(own)) if len(rig.V) else np.zeros(0, dtype=bool)
    voters = rig.owner == top if len(rig.V) else mine
    if voters.any() and (~mine).any():
        from scipy.spatial import cKDTree

        others = np.flatnonzero(~mine)
        d, i = cKDTree(rig.V[others]).query(rig.V[voters])
        near = d <= CONTACT * float(np.linalg.norm(rig.hi - rig.lo))
        if near.any():
            votes = np.bincount(rig.owner[others[i[near]]], minlength=rig.J)
            return int(np.argmax(votes))
    cand = [k for k in np.flatnonzero(rig.deforms) if k not in own]
    if not cand:
        return -1
    return int(cand[int(np.argmin(np.linalg.norm(rig.P[cand] - rig.P[top], axis=1)))])



def _main_chain(rig: _Rig, j: int) -> list[int]:
    """From ``j`` down, following the child with the heaviest subtree."""
    chain = [j]
    while True:
        kids = rig.dchildren(chain[-1])
        if not kids:
            return chain
        chain.append(max(kids, key=lambda c: rig.subtree_mass[c]))


def _lateral(rig: _Rig, j: int, k: int) -> bool:
    d = rig.P[k] - rig.P[j]
    n = float(np.linalg.norm(d))
    return n > 0 and abs(d[rig.axis]) > 0.7 * n


def _clavicle(rig: _Rig, chain: list[int]) -> bool:
    """Whether the chain's first bone is a clavicle: a bone across the body before the chain
    turns (an A-pose), or, where the chain goes on across (a T-pose), one under
    ``CLAVICLE_LENGTH`` of the next bone's length whose skin stays blended with the body."""
    if len(chain) < 3 or not _lateral(rig, chain[0], chain[1]):
        return False
    if not _lateral(rig, chain[1], chain[2]):
        return True
    first, second = (float(np.linalg.norm(rig.P[b] - rig.P[a])) for a, b in zip(chain, chain[1:3]))
    return first < CLAVICLE_LENGTH * second and rig.separation(chain[0]) < 0.7


def _limb_root(rig: _Rig, chain: list[int]) -> int:
    """How many joints along a paired chain the limb starts: past a clavicle (:func:`_clavicle`)
    and past a hip whose skin stays blended with the body behind it."""
    i = 0
    if _clavicle(rig, chain):
        i = 1
        if len(chain) >= 4 and rig.separation(chain[1]) < 0.7 <= rig.separation(chain[2]):
            i = 2
    return i


def _flat_wide(pts: np.ndarray) -> tuple[bool, float]:
    """Whether points form a thin, wide plate; and the flatness (smallest / largest extent)."""
    if len(pts) < 6:
        return False, 1.0
    c = pts - pts.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] <= 0:
        return False, 1.0
    return bool(s[2] < WING_FLATNESS * s[0] and s[1] > WING_WIDTH * s[0]), float(s[2] / s[0])


def _hull_volume(pts: np.ndarray) -> float:
    if len(pts) < 5:
        return 0.0
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(pts).volume)
    except (QhullError, ValueError):
        return 0.0


def classify_limbs(character: Character) -> BodyPlan:
    """Arms, legs, head, tail and wings of ``character``, from its skeleton and skin.

    Parameters
    ----------
    character : Character
        Any rig; one with no joint or no skin gives an empty plan.

    Returns
    -------
    BodyPlan
    """
    rig = _Rig(character)
    names = rig.names
    excluded = tuple(names[j] for j in range(rig.J) if not rig.deforms[j])
    if not rig.deforms.any():
        return BodyPlan((), (), excluded, rig.axis)
    paired = rig.partner >= 0
    roots = [j for j in range(rig.J) if rig.parents[j] < 0 and rig.deforms[j]]

    # 1. paired subtrees: topmost paired joints under an unpaired parent (or a root)
    starts = [j for j in range(rig.J) if rig.deforms[j] and paired[j]
              and (rig.parents[j] < 0 or not paired[rig.parents[j]])]
    in_start = {}
    for s in starts:
        for k in rig.subtree(s):
            in_start[k] = s

    # 2. the main root, its hub (the joints below it that carry no skin and hold one branch) and
    #    the loose subtrees: the hub's other branches and the other roots
    main_root = max(roots, key=lambda r: rig.subtree_mass[r])
    total = rig.subtree_mass[main_root]
    hub = main_root
    while rig.mass[hub] <= 0.01 * total and len(rig.dchildren(hub)) == 1:
        hub = rig.dchildren(hub)[0]
    loose = [r for r in roots if r != main_root]
    if rig.mass[hub] <= 0.01 * total:
        loose += rig.dchildren(hub)
    # a loose subtree is a detached part of the chain whose tip its skin touches: the IK feet of
    # the Quaternius rigs that carry the foot's skin but hang from the armature root, the Snake's
    # head mesh on a Mouth bone under the root. Its host is the joint outside it owning most of
    # the skin next to its own; the host must be a tip (a leaf, or a joint whose children are all
    # leaves) below the top of its own subtree (so a body never hangs from the feet it touches),
    # and the part must lie beyond the host (a thigh touching a hanging hand is no detached part).
    detached_of: dict[int, int] = {}  # detached top -> start of the paired subtree it joins
    unpaired_detached: dict[int, int] = {}  # detached top -> unpaired host joint
    start_set = set(starts)
    loose_top = {}
    for x in loose:
        for k in rig.subtree(x):
            loose_top[k] = x
    for x in loose:
        own = rig.subtree(x)
        if any(s != x and s in start_set for s in own):
            continue  # it has limbs of its own: a body, not a part
        top = next((k for k in own if rig.mass[k] > 0), x)
        t = _contact(rig, set(own), top)
        if t < 0 or loose_top.get(t) == t:
            continue
        kids = rig.dchildren(t)
        if any(rig.dchildren(c) for c in kids):
            continue
        # and it lies beyond the host, seen from where the host's chain starts
        origin = rig.P[in_start.get(t, main_root)]
        if np.linalg.norm(rig.P[top] - origin) < 0.8 * np.linalg.norm(rig.P[t] - origin):
            continue
        if t in in_start and in_start[t] != x:
            detached_of[x] = in_start[t]
        else:
            unpaired_detached[x] = t

    # 3. unpaired structure

    def unp_children(j):
        return [c for c in rig.dchildren(j) if not paired[c]]

    def heavy(c):
        return rig.subtree_mass[c] >= 0.05 * total

    skip = set(detached_of) | set(unpaired_detached)

    # trunk: from the main root to its last unpaired branch point with two heavy unpaired branches
    trunk = [main_root]
    j = main_root
    while True:
        kids = [c for c in unp_children(j) if c not in skip]
        heavy_kids = [c for c in kids if heavy(c)]
        if len(heavy_kids) >= 2 or not kids:
            break
        # descend only while something further down branches
        below = [k for k in rig.subtree(kids[0])
                 if len([c for c in unp_children(k) if heavy(c) and c not in skip]) >= 2]
        if not below:
            break
        j = max(kids, key=lambda c: rig.subtree_mass[c])
        trunk.append(j)
    # walk the heavy branch points below too: the trunk is every unpaired joint with >= 2 heavy
    # unpaired branches below the main root, and the path to it
    branch = [k for k in rig.subtree(main_root) if not paired[k]
              and len([c for c in unp_children(k) if heavy(c) and c not in skip]) >= 2]
    trunk_set = set(trunk)
    for b in branch:
        a = b
        while a >= 0 and a not in trunk_set:
            trunk_set.add(a)
            a = rig.parents[a]
    # unpaired chains hanging from the trunk (and other unpaired roots)
    chain_starts = []
    for t in sorted(trunk_set):
        for c in unp_children(t):
            if c not in trunk_set and c not in skip:
                chain_starts.append(c)
    for r in roots:
        if r != main_root and not paired[r] and r not in skip:
            chain_starts.append(r)

    # 4. limb roots of paired subtrees: skip clavicle/hip joints still blended with the body
    attach = {}  # paired start -> joint it hangs from
    limbs_raw = []  # (start, root)
    depth = {}
    for s in starts:
        if s not in skip:
            depth[s] = _limb_root(rig, _main_chain(rig, s))
    for s in starts:
        if s in skip:
            continue
        chain = _main_chain(rig, s)
        # a mirror pair starts at the same depth along its chains (the shallower of the two)
        i = min(depth[s], depth.get(rig.partner[s], depth[s]))
        attach[s] = rig.parents[s]
        limbs_raw.append((s, chain[min(i, len(chain) - 1)]))
    attach_points = {a for a in attach.values() if a >= 0}
    hanging = {a: sum(rig.subtree_mass[s] for s, p in attach.items() if p == a) for a in attach_points}

    def det_of(joints):
        """The detached parts hanging from ``joints`` (and from the parts themselves)."""
        out, todo = [], set(joints)
        grew = True
        while grew:
            grew = False
            for d, host in unpaired_detached.items():
                if host in todo and d not in todo:
                    sub = rig.subtree(d)
                    out += sub
                    todo.update(sub)
                    grew = True
        return out

    # unpaired chains: the path follows the heaviest unpaired child. A chain carrying little skin
    # (under 5 % of the body: a belly or rump bone) is body, unless the body has no heavier chain.
    chains = []
    for c in chain_starts:
        path = [c]
        while True:
            kids = [k for k in unp_children(path[-1]) if k not in skip]
            if not kids:
                break
            path.append(max(kids, key=lambda k: rig.subtree_mass[k]))
        mass = rig.subtree_mass[c] + sum(rig.subtree_mass[d] for d in det_of(rig.subtree(c)) if d in unpaired_detached)
        chains.append((c, path, mass))
    if any(m >= 0.05 * total for _, _, m in chains):
        chains = [t for t in chains if t[2] >= 0.05 * total]

    def chain_root(path, tail_like):
        """Where an unpaired chain leaves the body: after the last joint a paired limb hangs from
        (paired parts starting inside the skin of the chain's heaviest joint and lighter than it,
        ears on a head, belong to the chain); a joint named like a neck (a tail) settles it when
        the chain holds one."""
        bulk = path[int(np.argmax(rig.mass[path]))]
        box = rig.region([bulk])
        lo, hi = (box.min(axis=0), box.max(axis=0)) if len(box) else (rig.P[bulk], rig.P[bulk])

        def accessory(a):
            inside = all(np.all((rig.P[s] >= lo) & (rig.P[s] <= hi)) for s, p in attach.items() if p == a)
            return inside and hanging[a] < rig.mass[bulk]

        last = -1
        for i, k in enumerate(path):
            if k in attach_points and not accessory(k):
                last = i
        geo = path[min(last + 1, len(path) - 1)]
        pat = _TAIL if tail_like else _NECK
        named = [k for k in path if pat.search(names[k])]
        return (named[0], True) if named else (geo, False)

    def tip_region(path):
        joints = rig.subtree(path[-1])
        joints = joints + det_of(joints)
        pts = rig.region(joints)
        return pts if len(pts) else rig.P[joints]

    # 5. the head: the unpaired chain whose tip's skin reaches highest (a fraction of the height)
    #    plus its tip's size (a fraction of the largest tip's); a chain holding a joint named head
    #    wins within HEAD_TIE (the name only breaks a near tie)
    tops = [float(tip_region(path)[:, 1].max() - rig.lo[1]) / rig.height for _, path, _ in chains]
    vols = [_hull_volume(tip_region(path)) ** (1 / 3) for _, path, _ in chains]
    score = [t + v / (max(vols) or 1.0) for t, v in zip(tops, vols)]
    head = None
    head_conf = 0.5
    if chains:
        order_ = sorted(range(len(chains)), key=lambda i: -score[i])
        best = order_[0]
        for i in order_[1:]:
            if score[i] >= score[best] - HEAD_TIE and any(re.search("head", names[k], re.I) for k in chains[i][1]) \
                    and not any(re.search("head", names[k], re.I) for k in chains[best][1]):
                best = i
        head = best
        second = max((score[i] for i in order_ if i != best), default=0.0)
        head_conf = float(np.clip(0.5 + (score[best] - second) / 2, 0.5, 1.0))

    # 6. paired limbs: reach the ground, flat and wide, hang below
    ground = rig.lo[1]
    raw = []
    absorbed = set()
    for c, path, _ in chains:
        root, _ = chain_root(path, False)
        for s in starts:
            if s in rig.subtree(root) or s in det_of(rig.subtree(root)):
                absorbed.add(s)
    # a paired subtree whose skin stays inside the skin it hangs from (its bounding box) is a
    # feature of the body (eyebrows on the Crab's shell), no limb; so is its mirror
    feature = set()
    for s, root in limbs_raw:
        region = rig.region(rig.subtree(root))
        body = rig.region([attach[s]]) if attach[s] >= 0 else np.zeros((0, 3))
        if len(region) and len(body) and np.all(region >= body.min(axis=0)) and np.all(region <= body.max(axis=0)):
            feature.update((s, rig.partner[s]))
    for s, root in limbs_raw:
        if s in absorbed or s in feature:
            continue
        joints = rig.subtree(root)
        det = [k for d, host in detached_of.items() if host == s for k in rig.subtree(d)]
        det += det_of(joints + det)
        region = rig.region(joints + det)
        pts = np.concatenate([region, rig.P[joints + det]])
        low = float(pts[:, 1].min())
        flat, flatness = _flat_wide(region)
        raw.append(dict(s=s, root=root, joints=joints, det=det, low=low, flat=flat, flatness=flatness,
                        region=region, pts=pts))
    reach = [r for r in raw if r["low"] - ground <= GROUND * rig.height]
    for r in raw:
        nm = " ".join(names[k] for k in r["joints"] + r["det"])
        winged = bool(_WING.search(nm))
        above = (r["low"] - ground) / rig.height
        hangs = r["low"] < rig.P[r["s"], 1] - 0.05 * rig.height
        if r in reach:
            kind = "leg"
            conf = float(np.clip(1 - above / GROUND * 0.5, 0.5, 1.0))
        elif r["flat"] or (winged and r["flatness"] < 2 * WING_FLATNESS):
            kind, conf = "wing", (0.9 if winged or r["flat"] else 0.6)
        elif not reach and hangs and not _ARM.search(nm):
            kind, conf = "leg", 0.6  # hangs below a body that stands on nothing (flying)
        else:
            kind, conf = "arm", 0.8 if _ARM.search(nm) or not _LEG.search(nm) else 0.6
        r["kind"], r["conf"] = kind, conf
    # of the limbs on the ground, a pair hanging from well above the lowest-hanging pair (by half
    # the hip height), and above it rather than ahead of it, is a pair of long arms (a chibi's),
    # not a second pair of legs
    f = 2 if rig.axis != 2 else 0
    if reach:
        base = min(reach, key=lambda r: rig.P[r["s"], 1])
        for r in reach:
            gap = rig.P[r["s"], 1] - rig.P[base["s"], 1]
            if gap > 0.5 * (rig.P[base["s"], 1] - ground) and gap > abs(rig.P[r["s"], f] - rig.P[base["s"], f]):
                r["kind"], r["conf"] = "arm", 0.6

    # a mirror pair is one kind: where the two sides disagree, the surer side decides
    by_start = {r["s"]: r for r in raw}
    for r in raw:
        o = by_start.get(rig.partner[r["s"]])
        if o is not None and o["kind"] != r["kind"]:
            sure = max((r, o), key=lambda x: (x["conf"], -x["s"]))
            for x in (r, o):
                x["kind"], x["conf"] = sure["kind"], min(r["conf"], o["conf"])

    # 7. facing: the horizontal axis across the mirror plane's normal; its sign by the head (its
    #    tip ahead of where it leaves the body) and the feet (toes ahead of the hips); glTF's +Z
    #    breaks a tie
    vote = 0.02 if f == 2 else 0.0

    def centroid(pts):
        return pts.mean(axis=0)

    head_base = -1
    if head is not None:
        c, path, _ = chains[head]
        base = head_base = rig.parents[c] if rig.parents[c] >= 0 else c
        ahead = (centroid(tip_region(path))[f] - rig.P[base, f]) / rig.height
        if abs(ahead) > 0.1:  # a head above its neck (a biped's) says nothing
            vote += ahead
    toes = []
    for r in raw:
        if r["kind"] == "leg" and r in reach:
            foot = r["pts"][r["pts"][:, 1] <= ground + 0.03 * rig.height]
            if len(foot):
                # the toes lie ahead of the leg's lowest joint (the ankle, or a foot bone at the
                # heel) and of the hip (an IK foot bone at the toes hides the first)
                ankle = min(r["joints"] + r["det"], key=lambda k: rig.P[k, 1])
                toe = centroid(foot)[f]
                toes.append(float((2 * toe - rig.P[ankle, f] - rig.P[r["root"], f]) / rig.height))
    # the feet count when at least two stand on the ground and all point the same way (a stride
    # pose puts one foot ahead and one behind)
    if len(toes) >= 2 and (all(t > 0 for t in toes) or all(t < 0 for t in toes)):
        vote += 0.5 * sum(toes)
    forward = np.zeros(3)
    forward[f] = 1.0 if vote >= 0 else -1.0
    log.debug("limbs: head scores %s, facing vote %.3f (toes %s): forward %s",
              {names[c]: round(s_, 3) for (c, _, _), s_ in zip(chains, score)}, vote,
              [round(t, 3) for t in toes], forward)
    up = np.array([0.0, 1.0, 0.0])
    left = np.cross(up, forward)

    limbs: list[Limb] = []
    for i, (c, path, _) in enumerate(chains):
        if i == head:
            kind, conf = "head", head_conf
        else:
            # a tail: its skin lies behind where the head leaves the body, and it does not rise
            # more than it goes back (the Wasp's abdomen hangs down, behind the neck)
            region = rig.region(rig.subtree(c))
            mid = centroid(region if len(region) else rig.P[path])
            d = mid - rig.P[c]
            behind = head is not None and np.dot(mid - rig.P[head_base], forward) < 0
            if behind and -np.dot(d, forward) > d[1]:
                kind = "tail"
                conf = 0.9 if any(_TAIL.search(names[k]) for k in path) else 0.7
            else:
                kind, conf = "other", 0.5
        root, _ = chain_root(path, kind == "tail")
        joints = rig.subtree(root)
        det = det_of(joints)
        limbs.append(Limb(kind, None, names[root], tuple(names[k] for k in joints), None,
                          tuple(names[k] for k in det), round(conf, 2)))
    for r in raw:
        root = r["root"]
        side = "L" if (rig.P[root, rig.axis] - rig.plane.offset) * left[rig.axis] > 0 else "R"
        # the partner limb: the one whose start pairs with this one's start
        o = by_start.get(rig.partner[r["s"]])
        partner_name = names[o["root"]] if o is not None else None
        limbs.append(Limb(r["kind"], side, names[root], tuple(names[k] for k in r["joints"]), partner_name,
                          tuple(names[k] for k in r["det"]), round(r["conf"], 2)))
    # everything deforming that no limb holds is trunk
    held = set()
    for limb in limbs:
        held.update(limb.joints)
        held.update(limb.detached)
    trunk_names = tuple(names[j] for j in range(rig.J) if rig.deforms[j] and names[j] not in held)
    order = {k: i for i, k in enumerate(KINDS)}
    index = {n: i for i, n in enumerate(names)}
    limbs.sort(key=lambda lb: (order[lb.kind], lb.side or "", index[lb.root]))
    counts = {k: sum(1 for lb in limbs if lb.kind == k) for k in KINDS}
    return BodyPlan(tuple(limbs), trunk_names, excluded, rig.axis, counts, tuple(float(x) for x in forward))


def limbs_summary(character: Character) -> list[dict]:
    """:func:`classify_limbs` as JSON-ready rows, one per limb (then one for the excluded joints).

    Each row: ``kind``, ``side``, ``root``, ``joints`` (count), ``chain`` (names), ``partner``,
    ``detached``, ``confidence``.
    """
    plan = classify_limbs(character)
    rows = [{"kind": lb.kind, "side": lb.side, "root": lb.root, "joints": len(lb.joints), "chain": list(lb.joints),
             "partner": lb.partner, "detached": list(lb.detached), "confidence": lb.confidence}
            for lb in plan.limbs]
    return rows
