"""The composition matrix over the 27 characters, generated from the limb classifier.

:func:`load_subjects` reads every character of ``../shared/data/characters`` and
``../shared/data/corpus`` (``$RIGMIX_ASSETS``, ``$RIGMIX_CORPUS``) and classifies its limbs
(:func:`rigmix.limbs.classify_limbs`); :func:`generate_matrix` turns them into :class:`Case` s,
each a composition config (TOML text) whose paths read ``${RIGMIX_ASSETS}/...`` or
``${RIGMIX_CORPUS}/...``, so a config written anywhere composes on any machine.
:func:`ci_slice` picks the fixed slice the CI tests compose.

No joint or character is named here: every choice comes from the body plan.

Roles, from the classifier's counts of limbs
---------------------------------------------
* *humanoid*: arms, one pair of legs, no tail (Knight, CesiumMan, RiggedFigure,
  PlatformerCharacter, CyberpunkCharacter, Adventurer, Witch);
* *walker*: one pair of legs and nothing else paired, no tail (the robots EnemyLarge,
  EnemyTwoLegs, Leela);
* *quadruped*: two pairs of legs or more (the four-legged animals and dinosaurs, the Wasp);
* *tailed*: legs and a tail (the quadrupeds with tails, the two-legged dinosaurs);
* *donors* of a tail or of wings: any character with one.

Joints, from the skeleton
-------------------------
* *pelvis*: where the leg roots meet (where a tail is grafted; :attr:`Subject.pelvis`);
* *chest*: the lowest common ancestor of the arm and head roots;
* *waist*: the joint above the chest on the path from the pelvis (the root of a centaur's upper
  body: the chest alone would leave the belly behind, the pelvis would bring the hips);
* *shoulder*: the lowest common ancestor of the arm pair, else of the front leg pair (where wings
  go); the front leg of a side is the one whose root lies nearest the head's root.

Kinds (the order of the matrix)
-------------------------------
``identity``: every limb (head, tail, arms, legs, wings, other) of every character replaced by
itself: one file under two ids, the exact answer is the input. ``mirror``: every limb of a
mirror pair replaced by its partner, taken from the character mirrored (``mirror = true``,
unit scale). ``arm_swap``: the left arm of humanoid A replaced by humanoid B's, for every
unordered pair (21). ``leg_swap``: every walker with every humanoid (the humanoid is the body
for an even pair index, the walker otherwise), the walkers among themselves, and a ring over the
other legged characters (front left leg of each replaced by the next one's). ``head_swap``: a
ring over every character with a head and at least one other limb. ``torso``: a humanoid upper
body (waist up) replacing the head of every quadruped and tailed character (humanoids in turn).
``tail``: every tail attached at the pelvis of a humanoid (in turn). ``wings``: both wings of a
winged character attached at the shoulder of every humanoid and wingless quadruped (donors in
turn), each wing root kept as a joint of its own (``keep_joint``: the two wings keep their
spacing and flap by their own joints). ``three``: for each humanoid, the head of a quadruped (in
turn) and the left arm of the next humanoid. Cross-character donors have ``scale = "auto"``.

A limb is replaced with its detached parts (:func:`limb_actions`: the IK feet that carry a foot's
skin from the armature root are replaced by the donor's, or removed).
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from conftest import ASSETS, CHARACTERS, CORPUS, CORPUS_CHARACTERS  # noqa: E402

from rigmix.errors import InputError  # noqa: E402
from rigmix.limbs import BodyPlan, Limb, classify_limbs  # noqa: E402

__all__ = ["Case", "Subject", "KINDS", "load_subjects", "generate_matrix", "ci_slice", "write_configs",
           "limb_actions", "config_text", "character_files"]

#: the kinds of composition, in matrix order
KINDS = ("identity", "mirror", "arm_swap", "leg_swap", "head_swap", "torso", "tail", "wings", "three")

#: the CI slice holds at least this many cases
CI_SLICE_SIZE = 12


@dataclass(frozen=True)
class Case:
    """One composition of the matrix.

    Attributes
    ----------
    name : str
        Unique, file-name safe: ``<kind>__<body>__<detail>``.
    kind : str
        One of :data:`KINDS`.
    config : str
        The TOML config; character paths are ``${RIGMIX_ASSETS}/...`` or ``${RIGMIX_CORPUS}/...``.
    characters : tuple of str
        The characters it uses (body first), each once.
    """

    name: str
    kind: str
    config: str
    characters: tuple[str, ...]

    @property
    def sha(self) -> str:
        """SHA-256 of the config text (what a resumed run compares)."""
        return hashlib.sha256(self.config.encode()).hexdigest()


@dataclass(frozen=True)
class Subject:
    """One character as the generator reads it.

    Attributes
    ----------
    name : str
    path : str
        ``${RIGMIX_ASSETS}/<file>`` or ``${RIGMIX_CORPUS}/<file>``.
    plan : BodyPlan
    names : tuple of str, (J,)
        Joint names, in the file's joint order.
    parents : (J,) int array
        Parent joint, ``-1`` for a root.
    positions : (J, 3) float array
        Rest world positions of the joints, in the file's units.
    mirrored : tuple of str, (J,)
        Joint names of the character mirrored (:func:`rigmix.operations.mirror.mirror_character`),
        by joint index: what a ``mirror = true`` config names.
    """

    name: str
    path: str
    plan: BodyPlan
    names: tuple[str, ...]
    parents: np.ndarray
    positions: np.ndarray
    mirrored: tuple[str, ...]

    def limbs(self, kind: str, side: str | None = None) -> tuple[Limb, ...]:
        """Limbs of one kind (and side), in the classifier's order."""
        return tuple(lb for lb in self.plan.of_kind(kind) if side is None or lb.side == side)

    def detached_tops(self, limb: Limb) -> list[str]:
        """The top joints of ``limb``'s detached parts (those whose parent is not detached too)."""
        parts = set(limb.detached)
        return [j for j in limb.detached
                if self.parents[self.names.index(j)] < 0 or self.names[self.parents[self.names.index(j)]] not in parts]

    def count(self, kind: str) -> int:
        return len(self.plan.of_kind(kind))

    def ancestors(self, joint: str) -> list[str]:
        """``joint`` and its ancestors, root first."""
        out, j = [], self.names.index(joint)
        while j >= 0:
            out.append(self.names[j])
            j = int(self.parents[j])
        return out[::-1]

    def lca(self, joints) -> str:
        """Lowest common ancestor of ``joints`` (names; one joint is its own)."""
        paths = [self.ancestors(j) for j in joints]
        common = None
        for level in zip(*paths):
            if len(set(level)) > 1:
                break
            common = level[0]
        if common is None:
            raise InputError(f"corpus: {self.name}: joints {list(joints)} share no root")
        return common

    @property
    def head(self) -> Limb | None:
        heads = self.limbs("head")
        return heads[0] if heads else None

    @property
    def pelvis(self) -> str:
        """Where the legs meet (a tail is attached there): the lowest common ancestor of the leg
        roots, or the first joint below it on the way to the chest that lies among them (no
        farther from their midpoint than they are apart). An armature root on the floor is the
        legs' common ancestor in some rigs, and a tail grafted there comes out between the feet."""
        roots = [lb.root for lb in self.limbs("leg")]
        lca = self.lca(roots)
        R = self.positions[[self.names.index(j) for j in roots]]
        mid = R.mean(axis=0)
        spread = float(np.linalg.norm(R[:, None] - R[None], axis=2).max())
        path = [lca]
        if self.limbs("arm") and self.head is not None:
            up = self.ancestors(self.chest)
            path = up[up.index(lca):-1] if lca in up else path  # the chest is no pelvis
        for j in path:
            if np.linalg.norm(self.positions[self.names.index(j)] - mid) <= spread:
                return j
        return lca

    @property
    def chest(self) -> str:
        """Where the arms and the head meet."""
        return self.lca([lb.root for lb in self.limbs("arm")] + [self.head.root])

    @property
    def waist(self) -> str:
        """Root of the upper body: the joint above the chest, below the pelvis when the path allows."""
        path = self.ancestors(self.chest)
        below = path[path.index(self.pelvis) + 1:] if self.pelvis in path else path[-1:]
        return below[-2] if len(below) >= 2 else below[-1]

    def front_leg(self, side: str = "L") -> Limb:
        """The leg of ``side`` whose root lies nearest the head's root (the first one without a head)."""
        legs = self.limbs("leg", side)
        if self.head is None:
            return legs[0]
        h = self.positions[self.names.index(self.head.root)]
        return min(legs, key=lambda lb: float(np.linalg.norm(self.positions[self.names.index(lb.root)] - h)))

    @property
    def shoulder(self) -> str:
        """Where the arm pair (else the front leg pair) hangs: wings are attached there."""
        if self.limbs("arm"):
            return self.lca([lb.root for lb in self.limbs("arm")])
        front = self.front_leg("L")
        return self.lca([front.root, front.partner])

    # roles

    @property
    def humanoid(self) -> bool:
        return self.count("arm") >= 2 and self.count("leg") == 2 and not self.count("tail")

    @property
    def walker(self) -> bool:
        return self.count("leg") == 2 and not (self.count("arm") or self.count("wing") or self.count("tail"))

    @property
    def quadruped(self) -> bool:
        return self.count("leg") >= 4

    @property
    def tailed(self) -> bool:
        return self.count("leg") >= 2 and self.count("tail") >= 1


