"""Body plans: characters from joints and signed-distance primitives (used by :mod:`rigmix.examples`).

A body plan is a list of joints (name, parent name, rest world position) and a list of
:class:`Shape` primitives (round cones and ellipsoids), each owned by one joint and carrying a
colour. :func:`build_character` turns it into a skinned :class:`rigmix.character.Character`:

* Surface: the primitives' signed distance fields are combined with a smooth minimum, the zero
  level set is extracted by marching cubes (scikit-image, Lewiner), isotropically remeshed
  (Botsch and Kobbelt, gpytoolbox) and projected back onto the field: one closed, 2-manifold,
  consistently outward-oriented triangle mesh.
* Skin weights: for each vertex and joint, ``d_j`` is the signed distance to that joint's own
  primitives; ``w_j = exp(-((d_j - min_k d_k) / sigma)^2)``, the 4 largest kept, small ones
  dropped, rows normalized: a smooth blend over a few centimetres at every joint.
* Normals: the normalized field gradient. UVs: a planar projection over the bounding box (no
  seam). Vertex colours: the primitives' colours blended by proximity. One material.
* Skeleton: identity rest rotations (joint frames aligned with the world), so rest local
  translations are differences of world positions and inverse binds are pure translations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..character import Character, Material, Mesh, Skeleton

__all__ = ["Shape", "cone", "ellipsoid", "build_character"]

logger = logging.getLogger(__name__)

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
class Shape:
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


def cone(joint, a, b, ra, rb, color, blend=0.02):
    return Shape(joint, "cone", tuple(a), tuple(b), ra, rb, tuple(color), blend)


def ellipsoid(joint, c, r, color, blend=0.02):
    return Shape(joint, "ellipsoid", tuple(c), tuple(r), 0.0, 0.0, tuple(color), blend)


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
    shapes : sequence of Shape
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


def build_character(name, joints, shapes, clips_fn, *, voxel, edge, sigma, uv_axes):
    """A skinned character from a body plan.

    Parameters
    ----------
    name : str
    joints : list of (str, str or None, (3,) float)
        Name, parent name and rest world position, parents first.
    shapes : list of Shape
    clips_fn : callable
        ``clips_fn(skeleton) -> list of Clip``.
    voxel : float
        Marching cubes grid spacing (metres).
    edge : float
        Target edge length of the remeshed surface (metres).
    sigma : float
        Skin weight falloff (metres).
    uv_axes : (int, int)
        World axes projected to u and v.

    Returns
    -------
    Character
        One skinned mesh, one material, the clips.
    """
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
