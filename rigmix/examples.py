"""Built-in example characters, generated procedurally (no third-party assets).

Each example is a rigged, skinned, animated :class:`rigmix.character.Character` built from a
small *body plan*: a list of joints (name, parent, rest world position) and a list of shape
primitives (round cones and ellipsoids), each owned by one joint and carrying a colour.

* Surface: the primitives' signed distance fields are combined with a smooth minimum and the
  zero level set is extracted by marching cubes (scikit-image, Lewiner), then simplified and
  projected back onto the field. The result is **one closed, 2-manifold, genus-0, consistently
  outward-oriented triangle mesh** (a single connected component), checked by the tests.
* Skin weights: for each vertex and joint, ``d_j`` is the signed distance to that joint's own
  primitives; ``w_j = exp(-((d_j - min_k d_k) / sigma)^2)``, the 4 largest kept, small ones
  dropped, rows normalized. This gives a smooth blend over a few centimetres at every joint.
* Normals: the normalized gradient of the field at each vertex (smooth shading).
* UVs: a planar projection over the bounding box (front view for the humanoid, side view for
  the quadruped), so there is no seam. Vertex colours: the primitives' colours, blended by
  proximity. One material (white base colour, so ``COLOR_0`` shows).
* Skeleton: rest rotations are identity (joint frames aligned with the world), so rest local
  translations are differences of world positions and inverse binds are pure translations.
* Clips: ``LINEAR`` rotation tracks (plus a ``LINEAR`` translation track on ``Hips`` for the
  body bob), keyed at 30 fps over one loop (the last key equals the first).

Everything is deterministic: two calls give identical arrays. Sizes are metres, +Y up,
facing +Z (the character's left is +X), feet on ``y = 0``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .character import Character, Clip, Material, Mesh, Prop, Skeleton, Track
from .transforms import quat_multiply

__all__ = ["humanoid", "quadruped", "static_box", "HUMANOID_JOINTS", "QUADRUPED_JOINTS"]

logger = logging.getLogger(__name__)

_FPS = 30.0


# --------------------------------------------------------------------------------------------
# Signed distance primitives (vectorized over query points (n, 3))
# --------------------------------------------------------------------------------------------


def _sd_round_cone(P, a, b, ra, rb):
    """Exact signed distance to a round cone (spheres of radius ``ra`` at ``a``, ``rb`` at ``b``,
    joined by their common tangent cone), after Inigo Quilez.

    Parameters
    ----------
    P : (n, 3) float array
    a, b : (3,) float arrays
    ra, rb : float

    Returns
    -------
    (n,) float64, negative inside.
    """
    a = np.asarray(a, dtype=np.float64)
    ba = np.asarray(b, dtype=np.float64) - a
    l2 = float(ba @ ba)
    rr = ra - rb
    a2 = l2 - rr * rr
    il2 = 1.0 / l2
    pa = P - a
    y = pa @ ba
    z = y - l2
    x2 = np.sum((pa * l2 - y[:, None] * ba) ** 2, axis=1)
    y2 = y * y * l2
    z2 = z * z * l2
    k = np.sign(rr) * rr * rr * x2
    d_b = np.sqrt(x2 + z2) * il2 - rb
    d_a = np.sqrt(x2 + y2) * il2 - ra
    d_c = (np.sqrt(np.maximum(x2 * a2 * il2, 0.0)) + y * rr) * il2 - ra
    return np.where(np.sign(z) * a2 * z2 > k, d_b, np.where(np.sign(y) * a2 * y2 < k, d_a, d_c))


def _sd_ellipsoid(P, c, r):
    """Approximate signed distance to an axis-aligned ellipsoid (exact zero set), after Quilez.

    Parameters
    ----------
    P : (n, 3) float array
    c : (3,) centre
    r : (3,) semi-axes

    Returns
    -------
    (n,) float64, negative inside.
    """
    q = P - np.asarray(c, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    k0 = np.linalg.norm(q / r, axis=1)
    k1 = np.linalg.norm(q / (r * r), axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _smooth_min(a, b, k):
    """Polynomial smooth minimum of two distance arrays with blend radius ``k`` (metres)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


