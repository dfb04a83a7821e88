"""Mirror a rigged character: its left side becomes its right side (a user feature and a benchmark).

:func:`mirror_character` reflects a :class:`~rigmix.character.Character` across a plane of its
model space (the space its rest pose is skinned into) and swaps the sides in its joint names, so
that the mirrored character's ``UpperArm.L`` is the original's right arm, reflected onto the left.
A config can mirror any input (``mirror = true`` under ``[characters.NAME]``; see
:mod:`rigmix.config`), e.g. to graft a character's right arm onto the left side of another, and
``benchmarks/self_composition.py`` uses it for a ground truth that ``nearest`` cannot copy
(PIPELINE.md section 7: replace a limb by its mirror image from the other side).

The plane
---------
Always perpendicular to one axis of the model space (x, y or z): a reflection across such a
plane keeps every local scale diagonal (a glTF TRS holds no shear), and the three axes cover every
character authored facing an axis. ``axis=None`` (the config's ``mirror = true``) picks the axis
that separates the character's sides: the one along which its side-named joint pairs
(``UpperLeg.L``/``UpperLeg.R``, :func:`swap_side`) lie apart at rest (x for the shared characters
that face +Z with +Y up as glTF asks, z for the Wasp, which faces +X). The surface alone can
mislead: a robot whose legs are posed unequally at rest is more symmetric front to back than
left to right. Without such pairs it picks the axis whose plane the rest-pose surface is most
symmetric about; when no axis plane is a symmetry within ``tol`` it falls back to x.
The offset along the axis is the detected centre of symmetry, so a symmetric character stays
where it is (any offset gives the same character up to a translation, which the composition's
positioning removes anyway).

The maths
---------
With ``S`` the affine reflection (4x4) and ``H`` the linear one (``S`` without its offset; ``H =
H^-1``, ``S = S^-1``), every joint's world matrix becomes ``W'_j = S W_j H``: the joint frame
is reflected too, so that the rotation part ``H R H`` stays a proper rotation. Hence

* vertices ``v' = S v``, normals ``n' = H n``, and every face's winding is reversed (a
  reflection turns the surface inside out otherwise);
* local transforms of joints and of child anchors ``L' = H L H``: translation ``H t``,
  rotation quaternion ``(x, y, z, w) -> (x, -y, -z, w)`` for the x axis (the rotation axis is an
  axial vector: ``v' = -H v``), scale unchanged; the same holds for every animation key (and
  CUBICSPLINE tangents, which are linear in the values);
* the outermost transform (a top anchor, or a root joint without one) ``L' = S L H``: it also
  carries the offset of the plane (translation keys ``H t + 2 d e_axis``, tangents ``H t``);
* inverse bind matrices ``IB' = H IB S``, so that skinning matrices become ``S (W IB) S`` and
  every skinned vertex at every frame is the reflection of the original's;
* props: local matrix ``H M H`` (``S M H`` for a static prop), mesh reflected by ``H``.

Joint indices, weights, UVs, colours and materials are unchanged (a texture is mirrored with the
surface: lettering reads backwards). Mirroring twice across the same plane gives the original back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..character import Anchor, Character, Clip, Mesh, Prop, Skeleton, Track
from ..errors import InputError
from ..rig import swap_side

__all__ = ["MirrorPlane", "mirror_plane", "side_axis", "mirror_character", "swap_side", "AXES"]

log = logging.getLogger(__name__)

#: Axis names accepted by :func:`mirror_plane` and the config's ``mirror`` key.
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class MirrorPlane:
    """The plane ``{p : p[axis] = offset}`` of a character's model space.

    Attributes
    ----------
    axis : int
        0, 1 or 2 (x, y, z).
    offset : float
        In the character's units.
    error : float
        Mean distance from the reflected rest-pose vertices to the closest rest-pose vertex,
        relative to the bounding-box diagonal (0 for an exactly symmetric surface; ``nan`` when
        the plane was given, not detected).
    """

    axis: int
    offset: float = 0.0
    error: float = float("nan")

    def __post_init__(self):
        if self.axis not in (0, 1, 2):
            raise InputError(f"mirror: axis must be 0, 1 or 2 (x, y, z), got {self.axis!r}")

    @property
    def linear(self) -> np.ndarray:
        """``H`` (4, 4): the reflection through the origin (no translation)."""
        H = np.eye(4)
        H[self.axis, self.axis] = -1.0
        return H

    @property
    def matrix(self) -> np.ndarray:
        """``S`` (4, 4): the affine reflection across the plane."""
        S = self.linear
        S[self.axis, 3] = 2.0 * self.offset
        return S

    def reflect(self, X) -> np.ndarray:
        """Points ``(..., 3)`` reflected across the plane (float64 copy)."""
        X = np.array(X, dtype=np.float64, copy=True)
        X[..., self.axis] = 2.0 * self.offset - X[..., self.axis]
        return X

    def reflect_vectors(self, X) -> np.ndarray:
        """Directions ``(..., 3)`` (normals, translations of a local frame) reflected by ``H``."""
        X = np.array(X, dtype=np.float64, copy=True)
        X[..., self.axis] = -X[..., self.axis]
        return X

    def reflect_quaternions(self, Q) -> np.ndarray:
        """Rotations ``(..., 4)`` xyzw conjugated by the reflection: ``H R H``.

        The vector part of a quaternion is an axial vector: it maps to ``-H v`` (its component
        along the axis kept, the other two negated); ``w`` is kept.
        """
        Q = np.array(Q, dtype=np.float64, copy=True)
        for k in range(3):
            if k != self.axis:
                Q[..., k] = -Q[..., k]
        return Q


def _rest_positions(character: Character) -> np.ndarray:
    """Rest-pose positions of every skinned mesh (bind positions for unskinned ones), ``(n, 3)``."""
    from ..skinning import rest_pose

    parts = rest_pose(character) if character.meshes else []
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def mirror_plane(character: Character, axis=None, *, tol=0.02, iterations=3) -> MirrorPlane:
    """The plane :func:`mirror_character` reflects across by default.

    Parameters
    ----------
    character : Character
    axis : {"x", "y", "z", 0, 1, 2} or None
        The axis the plane is perpendicular to; ``None``: :func:`side_axis` where the skeleton has
        side-named joint pairs, otherwise the axis whose plane the rest-pose surface is most
        symmetric about (mean reflection error relative to the bounding-box diagonal), or x when
        none is within ``tol``.
    tol : float
        Largest reflection error of a detected symmetry (relative to the diagonal).
    iterations : int
        Offset refinements: the plane moves to the median midpoint between each vertex and the
        vertex closest to its reflection.

    Returns
    -------
    MirrorPlane
        Offset at the centre of symmetry along the axis (the middle of the rest pose's extent
        when the character has no vertex).
    """
    if isinstance(axis, str):
        if axis.lower() not in AXES:
            raise InputError(f"mirror: unknown axis {axis!r}; use one of {', '.join(AXES)}")
        axis = AXES.index(axis.lower())
    if axis is None:
        axis = side_axis(character.skeleton)
    V = np.unique(_rest_positions(character), axis=0)
    if len(V) < 3:
        return MirrorPlane(0 if axis is None else int(axis), 0.0)
    diag = float(np.linalg.norm(np.ptp(V, axis=0))) or 1.0
    tree = cKDTree(V)
    planes = []
    for a in ((0, 1, 2) if axis is None else (int(axis),)):
        plane = MirrorPlane(a, float(0.5 * (V[:, a].max() + V[:, a].min())))
        for _ in range(iterations + 1):
            d, i = tree.query(plane.reflect(V))
            plane = MirrorPlane(a, float(np.median(0.5 * (V[:, a] + V[i, a]))), float(d.mean() / diag))
        planes.append(plane)
    if axis is not None:
        return planes[0]
    best = min(planes, key=lambda p: p.error)
    if best.error > tol:
        log.info("mirror: %s is symmetric about no axis plane (best %s, error %.3f); mirroring across x",
                 character.name, AXES[best.axis], best.error)
        return planes[0]
    return best


def side_axis(skeleton) -> int | None:
    """The model-space axis along which a skeleton's left and right joints lie apart at rest.

    Parameters
    ----------
    skeleton : rigmix.character.Skeleton

    Returns
    -------
    int or None
        0, 1 or 2: the axis with the largest sum, over the joint pairs named for their sides
        (:func:`swap_side`), of the absolute difference of the two joints' rest world positions
        along it. ``None`` without such a pair, or when the pairs coincide.
    """
    names = list(skeleton.names)
    index = {n: i for i, n in enumerate(names)}
    pairs = [(i, index[m]) for i, n in enumerate(names) if (m := swap_side(n)) != n and m in index and i < index[m]]
    if not pairs:
        return None
    P = skeleton.rest_worlds()[:, :3, 3]
    i, j = np.asarray(pairs).T
    spread = np.abs(P[i] - P[j]).sum(axis=0)
    return int(np.argmax(spread)) if spread.max() > 0 else None


def _swapped_names(names) -> tuple[str, ...]:
    """Side-swapped joint names; a name whose swap would collide with another joint keeps its own."""
    names = tuple(names)
    out = [swap_side(n) for n in names]
    # a rig may name one side only (CesiumMan's "arm_joint_L__4_" pairs with "arm_joint_R"):
    # swapping is still a bijection unless a swapped name equals an unswapped one
    clash = {n for n in out if out.count(n) > 1}
    if clash:
        log.warning("mirror: joint names %s would repeat after swapping sides; kept unswapped", sorted(clash))
        out = [names[i] if out[i] in clash else out[i] for i in range(len(names))]
    return tuple(out)


def _mirror_mesh(mesh: Mesh, plane: MirrorPlane, *, affine: bool) -> Mesh:
    """A mesh reflected by ``S`` (``affine``) or ``H``, normals by ``H``, winding reversed."""
    pos = plane.reflect(mesh.positions) if affine else plane.reflect_vectors(mesh.positions)
    normals = None if mesh.normals is None else plane.reflect_vectors(mesh.normals)
    return replace(mesh, positions=pos, normals=normals, faces=np.asarray(mesh.faces)[:, [0, 2, 1]])


def _conjugate(M, plane: MirrorPlane, *, outer: bool) -> np.ndarray:
    """``H M H`` (a local matrix), or ``S M H`` (``outer``: the transform below the scene root)."""
    left = plane.matrix if outer else plane.linear
    return left @ np.asarray(M, np.float64) @ plane.linear


def _mirror_track(track: Track, plane: MirrorPlane, *, outer: bool) -> Track:
    """Keys of one channel mapped as its joint's local transform (tangents by the linear part)."""
    v = np.asarray(track.values, np.float64)
    if track.path == "scale":
        return track
    if track.path == "rotation":
        return replace(track, values=plane.reflect_quaternions(v))
    out = plane.reflect_vectors(v)
    if outer:  # only positions (not CUBICSPLINE tangents) carry the plane's offset
        shift = np.zeros(3)
        shift[plane.axis] = 2.0 * plane.offset
        if track.interpolation == "CUBICSPLINE":
            out[:, 1] += shift
        else:
            out += shift
    return replace(track, values=out)