# --------------------------------------------------------------------------- characters


def character_files() -> dict[str, tuple[str, Path]]:
    """name -> (config path with its variable, file on this machine), every character sorted by name."""
    out = {}
    for var, folder, table in (("RIGMIX_ASSETS", ASSETS, CHARACTERS), ("RIGMIX_CORPUS", CORPUS, CORPUS_CHARACTERS)):
        for name, rel in table.items():
            out[name] = (f"${{{var}}}/{rel}", folder / rel)
    return dict(sorted(out.items()))


def load_subjects(names=None) -> list[Subject]:
    """Read and classify characters (default: all 27), sorted by name.

    Raises
    ------
    InputError
        A file is missing, naming it and the variable that locates its folder.
    """
    from rigmix.io import load_character
    from rigmix.operations.mirror import mirror_character

    files = character_files()
    names = sorted(names) if names is not None else list(files)
    missing = [n for n in names if not files[n][1].is_file()]
    if missing:
        raise InputError(f"corpus: {len(missing)} characters missing ({', '.join(missing)}; first: "
                         f"{files[missing[0]][1]}): set RIGMIX_ASSETS to the shared characters folder "
                         f"(now {ASSETS}) and RIGMIX_CORPUS to the corpus folder (now {CORPUS})")
    out = []
    for name in names:
        ch = load_character(files[name][1])
        sk = ch.skeleton
        out.append(Subject(name, files[name][0], classify_limbs(ch), tuple(sk.names), np.asarray(sk.parents),
                           sk.rest_worlds()[:, :3, 3], tuple(mirror_character(ch).skeleton.names)))
    return out