@dataclass(frozen=True)
class _Shape:
    """One primitive of a body plan.

    ``kind`` is ``"cone"`` (``a``, ``b``, ``ra``, ``rb``) or ``"ellipsoid"`` (centre ``a``,
    semi-axes ``b``); ``blend`` is its smooth-union radius; ``joint`` the joint it belongs to.
    """

    joint: str
    kind: str
    a: tuple
    b: tuple
    ra: float = 0.0
    rb: float = 0.0
    color: tuple = (0.8, 0.8, 0.8)
    blend: float = 0.02

    def sdf(self, P):
        if self.kind == "cone":
            return _sd_round_cone(P, self.a, self.b, self.ra, self.rb)
        return _sd_ellipsoid(P, self.a, self.b)


def _cone(joint, a, b, ra, rb, color, blend=0.02):
    return _Shape(joint, "cone", tuple(a), tuple(b), ra, rb, tuple(color), blend)


def _ellipsoid(joint, c, r, color, blend=0.02):
    return _Shape(joint, "ellipsoid", tuple(c), tuple(r), 0.0, 0.0, tuple(color), blend)


def _shape_distances(shapes, P):
    """Per-shape signed distances ``(S, n)`` and their smooth union ``(n,)``."""
    D = np.stack([s.sdf(P) for s in shapes])
    field = D[0]
    for s, d in zip(shapes[1:], D[1:]):
        field = _smooth_min(field, d, s.blend)
    return D, field


def _field(shapes, P):
    return _shape_distances(shapes, P)[1]


def _field_gradient(shapes, P, eps):
    """Central-difference gradient of the smooth-union field at ``P`` ``(n, 3)``."""
    G = np.empty_like(P)
    for axis in range(3):
        dp = np.zeros(3)
        dp[axis] = eps
        G[:, axis] = (_field(shapes, P + dp) - _field(shapes, P - dp)) / (2 * eps)
    return G


# --------------------------------------------------------------------------------------------
# Surface extraction
# --------------------------------------------------------------------------------------------


def _surface(shapes, *, voxel, edge):
    """Closed triangle mesh of the zero set of the shapes' smooth union.

    Parameters
    ----------
    shapes : sequence of _Shape
    voxel : float
        Marching cubes grid spacing (metres).
    edge : float
        Target edge length of the isotropic remeshing (metres); 0 keeps marching cubes' mesh.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64, counter-clockwise seen from outside.
    N : (n, 3) float64 unit normals (field gradient).
    """
    from skimage.measure import marching_cubes

    vol, mins = _field_grid(shapes, voxel)
    V, F, _, _ = marching_cubes(vol, level=0.0, spacing=(voxel, voxel, voxel))
    V = V + mins
    F = F.astype(np.int64)
    if _signed_volume(V, F) < 0:
        F = F[:, ::-1]
    if edge:
        V, F = _remesh(V, F, edge)
    # project back onto the zero set (two Newton steps) and take the field gradient as normal
    eps = voxel * 0.25
    for _ in range(2):
        G = _field_gradient(shapes, V, eps)
        g2 = np.maximum(np.sum(G * G, axis=1), 1e-12)
        V = V - (_field(shapes, V) / g2)[:, None] * G
    G = _field_gradient(shapes, V, eps)
    N = G / np.maximum(np.linalg.norm(G, axis=1, keepdims=True), 1e-12)
    return V, F, N