def mirror_character(character: Character, plane: MirrorPlane | None = None, *, axis=None,
                     swap_names: bool = True) -> Character:
    """The character reflected across a plane of its model space, joint sides swapped.

    Parameters
    ----------
    character : Character
    plane : MirrorPlane, optional
        Default: :func:`mirror_plane` ``(character, axis)``.
    axis : {"x", "y", "z"} or None
        Only without ``plane``: see :func:`mirror_plane`.
    swap_names : bool
        Swap the sides in joint names (:func:`swap_side`), so that a joint keeps naming the side it
        is on. Joint indices never change.

    Returns
    -------
    Character
        Same joints (indices and topology), meshes, clips, materials and props, reflected as
        described in the module docstring: skinned with any pose of its clips, every vertex is
        the reflection of the original's vertex at the same pose. Name and source unchanged;
        ``mirrored`` toggled.
    """
    if plane is None:
        plane = mirror_plane(character, axis)
    sk = character.skeleton
    H = plane.linear
    J = sk.num_joints
    # the outermost transform of each root (its top anchor, or the root joint itself) carries S
    anchors = tuple(Anchor(a.name, _conjugate(a.matrix, plane, outer=a.parent < 0), a.parent) for a in sk.anchors)
    outer = (sk.parents < 0) & (sk.root_anchor < 0)  # (J,) root joints hanging from the scene root
    T = plane.reflect_vectors(sk.translations)
    if outer.any():
        T[outer] = plane.reflect(sk.translations[outer])
    skeleton = Skeleton(
        names=_swapped_names(sk.names) if swap_names else sk.names,
        parents=sk.parents,
        translations=T,
        rotations=plane.reflect_quaternions(sk.rotations),
        scales=sk.scales,
        inverse_binds=H @ np.asarray(sk.inverse_binds) @ plane.matrix,  # IB' = H IB S
        anchors=anchors,
        root_anchor=sk.root_anchor,
    )
    clips = tuple(Clip(c.name, tuple(_mirror_track(t, plane, outer=bool(0 <= t.joint < J and outer[t.joint]))
                                     for t in c.tracks)) for c in character.clips)
    meshes = tuple(_mirror_mesh(m, plane, affine=True) for m in character.meshes)
    props = tuple(Prop(_mirror_mesh(p.mesh, plane, affine=False), p.joint,
                       _conjugate(p.matrix, plane, outer=p.joint < 0)) for p in character.props)
    return replace(character, skeleton=skeleton, meshes=meshes, clips=clips, props=props,
                   mirrored=not character.mirrored)
