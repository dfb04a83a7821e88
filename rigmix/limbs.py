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
2. **Mirror pairs.** Two joints pair when one's rest position reflected across the character's
   symmetry plane (:func:`rigmix.operations.mirror.mirror_plane`) lands on the other, or when
   their names differ only by side (:func:`rigmix.rig.swap_side`) and both lie off the plane.
   A joint on the plane pairs with nothing.
3. **Chains.** The topmost paired joints below unpaired ones start the paired limbs. A paired
   subtree that hangs from a root (or from a root's direct child) and starts beside the tip of
   another limb is a *detached* part of that limb (the IK feet of the Quaternius rigs, which carry
   the foot's skin but hang from the armature root): it is reported under that limb's
   ``detached``. The unpaired joints form the trunk, the head chain and tail chains: the trunk is
   the part from the main root to the last unpaired branch point; each unpaired chain beyond it
   is a head, tail or other candidate.
4. **Where a limb starts.** Along a paired chain, clavicle, shoulder and hip joints whose skin
   stays blended with the body (less than ``SEPARATION`` of their own weight on vertices that
   their subtree owns) are part of the body: the limb starts at the first joint whose skin
   separates. Along an unpaired chain the head starts after the last joint where a paired limb
   attaches; a joint named like a neck (or ``tail`` for a tail) moves the start there when it is on
   the chain (a tie-breaker: the geometry decides where there is no such name).
5. **Kinds**, by geometry first (+Y up, glTF's convention):

   * *leg*: a paired limb whose skin reaches the ground (within ``GROUND`` of the character's
     height above its lowest rest point). When no limb reaches the ground (a flying wasp), the
     paired limbs that hang below the trunk are legs. A ground-reaching front pair of a
     four-legged body is a leg unless its joint names say ``arm`` (the Fox's forelegs).
   * *wing*: a paired limb whose skin is a thin, wide plate (smallest principal extent under
     ``WING_FLATNESS`` of the largest, the middle one over ``WING_WIDTH`` of it); a name holding
     ``wing`` settles a borderline case.
   * *arm*: any other paired limb that hangs from the upper body.
   * *head*: the unpaired chain with the largest skinned volume at its tip; *tail*: an unpaired
     chain leaving the trunk away from the head; other unpaired chains are *other*.

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
    """

    limbs: tuple[Limb, ...]
    trunk: tuple[str, ...]
    excluded: tuple[str, ...]
    symmetry_axis: int = 0
    counts: dict = field(default_factory=dict)

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
        self.W = (np.concatenate([m.dense_weights(J) for m in skinned]) if skinned else np.zeros((0, J)))
        mass = self.W.sum(axis=0)
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
        self.owner = np.argmax(self.W, axis=1) if len(self.W) else np.zeros(0, dtype=np.int64)
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
        out = [j]
        for k in range(j + 1, self.J):
            if self.parents[k] >= 0 and self.parents[k] in out and self.deforms[k]:
                out.append(k)
        return out

    def offset(self, j: int) -> float:
        return float(self.P[j, self.axis] - self.plane.offset)

    def _pairs(self) -> np.ndarray:
        """``(J,)`` mirror partner of each deforming joint, ``-1`` for none."""
        partner = np.full(self.J, -1)
        tol = PAIR_TOL * self.width
        dj = np.flatnonzero(self.deforms)
        if not len(dj):
            return partner
        R = self.P[dj].copy()
        R[:, self.axis] = 2 * self.plane.offset - R[:, self.axis]
        index = {n: i for i, n in enumerate(self.names)}
        # by name: the side-swapped name, on the other side of the joint (not at the same place)
        for j in dj:
            other = index.get(swap_side(self.names[j]), -1)
            if other >= 0 and other != j and self.deforms[other] \
                    and abs(self.P[j, self.axis] - self.P[other, self.axis]) > tol / 2:
                partner[j] = other
        # by position: mutual nearest reflections, off the plane
        free = [i for i, j in enumerate(dj) if partner[j] < 0 and abs(self.offset(j)) > tol / 4]
        near = {}
        for i in free:
            d = np.linalg.norm(self.P[dj] - R[i], axis=1)
            d[i] = np.inf
            k = int(np.argmin(d))
            if d[k] <= 2 * tol:
                near[dj[i]] = dj[k]
        for j, k in near.items():
            if near.get(k) == j and partner[k] < 0:
                partner[j] = k
        return partner

    def region(self, joints) -> np.ndarray:
        """Rest vertices whose largest weight is on one of ``joints``."""
        if not len(self.V):
            return np.zeros((0, 3))
        return self.V[np.isin(self.owner, list(joints))]

    def separation(self, j: int) -> float:
        """The fraction of joint ``j``'s own weight on vertices whose weight stays in its subtree."""
        if self.mass[j] <= 0 or not len(self.W):
            return 1.0
        sub = self.subtree(j)
        w = self.W[:, j]
        return float((w * self.W[:, sub].sum(axis=1)).sum() / w.sum())


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


def _limb_root(rig: _Rig, chain: list[int]) -> int:
    """Where a paired chain leaves the body: past a clavicle (a bone across the body before the
    chain turns) and past a hip whose skin stays blended with the body behind it."""
    i = 0
    if len(chain) >= 3 and _lateral(rig, chain[0], chain[1]) and not _lateral(rig, chain[1], chain[2]):
        i = 1
        if len(chain) >= 4 and rig.separation(chain[1]) < 0.7 <= rig.separation(chain[2]):
            i = 2
    return chain[i]


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

    def leaves_of(s):
        return [k for k in rig.subtree(s) if not rig.dchildren(k)]

    # 2. detached parts: a paired subtree hanging from a root (or a root's child) that starts
    #    beside a leaf of another paired subtree
    detached_of: dict[int, int] = {}
    rootish = [s for s in starts if rig.parents[s] < 0 or rig.parents[rig.parents[s]] < 0]
    loose = {k for s in rootish for k in rig.subtree(s)}
    for s in starts:
        p = rig.parents[s]
        if p >= 0 and rig.parents[p] >= 0:
            continue
        ancestors = set()
        a = p
        while a >= 0:
            ancestors.add(a)
            a = rig.parents[a]
        own = set(rig.subtree(s))
        cand = [k for k in range(rig.J) if rig.deforms[k] and k not in own and k not in ancestors
                and (k not in loose or in_start.get(k) in detached_of.values())]
        if not cand:
            continue
        d = np.linalg.norm(rig.P[cand] - rig.P[s], axis=1)
        k = cand[int(np.argmin(d))]
        host = in_start.get(k)
        if host is not None and host != s and k in leaves_of(host) and host not in detached_of:
            detached_of[s] = host
    # unpaired detached parts: an unpaired subtree hanging from a root that starts beside the tip of
    # the deepest unpaired chain (the Snake's head mesh on a Mouth bone under the root)
    unpaired_detached: dict[int, int] = {}

    # 3. unpaired structure
    unp = [j for j in range(rig.J) if rig.deforms[j] and not paired[j]]
    main_root = max(roots, key=lambda r: rig.subtree_mass[r])
    total = rig.subtree_mass[main_root]

    def unp_children(j):
        return [c for c in rig.dchildren(j) if not paired[c]]

    def heavy(c):
        return rig.subtree_mass[c] >= 0.05 * total

    for r in roots:
        for c in [r] + unp_children(r):
            if paired[c] or c == main_root or (c != r and heavy(c) and r != main_root):
                continue
            if c != r and c in unp_children(main_root):
                own = set(rig.subtree(c))
                cand = [k for k in unp if k not in own and k != r and rig.parents[k] >= 0]
                if not cand:
                    continue
                d = np.linalg.norm(rig.P[cand] - rig.P[c], axis=1)
                k = cand[int(np.argmin(d))]
                if not unp_children(k) and k not in own:
                    unpaired_detached[c] = k
    # trunk: from the main root to its last unpaired branch point with two heavy unpaired branches
    trunk = [main_root]
    j = main_root
    while True:
        kids = [c for c in unp_children(j) if c not in unpaired_detached]
        heavy_kids = [c for c in kids if heavy(c)]
        if len(heavy_kids) >= 2 or not kids:
            break
        # descend only while something further down branches
        below = [k for k in rig.subtree(kids[0])
                 if len([c for c in unp_children(k) if heavy(c)]) >= 2]
        if not below:
            break
        j = max(kids, key=lambda c: rig.subtree_mass[c])
        trunk.append(j)
    # walk the heavy branch points below too: the trunk is every unpaired joint with >= 2 heavy
    # unpaired branches below the main root, and the path to it
    branch = [k for k in rig.subtree(main_root) if not paired[k]
              and len([c for c in unp_children(k) if heavy(c) and c not in unpaired_detached]) >= 2]
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
            if c not in trunk_set and c not in unpaired_detached:
                chain_starts.append(c)
    for r in roots:
        if r != main_root and not paired[r] and r not in unpaired_detached:
            chain_starts.append(r)

    # 4. limb roots of paired subtrees: skip clavicle/hip joints still blended with the body
    attach = {}  # paired start -> joint it hangs from
    limbs_raw = []  # (start, root)
    for s in starts:
        if s in detached_of:
            continue
        chain = _main_chain(rig, s)
        root = _limb_root(rig, chain)
        attach[s] = rig.parents[s]
        limbs_raw.append((s, root))

    # which paired subtrees hang inside an unpaired chain's tip part: decided after the chain roots
    chains = []
    for c in chain_starts:
        path = _main_chain(rig, c)
        path = [k for k in path if not paired[k]]
        chains.append((c, path))

    # paired limbs attached along each unpaired chain
    attach_points = {a for a in attach.values() if a >= 0}

    def chain_root(path, tail_like):
        last = -1
        for i, k in enumerate(path):
            if k in attach_points:
                last = i
        geo = path[min(last + 1, len(path) - 1)]
        pat = _TAIL if tail_like else _NECK
        named = [k for k in path if pat.search(names[k])]
        if named:
            return named[0], True
        return geo, False

    # forward: from the trunk centre towards the heaviest-tipped chain, decided below
    def tip_volume(path, c):
        tip = path[-1]
        joints = [k for k in rig.subtree(path[-1])]
        for d, host in unpaired_detached.items():
            if host in path or host in joints:
                joints += rig.subtree(d)
        vol = _hull_volume(rig.region(joints))
        return vol if vol > 0 else float(rig.subtree_mass[tip])

    trunk_centre = rig.P[sorted(trunk_set)].mean(axis=0)
    up = np.array([0.0, 1.0, 0.0])
    scored = [(tip_volume(path, c), c, path) for c, path in chains]
    head = None
    if scored:
        vols = sorted((v for v, _, _ in scored), reverse=True)
        best = max(scored, key=lambda t: (t[0], any(re.search("head", names[k], re.I) for k in t[2])))
        # name tie-breaker: a chain holding a joint named head wins when within 30 %
        for v, c, path in scored:
            if v >= 0.7 * best[0] and any(re.search("head", names[k], re.I) for k in path) \
                    and not any(re.search("head", names[k], re.I) for k in best[2]):
                best = (v, c, path)
        head = best
        second = vols[1] if len(vols) > 1 else 0.0
        head_conf = float(np.clip(0.5 + 0.5 * (1 - second / best[0]) if best[0] > 0 else 0.5, 0.5, 1.0))
    forward = np.array([0.0, 0.0, 1.0])
    if head is not None:
        hp = rig.P[head[2][-1]] - trunk_centre
        hp[1] = 0.0
        hp[rig.axis] = 0.0
        if np.linalg.norm(hp) > 0.1 * rig.height:
            forward = hp / np.linalg.norm(hp)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-9:
        left = np.eye(3)[rig.axis]
    left = left / np.linalg.norm(left)

    limbs: list[Limb] = []
    absorbed_starts = set()
    # unpaired chains -> head / tail / other
    head_region_joints = set()
    for v, c, path in scored:
        tip = path[-1]
        direction = rig.P[tip] - rig.P[c]
        if head is not None and c == head[1]:
            kind, conf = "head", head_conf
        elif head is not None and np.dot(direction, forward) < 0 and np.dot(rig.P[tip] - trunk_centre, forward) < 0:
            kind = "tail"
            conf = 0.9 if any(_TAIL.search(names[k]) for k in path) else 0.7
        else:
            kind, conf = "other", 0.5
        root, named = chain_root(path, kind == "tail")
        if root not in path:
            root = c
        # the chain joints before the root are body
        for k in path[:path.index(root)]:
            trunk_set.add(k)
        joints = rig.subtree(root)
        det = []
        for d, host in unpaired_detached.items():
            if host in joints:
                det += rig.subtree(d)
        if kind in ("head", "tail", "other"):
            head_region_joints.update(joints)
        # paired subtrees inside the chain (ears on a head) belong to it
        for s in starts:
            if s in joints:
                absorbed_starts.add(s)
        limbs.append(Limb(kind, None, names[root], tuple(names[k] for k in joints), None,
                          tuple(names[k] for k in det), round(conf, 2)))

    # paired limbs
    ground = rig.lo[1]
    raw = []
    for s, root in limbs_raw:
        if s in absorbed_starts:
            continue
        joints = rig.subtree(root)
        det = [k for d, host in detached_of.items() if host == s for k in rig.subtree(d)]
        pts = np.concatenate([rig.region(joints + det), rig.P[joints + det]])
        low = float(pts[:, 1].min())
        flat, flatness = _flat_wide(rig.region(joints + det))
        raw.append(dict(s=s, root=root, joints=joints, det=det, low=low, flat=flat, flatness=flatness,
                        pos=rig.P[root]))
    reach = [r for r in raw if r["low"] - ground <= GROUND * rig.height]
    trunk_y = float(rig.P[sorted(trunk_set)][:, 1].mean())
    for r in raw:
        nm = " ".join(names[k] for k in r["joints"] + r["det"])
        winged = bool(_WING.search(nm))
        above = (r["low"] - ground) / rig.height
        if r in reach:
            kind = "leg"
            conf = float(np.clip(1 - above / GROUND * 0.5, 0.5, 1.0))
        elif r["flat"] or (winged and r["flatness"] < 2 * WING_FLATNESS):
            kind, conf = "wing", (0.9 if winged or r["flat"] else 0.6)
        elif not reach and r["low"] < trunk_y and not _ARM.search(nm):
            kind, conf = "leg", 0.6  # hangs below a body that stands on nothing (flying)
        else:
            kind, conf = "arm", 0.8 if _ARM.search(nm) or not _LEG.search(nm) else 0.6
        r["kind"], r["conf"] = kind, conf
    # a four-legged body: its front ground pair is a leg unless its names say arm
    legs = [r for r in raw if r["kind"] == "leg" and r in reach]
    if len(legs) >= 4:
        for r in legs:
            nm = " ".join(names[k] for k in r["joints"])
            if _ARM.search(nm) and not _LEG.search(nm):
                r["kind"], r["conf"] = "arm", 0.6
    for r in raw:
        root = r["root"]
        side_val = float(np.dot(rig.P[root] - trunk_centre, left))
        side = "L" if side_val > 0 else "R"
        partner = rig.partner[root]
        partner_name = names[partner] if partner >= 0 else None
        if partner < 0:
            # the partner limb's root: the limb whose start pairs with this one's start
            ps = rig.partner[r["s"]]
            for o in raw:
                if o["s"] == ps:
                    partner_name = names[o["root"]]
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
    return BodyPlan(tuple(limbs), trunk_names, excluded, rig.axis, counts)


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