def _field_grid(shapes, voxel):
    """The smooth-union field sampled on a regular grid, each shape evaluated near itself only.

    A shape farther than ``margin`` (more than any blend radius) from a grid point cannot change
    the zero set or the sign there, so it counts as ``+margin`` (a large distance) there.

    Returns
    -------
    vol : (nx, ny, nz) float64
        Field values; ``vol[i, j, k]`` is at ``origin + voxel * (i, j, k)``.
    origin : (3,) float64
    """
    margin = max(s.blend for s in shapes) + 4 * voxel
    lo = np.min([_shape_bounds(s)[0] for s in shapes], axis=0) - 3 * voxel
    hi = np.max([_shape_bounds(s)[1] for s in shapes], axis=0) + 3 * voxel
    shape = tuple(int(n) for n in np.ceil((hi - lo) / voxel).astype(int) + 1)
    vol = np.full(shape, margin)
    for s in shapes:
        b_lo, b_hi = _shape_bounds(s)
        i0 = np.maximum(np.floor((b_lo - margin - lo) / voxel).astype(int), 0)
        i1 = np.minimum(np.ceil((b_hi + margin - lo) / voxel).astype(int) + 1, shape)
        axes = [lo[a] + voxel * np.arange(i0[a], i1[a]) for a in range(3)]
        P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        d = np.minimum(s.sdf(P), margin).reshape(tuple(i1 - i0))
        box = tuple(slice(i0[a], i1[a]) for a in range(3))
        vol[box] = _smooth_min(vol[box], d, s.blend)
    return vol, lo


def _remesh(V, F, edge):
    """Isotropic remeshing (Botsch and Kobbelt) to about ``edge`` metres, closed and manifold."""
    import gpytoolbox

    Vr, Fr = gpytoolbox.remesh_botsch(V, F.astype(np.int32), i=10, h=edge, project=True)
    Fr = np.asarray(Fr, dtype=np.int64)
    if not _is_closed_manifold(Fr):
        logger.debug("examples: remeshing broke manifoldness; keeping the marching cubes mesh")
        return V, F
    return np.asarray(Vr, dtype=np.float64), Fr


def _shape_bounds(s):
    if s.kind == "cone":
        a, b = np.array(s.a), np.array(s.b)
        r = max(s.ra, s.rb)
        return np.minimum(a, b) - r, np.maximum(a, b) + r
    c, r = np.array(s.a), np.array(s.b)
    return c - r, c + r


def _signed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


def _is_closed_manifold(F):
    """Every directed edge appears once and its opposite once (closed, oriented 2-manifold)."""
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    if len(np.unique(E, axis=0)) != len(E):
        return False
    fwd = {tuple(e) for e in E.tolist()}
    return all((b, a) in fwd for a, b in fwd)


# --------------------------------------------------------------------------------------------
# Body plan -> Character
# --------------------------------------------------------------------------------------------


def _skeleton(joints):
    """Skeleton from ``[(name, parent name or None, world position)]`` in topological order."""
    names = [j[0] for j in joints]
    parents = np.array([-1 if p is None else names.index(p) for _, p, _ in joints], dtype=np.int64)
    world = np.array([pos for _, _, pos in joints], dtype=np.float64)
    local = world - np.where(parents[:, None] >= 0, world[np.maximum(parents, 0)], 0.0)
    J = len(names)
    inverse_binds = np.broadcast_to(np.eye(4), (J, 4, 4)).copy()
    inverse_binds[:, :3, 3] = -world
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (J, 1))
    return Skeleton(
        names=tuple(names),
        parents=parents,
        translations=local,
        rotations=rotations,
        scales=np.ones((J, 3)),
        inverse_binds=inverse_binds,
    )