# --------------------------------------------------------------------------- configs


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v))
    return json.dumps(v)  # a JSON string is a TOML basic string


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)


def config_text(name: str, comment: str, characters: dict, actions: list[dict]) -> str:
    """A composition config as TOML: ``characters`` id -> (Subject, options), actions as dicts."""
    lines = [f"# {comment}", "# generated by benchmarks/corpus_matrix.py", f"name = {_value(name)}", ""]
    for cid, (subject, options) in characters.items():
        lines.append(f"[characters.{cid}]")
        lines.append(f"path = {_value(subject.path)}")
        lines += [f"{k} = {_value(v)}" for k, v in options.items()]
        lines.append("")
    for action in actions:
        lines.append("[[actions]]")
        lines += [f"{k} = {_value(v)}" for k, v in action.items()]
        lines.append("")
    return "\n".join(lines)


def _case(kind, detail, comment, characters, actions) -> Case:
    body = next(iter(characters.values()))[0].name
    name = _slug(f"{kind}__{body}__{detail}")
    used = tuple(dict.fromkeys(s.name for s, _ in characters.values()))
    return Case(name, kind, config_text(name, comment, characters, actions), used)


def _replace(source, source_joint, target, target_joint) -> dict:
    return {"op": "replace", "source": source, "source_joint": source_joint, "target": target,
            "target_joint": target_joint, "mode": "blend"}


def limb_actions(body: Subject, limb: Limb, donor_id: str, donor: Subject, donor_limb: Limb, *,
                 mirrored: bool = False) -> list[dict]:
    """The actions replacing ``limb`` of the body (id ``"body"``) by ``donor_limb`` of ``donor``.

    A limb is its root's subtree and its detached parts (:attr:`rigmix.limbs.Limb.detached`: an IK
    foot carrying the foot's skin from the armature root): each detached part of the body is
    replaced by the donor's part of the same rank, or removed when the donor has none left (the
    body's foot would stay where the old leg stood); a donor part with no body part to replace is
    left out. ``mirrored``: the donor is listed with ``mirror = true``, so its joints are named as
    mirrored (:attr:`Subject.mirrored`).
    """
    def named(joint):
        return donor.mirrored[donor.names.index(joint)] if mirrored else joint

    out = [_replace(donor_id, named(donor_limb.root), "body", limb.root)]
    ours, theirs = body.detached_tops(limb), donor.detached_tops(donor_limb)
    out += [_replace(donor_id, named(d), "body", b) for b, d in zip(ours, theirs)]
    out += [{"op": "remove", "target": "body", "target_joint": b} for b in ours[len(theirs):]]
    return out


