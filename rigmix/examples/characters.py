"""Built-in example characters, generated procedurally (no third-party assets).

Each example is a rigged, skinned, animated :class:`rigmix.character.Character` built from a
body plan (:mod:`rigmix.examples.bodyplan`): joints with rest world positions and signed-distance
primitives (round cones, ellipsoids) owned by the joints. The surface is **one closed,
2-manifold, genus-0, consistently outward-oriented triangle mesh** (a single welded connected
component, the zero set of the primitives' smooth union), with smooth distance-based skin
weights (at most 4 influences), field-gradient normals, planar UVs (front view for the
humanoid, side view for the quadruped: no seam), vertex colours and one white material (so
``COLOR_0`` shows). Rest rotations are identity; clips are ``LINEAR`` rotation tracks (plus a
``LINEAR`` translation track on ``Hips`` for the body bob) keyed at 30 fps over one loop (the
last key equals the first).

Everything is deterministic: two calls give identical arrays. Sizes are metres, +Y up,
facing +Z (the character's left is +X), feet on ``y = 0``.
"""

from __future__ import annotations

import logging

import numpy as np

from ..character import Character, Clip, Material, Mesh, Prop, Skeleton, Track
from ..transforms import quat_multiply
from .bodyplan import build_character, cone, ellipsoid

__all__ = ["humanoid", "quadruped", "static_box", "HUMANOID_JOINTS", "QUADRUPED_JOINTS"]

logger = logging.getLogger(__name__)

_FPS = 30.0


# --------------------------------------------------------------------------------------------
# Animation helpers
# --------------------------------------------------------------------------------------------