def _skin_weights(D, shape_joint, num_joints, *, sigma, max_influences=4, min_weight=0.01):
    """Smooth skin weights from per-shape distances.

    Parameters
    ----------
    D : (S, n) float array
        Signed distance of each vertex to each shape.
    shape_joint : (S,) int array
        Owning joint of each shape.
    num_joints : int
    sigma : float
        Falloff width (metres).

    Returns
    -------
    joints : (n, 4) int64
        Sorted by decreasing weight; unused slots are joint 0 with weight 0.
    weights : (n, 4) float64
        Non-negative, rows sum to 1.
    """
    n = D.shape[1]
    Dj = np.full((num_joints, n), np.inf)
    np.minimum.at(Dj, shape_joint, D)  # per joint: distance to its nearest own shape
    rel = Dj - Dj.min(axis=0, keepdims=True)
    W = np.exp(-((rel / sigma) ** 2)).T  # (n, J); inf -> 0
    order = np.argsort(-W, axis=1, kind="stable")[:, :max_influences]
    w = np.take_along_axis(W, order, axis=1)
    w = np.where(w >= min_weight * w[:, :1], w, 0.0)
    w = w / w.sum(axis=1, keepdims=True)
    joints = np.where(w > 0, order, 0).astype(np.int64)
    return joints, w


def _vertex_colors(D, shapes, *, tau=0.01):
    """Shape colours blended by proximity (softmin of distances), linear RGBA ``(n, 4)``."""
    C = np.array([s.color for s in shapes], dtype=np.float64)
    logits = -(D - D.min(axis=0, keepdims=True)) / tau
    A = np.exp(logits)
    A /= A.sum(axis=0, keepdims=True)
    rgb = A.T @ C
    return np.concatenate([rgb, np.ones((len(rgb), 1))], axis=1)