def _attach(source, source_joint, target, target_joint, *, keep_joint=False) -> dict:
    out = {"op": "attach", "source": source, "source_joint": source_joint, "target": target,
           "target_joint": target_joint}
    return out | {"keep_joint": True} if keep_joint else out


AUTO = {"scale": "auto"}


# --------------------------------------------------------------------------- kinds


def identity_cases(subjects) -> list[Case]:
    out = []
    for s in subjects:
        for lb in s.plan.limbs:
            out.append(_case("identity", lb.root, f"{s.name}: {lb.label} ({lb.root}) replaced by itself",
                             {"body": (s, {}), "donor": (s, {})}, limb_actions(s, lb, "donor", s, lb)))
    return out


def mirror_cases(subjects) -> list[Case]:
    out = []
    for s in subjects:
        for lb in s.plan.limbs:
            if lb.partner is None:
                continue
            out.append(_case("mirror", lb.root,
                             f"{s.name}: {lb.label} ({lb.root}) replaced by its partner {lb.partner}, mirrored",
                             {"body": (s, {}), "mirror": (s, {"mirror": True, "scale": 1.0})},
                             limb_actions(s, lb, "mirror", s, s.plan.limb(lb.partner), mirrored=True)))
    return out


def arm_swap_cases(subjects) -> list[Case]:
    humanoids = [s for s in subjects if s.humanoid]
    out = []
    for a, b in combinations(humanoids, 2):
        arm, donor = a.limbs("arm", "L")[0], b.limbs("arm", "L")[0]
        out.append(_case("arm_swap", b.name, f"{a.name}'s left arm replaced by {b.name}'s",
                         {"body": (a, {}), "donor": (b, AUTO)}, limb_actions(a, arm, "donor", b, donor)))
    return out


def leg_swap_case(a: Subject, b: Subject, leg: Limb, donor: Limb, what: str) -> Case:
    """``a``'s ``leg`` replaced by ``b``'s ``donor`` limb (``what`` names it in the config's comment)."""
    return _case("leg_swap", b.name, f"{a.name}'s {what} replaced by {b.name}'s",
                 {"body": (a, {}), "donor": (b, AUTO)}, limb_actions(a, leg, "donor", b, donor))


def leg_swap_cases(subjects) -> list[Case]:
    humanoids = [s for s in subjects if s.humanoid]
    walkers = [s for s in subjects if s.walker]
    out = []
    for i, (w, h) in enumerate((w, h) for w in walkers for h in humanoids):
        a, b = (h, w) if i % 2 == 0 else (w, h)
        out.append(leg_swap_case(a, b, a.limbs("leg", "L")[0], b.limbs("leg", "L")[0], "left leg"))
    for a, b in combinations(walkers, 2):
        out.append(leg_swap_case(a, b, a.limbs("leg", "L")[0], b.limbs("leg", "L")[0], "left leg"))
    others = [s for s in subjects if s.limbs("leg") and not (s.humanoid or s.walker)]
    for a, b in zip(others, others[1:] + others[:1]):
        out.append(leg_swap_case(a, b, a.front_leg("L"), b.front_leg("L"), "front left leg"))
    return out


def head_swap_cases(subjects) -> list[Case]:
    ring = [s for s in subjects if s.head is not None and len(s.plan.limbs) >= 2]
    return [_case("head_swap", b.name, f"{a.name}'s head replaced by {b.name}'s",
                  {"body": (a, {}), "donor": (b, AUTO)}, limb_actions(a, a.head, "donor", b, b.head))
            for a, b in zip(ring, ring[1:] + ring[:1])]


def torso_cases(subjects) -> list[Case]:
    humanoids = [s for s in subjects if s.humanoid]
    bodies = [s for s in subjects if (s.quadruped or s.tailed) and not s.humanoid and s.head is not None]
    out = []
    for i, a in enumerate(bodies):
        h = humanoids[i % len(humanoids)]
        out.append(_case("torso", h.name, f"{h.name}'s upper body ({h.waist} up) replacing {a.name}'s head",
                         {"body": (a, {}), "rider": (h, AUTO)},
                         [_replace("rider", h.waist, "body", a.head.root)]
                         + [{"op": "remove", "target": "body", "target_joint": j} for j in a.detached_tops(a.head)]))
    return out