def _axis_angle(axis, angle):
    """Quaternions ``(k, 4)`` xyzw for rotations of ``angle`` ``(k,)`` radians about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle, dtype=np.float64)
    half = 0.5 * angle[..., None]
    return np.concatenate([np.sin(half) * axis, np.cos(half)], axis=-1)


def _euler(t, *, x=0.0, y=0.0, z=0.0):
    """``R_z(z) @ R_y(y) @ R_x(x)`` as quaternions ``(k, 4)``; angles scalars or ``(k,)`` arrays."""
    k = len(t)
    qx = _axis_angle([1, 0, 0], np.broadcast_to(x, (k,)))
    qy = _axis_angle([0, 1, 0], np.broadcast_to(y, (k,)))
    qz = _axis_angle([0, 0, 1], np.broadcast_to(z, (k,)))
    return quat_multiply(qz, quat_multiply(qy, qx))


def _key_times(duration):
    return np.linspace(0.0, duration, int(round(duration * _FPS)) + 1)


def _wave(t, period, phase=0.0):
    """``sin(2 pi (t / period + phase))``, exactly periodic over the clip."""
    return np.sin(2.0 * np.pi * (t / period + phase))


def _lift(t, period, phase=0.0):
    """A smooth bump in [0, 1] during half of each cycle (the swing phase of a leg)."""
    return np.maximum(0.0, _wave(t, period, phase)) ** 1.5


def _rot_track(skeleton, joint, t, q):
    # keep consecutive keys in one hemisphere, so LINEAR slerp takes the short way everywhere
    q = np.array(q, dtype=np.float64)
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return Track(skeleton.index(joint), "rotation", t, q, "LINEAR")


def _trans_track(skeleton, joint, t, offset):
    rest = skeleton.translations[skeleton.index(joint)]
    return Track(skeleton.index(joint), "translation", t, rest + offset, "LINEAR")


# --------------------------------------------------------------------------------------------
# Humanoid
# --------------------------------------------------------------------------------------------

#: Joint names of :func:`humanoid`, in topological order.
HUMANOID_JOINTS = (
    "Hips", "Spine", "Chest", "Neck", "Head",
    "Shoulder.L", "UpperArm.L", "LowerArm.L", "Hand.L",
    "Shoulder.R", "UpperArm.R", "LowerArm.R", "Hand.R",
    "UpperLeg.L", "LowerLeg.L", "Foot.L",
    "UpperLeg.R", "LowerLeg.R", "Foot.R",
)

_SKIN = (0.80, 0.52, 0.38)
_SHIRT = (0.12, 0.28, 0.62)
_TROUSERS = (0.16, 0.16, 0.20)
_SHOES = (0.30, 0.16, 0.07)


def _humanoid_plan():
    joints = [
        ("Hips", None, (0.0, 0.95, 0.0)),
        ("Spine", "Hips", (0.0, 1.07, 0.0)),
        ("Chest", "Spine", (0.0, 1.24, 0.0)),
        ("Neck", "Chest", (0.0, 1.49, 0.0)),
        ("Head", "Neck", (0.0, 1.59, 0.0)),
    ]
    shapes = [
        ellipsoid("Hips", (0.0, 0.95, 0.0), (0.165, 0.11, 0.115), _TROUSERS, 0.03),
        ellipsoid("Spine", (0.0, 1.12, 0.0), (0.145, 0.13, 0.1), _SHIRT, 0.05),
        ellipsoid("Chest", (0.0, 1.33, 0.0), (0.175, 0.155, 0.11), _SHIRT, 0.05),
        cone("Neck", (0.0, 1.44, -0.005), (0.0, 1.62, 0.0), 0.055, 0.05, _SKIN, 0.03),
        ellipsoid("Head", (0.0, 1.695, 0.012), (0.085, 0.108, 0.098), _SKIN, 0.03),
        ellipsoid("Head", (0.0, 1.685, 0.108), (0.014, 0.024, 0.02), _SKIN, 0.012),  # nose
    ]
    for side, sx in (("L", 1.0), ("R", -1.0)):
        def p(x, y, z):
            return (sx * x, y, z)

        joints += [
            (f"Shoulder.{side}", "Chest", p(0.03, 1.43, 0.0)),
            (f"UpperArm.{side}", f"Shoulder.{side}", p(0.18, 1.44, 0.0)),
            (f"LowerArm.{side}", f"UpperArm.{side}", p(0.45, 1.44, -0.01)),
            (f"Hand.{side}", f"LowerArm.{side}", p(0.71, 1.44, 0.0)),
        ]
        shapes += [
            cone(f"Shoulder.{side}", p(0.05, 1.42, 0.0), p(0.18, 1.44, 0.0), 0.06, 0.058, _SHIRT, 0.04),
            cone(f"UpperArm.{side}", p(0.18, 1.44, 0.0), p(0.45, 1.44, -0.01), 0.054, 0.042, _SHIRT, 0.02),
            cone(f"LowerArm.{side}", p(0.45, 1.44, -0.01), p(0.71, 1.44, 0.0), 0.041, 0.03, _SKIN, 0.02),
            ellipsoid(f"Hand.{side}", p(0.79, 1.438, 0.0), (0.075, 0.022, 0.045), _SKIN, 0.02),
            cone(f"Hand.{side}", p(0.73, 1.436, 0.03), p(0.78, 1.43, 0.075), 0.015, 0.012, _SKIN, 0.012),
        ]
    for side, sx in (("L", 1.0), ("R", -1.0)):
        def p(x, y, z):
            return (sx * x, y, z)

        joints += [
            (f"UpperLeg.{side}", "Hips", p(0.095, 0.91, 0.0)),
            (f"LowerLeg.{side}", f"UpperLeg.{side}", p(0.1, 0.5, 0.01)),
            (f"Foot.{side}", f"LowerLeg.{side}", p(0.1, 0.085, -0.01)),
        ]
        shapes += [
            cone(f"UpperLeg.{side}", p(0.095, 0.92, 0.0), p(0.1, 0.5, 0.01), 0.085, 0.053, _TROUSERS, 0.025),
            cone(f"LowerLeg.{side}", p(0.1, 0.5, 0.01), p(0.1, 0.1, -0.01), 0.051, 0.036, _TROUSERS, 0.02),
            cone(f"Foot.{side}", p(0.1, 0.045, -0.03), p(0.1, 0.03, 0.16), 0.045, 0.03, _SHOES, 0.03),
        ]
    return joints, shapes


def _humanoid_clips(sk):
    return [_humanoid_walk(sk), _humanoid_idle(sk)]


#: Arms hang down from the T pose by this angle in the clips (radians).
_ARM_DOWN = np.radians(72.0)


def _arm(t, down, swing):
    """Upper arm rotation: lowered from the T pose about Z, then swung forward about X."""
    return quat_multiply(_euler(t, x=swing), _euler(t, z=down))


def _humanoid_walk(sk, period=1.0):
    """A walk cycle in place: legs swing, knees bend in the swing phase, arms swing opposite."""
    t = _key_times(period)
    tracks = [
        # the body is highest when passing over the standing leg: twice per cycle
        _trans_track(sk, "Hips", t, np.stack([0.0 * t, 0.018 * np.cos(4 * np.pi * t / period) - 0.012,
                                              0.0 * t], axis=1)),
        _rot_track(sk, "Hips", t, _euler(t, y=np.radians(6) * _wave(t, period), x=np.radians(3))),
        _rot_track(sk, "Spine", t, _euler(t, y=-np.radians(4) * _wave(t, period))),
        _rot_track(sk, "Chest", t, _euler(t, y=-np.radians(5) * _wave(t, period), x=np.radians(2))),
        _rot_track(sk, "Head", t, _euler(t, y=np.radians(3) * _wave(t, period), x=-np.radians(4))),
    ]
    for side, sx, phase in (("L", 1.0, 0.0), ("R", -1.0, 0.5)):
        swing = _wave(t, period, phase)  # +1: this leg forward
        tracks += [
            # negative rotation about +X swings a downward limb forward (+Z)
            _rot_track(sk, f"UpperLeg.{side}", t, _euler(t, x=-np.radians(26) * swing)),
            _rot_track(sk, f"LowerLeg.{side}", t,
                       _euler(t, x=np.radians(8) + np.radians(45) * _lift(t, period, phase + 0.22))),
            _rot_track(sk, f"Foot.{side}", t, _euler(t, x=np.radians(12) * _wave(t, period, phase - 0.15))),
            # arm hangs down (rotation about Z), then swings opposite to the leg of its side
            _rot_track(sk, f"UpperArm.{side}", t,
                       _arm(t, -sx * _ARM_DOWN, np.radians(22) * swing)),
            _rot_track(sk, f"LowerArm.{side}", t,
                       _euler(t, y=-sx * (np.radians(18) + np.radians(12) * np.maximum(0, -swing)))),
        ]
    return Clip("walk", tracks)


def _humanoid_idle(sk, period=3.0):
    """Idle: slow breathing in the chest, a slight weight shift and the head looking around."""
    t = _key_times(period)
    breath = _wave(t, period / 2)  # two breaths per loop
    tracks = [
        _trans_track(sk, "Hips", t, np.stack([0.012 * _wave(t, period), 0.004 * breath, 0 * t], axis=1)),
        _rot_track(sk, "Hips", t, _euler(t, z=np.radians(2) * _wave(t, period))),
        _rot_track(sk, "Spine", t, _euler(t, x=-np.radians(1.0) * breath, z=-np.radians(2) * _wave(t, period))),
        _rot_track(sk, "Chest", t, _euler(t, x=-np.radians(1.5) * breath)),
        _rot_track(sk, "Neck", t, _euler(t, x=np.radians(2) * breath)),
        _rot_track(sk, "Head", t, _euler(t, y=np.radians(14) * _wave(t, period, 0.1),
                                         x=np.radians(4) * _wave(t, period, 0.35))),
    ]
    for side, sx in (("L", 1.0), ("R", -1.0)):
        tracks += [
            _rot_track(sk, f"Shoulder.{side}", t, _euler(t, z=sx * np.radians(2.5) * breath)),
            _rot_track(sk, f"UpperArm.{side}", t,
                       _arm(t, -sx * (_ARM_DOWN + np.radians(2) * breath), np.radians(3))),
            _rot_track(sk, f"LowerArm.{side}", t, _euler(t, y=-sx * np.radians(12))),
            _rot_track(sk, f"UpperLeg.{side}", t, _euler(t, z=-np.radians(2) * _wave(t, period))),
        ]
    return Clip("idle", tracks)


def humanoid() -> Character:
    """A procedural humanoid, about 1.8 m tall, in T pose.

    Joints (:data:`HUMANOID_JOINTS`): ``Hips`` (root) > ``Spine`` > ``Chest`` > ``Neck`` >
    ``Head``; ``Chest`` > ``Shoulder.L`` > ``UpperArm.L`` > ``LowerArm.L`` > ``Hand.L`` (and
    ``.R``); ``Hips`` > ``UpperLeg.L`` > ``LowerLeg.L`` > ``Foot.L`` (and ``.R``).
    Clips: ``walk`` (1 s loop) and ``idle`` (3 s loop).

    Returns
    -------
    Character
        One skinned mesh (closed, manifold, one component, about 7,000 triangles), one
        material, two clips. Deterministic.
    """
    joints, shapes = _humanoid_plan()
    return build_character("Humanoid", joints, shapes, _humanoid_clips,
                  voxel=0.01, edge=0.022, sigma=0.025, uv_axes=(0, 1))


# --------------------------------------------------------------------------------------------
# Quadruped
# --------------------------------------------------------------------------------------------

#: Joint names of :func:`quadruped`, in topological order.
QUADRUPED_JOINTS = (
    "Hips", "Spine", "Chest", "Neck", "Head",
    "Tail.1", "Tail.2", "Tail.3",
    "FrontUpperLeg.L", "FrontLowerLeg.L", "FrontFoot.L",
    "FrontUpperLeg.R", "FrontLowerLeg.R", "FrontFoot.R",
    "BackUpperLeg.L", "BackLowerLeg.L", "BackFoot.L",
    "BackUpperLeg.R", "BackLowerLeg.R", "BackFoot.R",
)

_FUR = (0.55, 0.33, 0.17)
_BELLY = (0.85, 0.74, 0.58)
_DARK = (0.12, 0.08, 0.06)


def _quadruped_plan():
    joints = [
        ("Hips", None, (0.0, 0.9, -0.5)),
        ("Spine", "Hips", (0.0, 0.92, -0.15)),
        ("Chest", "Spine", (0.0, 0.92, 0.25)),
        ("Neck", "Chest", (0.0, 0.98, 0.48)),
        ("Head", "Neck", (0.0, 1.16, 0.7)),
        ("Tail.1", "Hips", (0.0, 0.93, -0.8)),
        ("Tail.2", "Tail.1", (0.0, 0.87, -0.94)),
        ("Tail.3", "Tail.2", (0.0, 0.77, -1.03)),
    ]
    shapes = [
        ellipsoid("Hips", (0.0, 0.88, -0.48), (0.18, 0.2, 0.3), _FUR, 0.05),
        ellipsoid("Spine", (0.0, 0.86, -0.1), (0.175, 0.2, 0.3), _FUR, 0.08),
        ellipsoid("Chest", (0.0, 0.89, 0.27), (0.18, 0.23, 0.26), _FUR, 0.08),
        cone("Neck", (0.0, 0.94, 0.42), (0.0, 1.14, 0.7), 0.13, 0.075, _FUR, 0.05),
        ellipsoid("Head", (0.0, 1.19, 0.76), (0.09, 0.095, 0.12), _FUR, 0.04),
        cone("Head", (0.0, 1.17, 0.8), (0.0, 1.12, 0.99), 0.07, 0.042, _BELLY, 0.04),
        ellipsoid("Head", (0.0, 1.13, 1.02), (0.026, 0.02, 0.016), _DARK, 0.015),  # nose
        cone("Head", (0.055, 1.26, 0.71), (0.075, 1.35, 0.69), 0.035, 0.012, _DARK, 0.02),  # ears
        cone("Head", (-0.055, 1.26, 0.71), (-0.075, 1.35, 0.69), 0.035, 0.012, _DARK, 0.02),
        cone("Tail.1", (0.0, 0.93, -0.76), (0.0, 0.87, -0.94), 0.05, 0.042, _FUR, 0.03),
        cone("Tail.2", (0.0, 0.87, -0.94), (0.0, 0.77, -1.03), 0.042, 0.034, _FUR, 0.02),
        cone("Tail.3", (0.0, 0.77, -1.03), (0.0, 0.63, -1.08), 0.034, 0.02, _DARK, 0.02),
    ]
    legs = (
        ("Front", "Chest", 0.3, (0.02, 0.0, 0.06)),   # knee forward a bit, toes forward
        ("Back", "Hips", -0.5, (-0.12, 0.06, 0.06)),  # hock backward
    )
    for end, parent, z0, (dz_knee, dz_ankle, dz_toe) in legs:
        for side, sx in (("L", 1.0), ("R", -1.0)):
            hip = (sx * 0.13, 0.78, z0)
            knee = (sx * 0.13, 0.45, z0 + dz_knee)
            ankle = (sx * 0.13, 0.11, z0 + dz_ankle)
            toe = (sx * 0.13, 0.03, z0 + dz_ankle + dz_toe)
            joints += [
                (f"{end}UpperLeg.{side}", parent, hip),
                (f"{end}LowerLeg.{side}", f"{end}UpperLeg.{side}", knee),
                (f"{end}Foot.{side}", f"{end}LowerLeg.{side}", ankle),
            ]
            shapes += [
                cone(f"{end}UpperLeg.{side}", hip, knee, 0.085, 0.05, _FUR, 0.05),
                cone(f"{end}LowerLeg.{side}", knee, ankle, 0.048, 0.035, _FUR, 0.02),
                cone(f"{end}Foot.{side}", ankle, toe, 0.036, 0.032, _DARK, 0.02),
            ]
    # topological order: legs after their parents (Chest, Hips) - already true
    return joints, shapes


def _quadruped_gait(sk, name, period, phases, *, swing, knee, bob, tail):
    """A gait cycle: each leg swings with its own phase; knees lift in the swing phase."""
    t = _key_times(period)
    tracks = [
        _trans_track(sk, "Hips", t, np.stack([0 * t, bob * np.cos(4 * np.pi * t / period), 0 * t], axis=1)),
        _rot_track(sk, "Hips", t, _euler(t, x=np.radians(2) * _wave(t, period / 2))),
        _rot_track(sk, "Spine", t, _euler(t, y=np.radians(3) * _wave(t, period))),
        _rot_track(sk, "Chest", t, _euler(t, x=-np.radians(2) * _wave(t, period / 2, 0.25))),
        _rot_track(sk, "Neck", t, _euler(t, x=np.radians(4) * _wave(t, period / 2, 0.1))),
        _rot_track(sk, "Head", t, _euler(t, x=-np.radians(3) * _wave(t, period / 2, 0.1))),
        _rot_track(sk, "Tail.1", t, _euler(t, y=np.radians(tail) * _wave(t, period), x=np.radians(10))),
        _rot_track(sk, "Tail.2", t, _euler(t, y=np.radians(tail) * _wave(t, period, -0.1))),
        _rot_track(sk, "Tail.3", t, _euler(t, y=np.radians(tail) * _wave(t, period, -0.2))),
    ]
    for leg, phase in phases.items():
        s = _wave(t, period, phase)  # +1: foot forward
        lift = _lift(t, period, phase + 0.22)
        if leg.startswith("Front"):  # the knee folds backward: foot up and back
            lower = np.radians(knee) * lift
        else:  # the hock folds forward a little; the shin stays near vertical as the leg swings
            lower = 0.6 * np.radians(swing) * s - 0.3 * np.radians(knee) * lift
        tracks += [
            _rot_track(sk, f"{leg[:-2]}UpperLeg{leg[-2:]}", t, _euler(t, x=-np.radians(swing) * s)),
            _rot_track(sk, f"{leg[:-2]}LowerLeg{leg[-2:]}", t, _euler(t, x=lower)),
            _rot_track(sk, f"{leg[:-2]}Foot{leg[-2:]}", t,
                       _euler(t, x=np.radians(10) * _wave(t, period, phase - 0.15))),
        ]
    return Clip(name, tracks)


def _quadruped_idle(sk, period=4.0):
    """Idle: breathing, the head looking around, a lazy tail wag."""
    t = _key_times(period)
    breath = _wave(t, period / 2)
    tracks = [
        _trans_track(sk, "Hips", t, np.stack([0 * t, 0.004 * breath, 0 * t], axis=1)),
        _rot_track(sk, "Spine", t, _euler(t, x=np.radians(1.5) * breath)),
        _rot_track(sk, "Chest", t, _euler(t, x=-np.radians(2) * breath)),
        _rot_track(sk, "Neck", t,
                   _euler(t, y=np.radians(15) * _wave(t, period), x=np.radians(6) * _wave(t, period, 0.3))),
        _rot_track(sk, "Head", t,
                   _euler(t, y=np.radians(10) * _wave(t, period, 0.05), z=np.radians(5) * _wave(t, period / 2))),
        _rot_track(sk, "Tail.1", t, _euler(t, y=np.radians(15) * _wave(t, period / 4), x=np.radians(15))),
        _rot_track(sk, "Tail.2", t, _euler(t, y=np.radians(15) * _wave(t, period / 4, -0.1))),
        _rot_track(sk, "Tail.3", t, _euler(t, y=np.radians(15) * _wave(t, period / 4, -0.2))),
    ]
    return Clip("idle", tracks)


def _quadruped_clips(sk):
    # lateral-sequence walk: LH, LF, RH, RF a quarter cycle apart; trot: diagonal pairs together
    # keys: leg prefix + side ("Back.L" drives BackUpperLeg.L, BackLowerLeg.L, BackFoot.L)
    walk = {"Back.L": 0.0, "Front.L": 0.25, "Back.R": 0.5, "Front.R": 0.75}
    trot = {"Back.L": 0.0, "Front.R": 0.0, "Back.R": 0.5, "Front.L": 0.5}
    return [
        _quadruped_gait(sk, "walk", 1.2, walk, swing=22, knee=45, bob=0.01, tail=8),
        _quadruped_gait(sk, "trot", 0.6, trot, swing=30, knee=60, bob=0.02, tail=12),
        _quadruped_idle(sk),
    ]


def quadruped() -> Character:
    """A procedural quadruped (dog/horse-like), about 1.2 m tall (ears) and 2.1 m long.

    Joints (:data:`QUADRUPED_JOINTS`): ``Hips`` (root) > ``Spine`` > ``Chest`` > ``Neck`` >
    ``Head``; ``Hips`` > ``Tail.1`` > ``Tail.2`` > ``Tail.3``; ``Chest`` >
    ``FrontUpperLeg.L`` > ``FrontLowerLeg.L`` > ``FrontFoot.L`` (and ``.R``); ``Hips`` >
    ``BackUpperLeg.L`` > ``BackLowerLeg.L`` > ``BackFoot.L`` (and ``.R``).
    Clips: ``walk`` (1.2 s), ``trot`` (0.6 s) and ``idle`` (4 s), all loops.

    Returns
    -------
    Character
        One skinned mesh (closed, manifold, one component), one material, three clips.
    """
    joints, shapes = _quadruped_plan()
    joints = _topological(joints)
    return build_character("Quadruped", joints, shapes, _quadruped_clips,
                  voxel=0.012, edge=0.028, sigma=0.03, uv_axes=(2, 1))


def _topological(joints):
    """Reorder ``[(name, parent, pos)]`` so that parents come first (stable otherwise)."""
    done, out = set(), []
    pending = list(joints)
    while pending:
        rest = []
        for j in pending:
            if j[1] is None or j[1] in done:
                out.append(j)
                done.add(j[0])
            else:
                rest.append(j)
        if len(rest) == len(pending):
            raise ValueError(f"examples: joints with unknown parents: {[j[0] for j in rest]}")
        pending = rest
    return out


# --------------------------------------------------------------------------------------------
# Static box
# --------------------------------------------------------------------------------------------


def static_box(size=(0.5, 0.5, 0.5)) -> Character:
    """A static, unskinned box (no joints, no skin): for the "not a rigged character" paths.

    Parameters
    ----------
    size : (3,) float
        Edge lengths in metres; the box sits on ``y = 0``, centred in x and z.

    Returns
    -------
    Character
        Zero joints, no skinned mesh, one static :class:`~rigmix.character.Prop` (24 vertices
        split at the edges for flat normals, 12 triangles; closed after welding), one material.
    """
    half = 0.5 * np.asarray(size, dtype=np.float64).reshape(3)
    V, N, UV, F = [], [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u_ax, v_ax = [a for a in range(3) if a != axis]
            e_u, e_v = np.eye(3)[u_ax], np.eye(3)[v_ax]
            if np.dot(np.cross(e_u, e_v), n) < 0:  # make (u, v, n) right-handed: CCW outside
                e_u, e_v = e_v, e_u
            base = len(V)
            for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                V.append((n + cu * e_u + cv * e_v) * half + (0.0, half[1], 0.0))
                N.append(n)
                UV.append(((cu + 1) / 2, (1 - cv) / 2))
            F += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    mesh = Mesh(name="Box", positions=np.array(V), faces=np.array(F), normals=np.array(N),
                uvs=(np.array(UV),), material=0)
    skeleton = Skeleton(names=(), parents=np.zeros(0), translations=np.zeros((0, 3)),
                        rotations=np.zeros((0, 4)), scales=np.zeros((0, 3)),
                        inverse_binds=np.zeros((0, 4, 4)))
    material = Material(name="Box", base_color=(0.6, 0.6, 0.65, 1.0), metallic=0.0, roughness=0.8)
    return Character(name="Box", skeleton=skeleton, props=(Prop(mesh, -1, np.eye(4)),),
                     materials=(material,))