def _planar_uvs(V, u_axis, v_axis):
    """UVs by planar projection over the bounding box, ``(n, 2)`` in [0, 1] (v down)."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    ext = np.maximum(hi - lo, 1e-9)
    side = max(ext[u_axis], ext[v_axis])  # keep the aspect ratio
    u = (V[:, u_axis] - lo[u_axis]) / side
    v = 1.0 - (V[:, v_axis] - lo[v_axis]) / side
    return np.stack([u, v], axis=1)


def _build(name, joints, shapes, clips_fn, *, voxel, edge, sigma, uv_axes):
    skeleton = _skeleton(joints)
    V, F, N = _surface(shapes, voxel=voxel, edge=edge)
    D, _ = _shape_distances(shapes, V)
    shape_joint = np.array([skeleton.index(s.joint) for s in shapes], dtype=np.int64)
    jidx, w = _skin_weights(D, shape_joint, skeleton.num_joints, sigma=sigma)
    mesh = Mesh(
        name=f"{name}Body",
        positions=V,
        faces=F,
        normals=N,
        uvs=(_planar_uvs(V, *uv_axes),),
        colors=_vertex_colors(D, shapes),
        joints=jidx,
        weights=w,
        material=0,
    )
    material = Material(name=f"{name}Skin", base_color=np.ones(4), metallic=0.0, roughness=0.7)
    return Character(
        name=name,
        skeleton=skeleton,
        meshes=(mesh,),
        clips=tuple(clips_fn(skeleton)),
        materials=(material,),
    )


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
        _ellipsoid("Hips", (0.0, 0.95, 0.0), (0.165, 0.11, 0.115), _TROUSERS, 0.03),
        _ellipsoid("Spine", (0.0, 1.12, 0.0), (0.145, 0.13, 0.1), _SHIRT, 0.05),
        _ellipsoid("Chest", (0.0, 1.33, 0.0), (0.175, 0.155, 0.11), _SHIRT, 0.05),
        _cone("Neck", (0.0, 1.44, -0.005), (0.0, 1.62, 0.0), 0.055, 0.05, _SKIN, 0.03),
        _ellipsoid("Head", (0.0, 1.695, 0.012), (0.085, 0.108, 0.098), _SKIN, 0.03),
        _ellipsoid("Head", (0.0, 1.685, 0.108), (0.014, 0.024, 0.02), _SKIN, 0.012),  # nose
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
            _cone(f"Shoulder.{side}", p(0.05, 1.42, 0.0), p(0.18, 1.44, 0.0), 0.06, 0.058, _SHIRT, 0.04),
            _cone(f"UpperArm.{side}", p(0.18, 1.44, 0.0), p(0.45, 1.44, -0.01), 0.054, 0.042, _SHIRT, 0.02),
            _cone(f"LowerArm.{side}", p(0.45, 1.44, -0.01), p(0.71, 1.44, 0.0), 0.041, 0.03, _SKIN, 0.02),
            _ellipsoid(f"Hand.{side}", p(0.79, 1.438, 0.0), (0.075, 0.022, 0.045), _SKIN, 0.02),
            _cone(f"Hand.{side}", p(0.73, 1.436, 0.03), p(0.78, 1.43, 0.075), 0.015, 0.012, _SKIN, 0.012),
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
            _cone(f"UpperLeg.{side}", p(0.095, 0.92, 0.0), p(0.1, 0.5, 0.01), 0.085, 0.053, _TROUSERS, 0.025),
            _cone(f"LowerLeg.{side}", p(0.1, 0.5, 0.01), p(0.1, 0.1, -0.01), 0.051, 0.036, _TROUSERS, 0.02),
            _cone(f"Foot.{side}", p(0.1, 0.045, -0.03), p(0.1, 0.03, 0.16), 0.045, 0.03, _SHOES, 0.03),
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
    return _build("Humanoid", joints, shapes, _humanoid_clips,
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
        _ellipsoid("Hips", (0.0, 0.88, -0.48), (0.18, 0.2, 0.3), _FUR, 0.05),
        _ellipsoid("Spine", (0.0, 0.86, -0.1), (0.175, 0.2, 0.3), _FUR, 0.08),
        _ellipsoid("Chest", (0.0, 0.89, 0.27), (0.18, 0.23, 0.26), _FUR, 0.08),
        _cone("Neck", (0.0, 0.94, 0.42), (0.0, 1.14, 0.7), 0.13, 0.075, _FUR, 0.05),
        _ellipsoid("Head", (0.0, 1.19, 0.76), (0.09, 0.095, 0.12), _FUR, 0.04),
        _cone("Head", (0.0, 1.17, 0.8), (0.0, 1.12, 0.99), 0.07, 0.042, _BELLY, 0.04),
        _ellipsoid("Head", (0.0, 1.13, 1.02), (0.026, 0.02, 0.016), _DARK, 0.015),  # nose
        _cone("Head", (0.055, 1.26, 0.71), (0.075, 1.35, 0.69), 0.035, 0.012, _DARK, 0.02),  # ears
        _cone("Head", (-0.055, 1.26, 0.71), (-0.075, 1.35, 0.69), 0.035, 0.012, _DARK, 0.02),
        _cone("Tail.1", (0.0, 0.93, -0.76), (0.0, 0.87, -0.94), 0.05, 0.042, _FUR, 0.03),
        _cone("Tail.2", (0.0, 0.87, -0.94), (0.0, 0.77, -1.03), 0.042, 0.034, _FUR, 0.02),
        _cone("Tail.3", (0.0, 0.77, -1.03), (0.0, 0.63, -1.08), 0.034, 0.02, _DARK, 0.02),
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
                _cone(f"{end}UpperLeg.{side}", hip, knee, 0.085, 0.05, _FUR, 0.05),
                _cone(f"{end}LowerLeg.{side}", knee, ankle, 0.048, 0.035, _FUR, 0.02),
                _cone(f"{end}Foot.{side}", ankle, toe, 0.036, 0.032, _DARK, 0.02),
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
        _rot_track(sk, "Neck", t, _euler(t, y=np.radians(15) * _wave(t, period), x=np.radians(6) * _wave(t, period, 0.3))),
        _rot_track(sk, "Head", t, _euler(t, y=np.radians(10) * _wave(t, period, 0.05), z=np.radians(5) * _wave(t, period / 2))),
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
    return _build("Quadruped", joints, shapes, _quadruped_clips,
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