def tail_cases(subjects) -> list[Case]:
    humanoids = [s for s in subjects if s.humanoid]
    donors = [s for s in subjects if s.limbs("tail")]
    out = []
    for i, d in enumerate(donors):
        h = humanoids[i % len(humanoids)]
        tail = d.limbs("tail")[0]
        out.append(_case("tail", d.name, f"{d.name}'s tail attached at {h.name}'s pelvis",
                         {"body": (h, {}), "donor": (d, AUTO)}, [_attach("donor", tail.root, "body", h.pelvis)]))
    return out


def wings_cases(subjects) -> list[Case]:
    donors = [s for s in subjects if s.limbs("wing", "L") and s.limbs("wing", "R")]
    bodies = [s for s in subjects if (s.humanoid or s.quadruped) and not s.limbs("wing")]
    out = []
    for i, a in enumerate(bodies):
        d = donors[i % len(donors)]
        wings = (d.limbs("wing", "L")[0], d.limbs("wing", "R")[0])
        out.append(_case("wings", d.name, f"{d.name}'s wings attached at {a.name}'s shoulders",
                         {"body": (a, {}), "donor": (d, AUTO)},
                         [_attach("donor", w.root, "body", a.shoulder, keep_joint=True) for w in wings]))
    return out


def three_cases(subjects) -> list[Case]:
    humanoids = [s for s in subjects if s.humanoid]
    heads = [s for s in subjects if s.quadruped and s.head is not None and not s.limbs("wing")]
    out = []
    for i, a in enumerate(humanoids):
        q, b = heads[i % len(heads)], humanoids[(i + 1) % len(humanoids)]
        out.append(_case("three", f"{q.name}__{b.name}", f"{a.name} with {q.name}'s head and {b.name}'s left arm",
                         {"body": (a, {}), "head": (q, AUTO), "arm": (b, AUTO)},
                         limb_actions(a, a.head, "head", q, q.head)
                         + limb_actions(a, a.limbs("arm", "L")[0], "arm", b, b.limbs("arm", "L")[0])))
    return out


GENERATORS = {"identity": identity_cases, "mirror": mirror_cases, "arm_swap": arm_swap_cases,
              "leg_swap": leg_swap_cases, "head_swap": head_swap_cases, "torso": torso_cases,
              "tail": tail_cases, "wings": wings_cases, "three": three_cases}


def generate_matrix(subjects) -> list[Case]:
    """Every case of every kind, in :data:`KINDS` order, then by body character name.

    Parameters
    ----------
    subjects : iterable of Subject
        :func:`load_subjects`; sorted by name here, so the order of the argument does not matter.

    Returns
    -------
    list of Case
        Deterministic: the same characters give the same names, configs and order.
    """
    subjects = sorted(subjects, key=lambda s: s.name)
    cases = [c for kind in KINDS for c in GENERATORS[kind](subjects)]
    names = [c.name for c in cases]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise AssertionError(f"corpus: duplicate case names {dup}")
    return cases


def ci_slice(cases, size: int = CI_SLICE_SIZE) -> list[Case]:
    """A fixed slice of at least ``size`` cases covering every kind present, in matrix order.

    Round-robin over the kinds; within a kind, the next case taken is the first (in matrix order)
    that brings the most characters the slice does not hold yet, so the slice spreads over the
    corpus. Deterministic for a given matrix.
    """
    by_kind = {k: [c for c in cases if c.kind == k] for k in KINDS}
    by_kind = {k: v for k, v in by_kind.items() if v}
    picked, seen = [], set()

    def done():
        return len(picked) >= size and by_kind.keys() <= {c.kind for c in picked}

    while not done():
        left = {k: [c for c in pool if c not in picked] for k, pool in by_kind.items()}
        if not any(left.values()):
            break
        for kind, pool in left.items():
            if pool and not done():
                best = max(pool, key=lambda c: len(set(c.characters) - seen))  # max keeps the first of ties
                picked.append(best)
                seen.update(best.characters)
    order = {c.name: i for i, c in enumerate(cases)}
    return sorted(picked, key=lambda c: order[c.name])


def write_configs(cases, folder: Path) -> dict[str, Path]:
    """Write each case's config as ``folder/<name>.toml`` (unchanged files are not rewritten)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for c in cases:
        p = folder / f"{c.name}.toml"
        if not p.is_file() or p.read_text() != c.config:
            p.write_text(c.config)
        out[c.name] = p
    return out
