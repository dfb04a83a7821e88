"""The domain model: Character, Skeleton, Mesh, Clip, and the project's conventions.

Conventions (the only place they are written; every module follows them)
-----------------------------------------------------------------------
* Units and axes are glTF's: metres, +Y up, right-handed, after loading. Characters are *not*
  rescaled on load (the shared Fox is ~79 units tall); scale matching is a composition step.
* 4x4 matrices act on **column vectors**: ``p' = M @ p``; translation in ``M[:3, 3]``.
  USD's row-vector matrices are transposed in :mod:`rigmix.io.usd` and nowhere else.
* Quaternions are ``(..., 4)`` arrays in **x, y, z, w** order (glTF and scipy), unit length.
* A local transform is ``T @ R @ S`` (glTF's order). Joint world matrices are
  ``world[j] = world[parents[j]] @ local[j]``; a root joint's parent is its *anchor*: the world
  matrix of the non-joint node it hangs from (e.g. CesiumMan's Z-up to Y-up ``Z_UP`` node).
* Joints are in topological order: ``parents[j] < j``, roots have ``-1``. Several roots are
  allowed (the shared Horse has five).
* Skinning follows glTF: ``skin_matrix[j] = world[j] @ inverse_bind[j]``, and a skinned vertex
  is ``sum_k w_k * skin_matrix[joint_k] @ v`` (the mesh node's own transform is ignored).
* Times are in seconds. Vertex order is never changed silently: a function that reindexes
  returns the index map.

Objects are frozen dataclasses over numpy arrays; arrays are made read-only on construction so
that an input character can never be modified by a stage (stages return new objects, e.g. with
:func:`dataclasses.replace`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import UnsupportedError
from .transforms import trs_to_matrix

__all__ = [
    "Anchor",
    "Skeleton",
    "Texture",
    "Material",
    "Mesh",
    "Prop",
    "Track",
    "Clip",
    "Character",
]

Interpolation = Literal["LINEAR", "STEP", "CUBICSPLINE"]
TrackPath = Literal["translation", "rotation", "scale"]


def _frozen(a, dtype=None):
    """A read-only array (a copy only when the dtype changes or the input is writeable)."""
    if a is None:
        return None
    arr = np.array(a, dtype=dtype, copy=True) if dtype is not None else np.array(a, copy=True)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Anchor:
    """A non-joint node above the skeleton (e.g. ``Z_UP`` or ``Armature``).

    Attributes
    ----------
    name : str
    matrix : (4, 4) float64
        Local matrix relative to ``parent`` (column vectors).
    parent : int
        Index of the parent anchor in ``Skeleton.anchors``, ``-1`` for a scene root.
    """

    name: str
    matrix: np.ndarray
    parent: int = -1

    def __post_init__(self):
        object.__setattr__(self, "matrix", _frozen(self.matrix, np.float64))


@dataclass(frozen=True)
class Skeleton:
    """A joint forest with its rest pose and bind matrices.

    Attributes
    ----------
    names : tuple of str, (J,)
        Joint names as in the file (unique; unnamed joints get ``joint_<node index>``).
    parents : (J,) int64
        Parent joint index, ``parents[j] < j``; ``-1`` for roots.
    translations : (J, 3) float64
        Rest local translations.
    rotations : (J, 4) float64
        Rest local rotations, quaternions xyzw.
    scales : (J, 3) float64
        Rest local scales.
    inverse_binds : (J, 4, 4) float64
        Inverse bind matrices (glTF ``skin.inverseBindMatrices``), world -> joint space at bind.
    anchors : tuple of Anchor
        Non-joint nodes above the roots, parents before children.
    root_anchor : (J,) int64
        For a root joint, the index of the anchor it hangs from (``-1``: the scene root); ``-1``
        for every non-root joint.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    translations: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    inverse_binds: np.ndarray
    anchors: tuple[Anchor, ...] = ()
    root_anchor: np.ndarray | None = None

    def __post_init__(self):
        J = len(self.names)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "parents", _frozen(self.parents, np.int64).reshape(J))
        object.__setattr__(self, "translations", _frozen(self.translations, np.float64).reshape(J, 3))
        object.__setattr__(self, "rotations", _frozen(self.rotations, np.float64).reshape(J, 4))
        object.__setattr__(self, "scales", _frozen(self.scales, np.float64).reshape(J, 3))
        object.__setattr__(self, "inverse_binds", _frozen(self.inverse_binds, np.float64).reshape(J, 4, 4))
        object.__setattr__(self, "anchors", tuple(self.anchors))
        ra = np.full(J, -1) if self.root_anchor is None else self.root_anchor
        object.__setattr__(self, "root_anchor", _frozen(ra, np.int64).reshape(J))
        if J and np.any(self.parents >= np.arange(J)):
            raise ValueError("Skeleton joints must be in topological order (parents[j] < j)")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def roots(self) -> np.ndarray:
        """Indices of root joints, ``(R,)``."""
        return np.flatnonzero(self.parents < 0)

    def index(self, name: str) -> int:
        """Index of the joint called ``name`` (``KeyError`` if absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(name) from None

    def children(self, j: int) -> np.ndarray:
        """Direct children of joint ``j``, ``(c,)``."""
        return np.flatnonzero(self.parents == j)

    def subtree(self, j: int) -> np.ndarray:
        """``(J,)`` bool mask of ``j`` and all its descendants."""
        mask = np.zeros(self.num_joints, dtype=bool)
        mask[j] = True
        for k in range(j + 1, self.num_joints):  # topological order: one pass suffices
            p = self.parents[k]
            if p >= 0 and mask[p]:
                mask[k] = True
        return mask

    def anchor_worlds(self) -> np.ndarray:
        """World matrices of the anchors, ``(A, 4, 4)``."""
        out = np.zeros((len(self.anchors), 4, 4))
        for i, a in enumerate(self.anchors):
            out[i] = a.matrix if a.parent < 0 else out[a.parent] @ a.matrix
        return out

    def root_parent_worlds(self) -> np.ndarray:
        """``(J, 4, 4)``: for each joint, the world matrix of its root's anchor (identity if none)."""
        aw = self.anchor_worlds()
        out = np.broadcast_to(np.eye(4), (self.num_joints, 4, 4)).copy()
        has = self.root_anchor >= 0
        out[has] = aw[self.root_anchor[has]]
        return out

    def rest_locals(self) -> np.ndarray:
        """Rest local matrices ``(J, 4, 4)``."""
        return trs_to_matrix(self.translations, self.rotations, self.scales)

    def world_matrices(self, locals_) -> np.ndarray:
        """Forward kinematics.

        Parameters
        ----------
        locals_ : (..., J, 4, 4) local matrices (e.g. one pose or a stack of frames).

        Returns
        -------
        (..., J, 4, 4) world matrices, anchors applied to the roots.
        """
        locals_ = np.asarray(locals_, dtype=np.float64)
        out = np.empty_like(locals_)
        base = self.root_parent_worlds()
        for j in range(self.num_joints):
            p = self.parents[j]
            parent = out[..., p, :, :] if p >= 0 else base[j]
            out[..., j, :, :] = parent @ locals_[..., j, :, :]
        return out

    def rest_worlds(self) -> np.ndarray:
        """Rest world matrices ``(J, 4, 4)``."""
        return self.world_matrices(self.rest_locals())


@dataclass(frozen=True)
class Texture:
    """An image used by a material.

    Attributes
    ----------
    data : bytes
        Encoded image (PNG or JPEG), exactly as in the file.
    mime_type : str
        ``image/png`` or ``image/jpeg``.
    name : str
    sampler : dict
        glTF sampler properties (``magFilter``, ``minFilter``, ``wrapS``, ``wrapT``), may be empty.
    """

    data: bytes
    mime_type: str
    name: str = ""
    sampler: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Material:
    """A glTF metallic-roughness material.

    Attributes
    ----------
    name : str
    base_color : (4,) float64
        ``baseColorFactor``, linear RGBA.
    metallic, roughness : float
    base_color_texture : Texture or None
    base_color_texcoord : int
        Which ``TEXCOORD_n`` set the base colour texture uses.
    double_sided : bool
    alpha_mode : str
        ``OPAQUE``, ``MASK`` or ``BLEND``.
    alpha_cutoff : float
    emissive : (3,) float64
    extra : dict
        Other glTF material properties kept verbatim where they hold no index (e.g. ``extras``).
    """

    name: str = ""
    base_color: np.ndarray = field(default_factory=lambda: np.ones(4))
    metallic: float = 1.0
    roughness: float = 1.0
    base_color_texture: Texture | None = None
    base_color_texcoord: int = 0
    double_sided: bool = False
    alpha_mode: str = "OPAQUE"
    alpha_cutoff: float = 0.5
    emissive: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "base_color", _frozen(self.base_color, np.float64).reshape(4))
        object.__setattr__(self, "emissive", _frozen(self.emissive, np.float64).reshape(3))


@dataclass(frozen=True)
class Mesh:
    """One triangle primitive, skinned or not, as split by the file (UV/normal seams kept).

    Attributes
    ----------
    name : str
        ``<mesh name>`` or ``<mesh name>.<primitive index>`` when a mesh has several primitives.
    positions : (n, 3) float64
        Vertex positions in the mesh's bind space (glTF POSITION).
    faces : (m, 3) int64
        Triangles, counter-clockwise front faces.
    normals : (n, 3) float64 or None
    uvs : tuple of (n, 2) float64
        TEXCOORD_0, TEXCOORD_1, ... (glTF convention: v down from the top of the image).
    colors : (n, 4) float64 or None
        COLOR_0 as linear RGBA in [0, 1].
    joints : (n, K) int64 or None
        Joint indices into ``Character.skeleton``; ``K`` is 4 per JOINTS_n set read.
    weights : (n, K) float64 or None
        Skin weights, rows non-negative and summing to 1 (repaired on load).
    material : int
        Index into ``Character.materials``, ``-1`` for the default material.
    """

    name: str
    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: tuple[np.ndarray, ...] = ()
    colors: np.ndarray | None = None
    joints: np.ndarray | None = None
    weights: np.ndarray | None = None
    material: int = -1

    def __post_init__(self):
        object.__setattr__(self, "positions", _frozen(self.positions, np.float64).reshape(-1, 3))
        object.__setattr__(self, "faces", _frozen(self.faces, np.int64).reshape(-1, 3))
        n = len(self.positions)
        if self.normals is not None:
            object.__setattr__(self, "normals", _frozen(self.normals, np.float64).reshape(n, 3))
        object.__setattr__(self, "uvs", tuple(_frozen(u, np.float64).reshape(n, 2) for u in self.uvs))
        if self.colors is not None:
            object.__setattr__(self, "colors", _frozen(self.colors, np.float64).reshape(n, 4))
        if (self.joints is None) != (self.weights is None):
            raise ValueError(f"mesh {self.name!r}: joints and weights go together")
        if self.joints is not None:
            object.__setattr__(self, "joints", _frozen(self.joints, np.int64).reshape(n, -1))
            object.__setattr__(self, "weights", _frozen(self.weights, np.float64).reshape(n, -1))

    @property
    def skinned(self) -> bool:
        return self.joints is not None

    def dense_weights(self, num_joints: int) -> np.ndarray:
        """Weights as a dense ``(n, J)`` matrix (duplicate joint slots summed)."""
        W = np.zeros((len(self.positions), num_joints))
        if self.joints is None:
            return W
        rows = np.repeat(np.arange(len(self.positions)), self.joints.shape[1])
        np.add.at(W, (rows, self.joints.ravel()), self.weights.ravel())
        return W


@dataclass(frozen=True)
class Prop:
    """A rigid (unskinned) mesh that follows one joint, e.g. a sword parented to a hand.

    Attributes
    ----------
    mesh : Mesh
        Geometry in the prop node's local space (``joints``/``weights`` are None).
    joint : int
        The joint it follows, or ``-1`` for a static mesh placed in the world.
    matrix : (4, 4) float64
        The prop node's matrix relative to the joint (or to the world when ``joint == -1``).
    """

    mesh: Mesh
    joint: int
    matrix: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "matrix", _frozen(self.matrix, np.float64).reshape(4, 4))


@dataclass(frozen=True)
class Track:
    """One animation channel: keyframes of one property of one joint.

    Attributes
    ----------
    joint : int
        Index into the skeleton.
    path : {"translation", "rotation", "scale"}
    times : (k,) float64
        Key times in seconds, strictly increasing.
    values : (k, C) float64, or (k, 3, C) for CUBICSPLINE
        ``C`` is 3, or 4 for rotation (xyzw). CUBICSPLINE keys hold
        ``(in_tangent, value, out_tangent)`` along axis 1, as in glTF.
    interpolation : {"LINEAR", "STEP", "CUBICSPLINE"}
    """

    joint: int
    path: TrackPath
    times: np.ndarray
    values: np.ndarray
    interpolation: Interpolation = "LINEAR"

    def __post_init__(self):
        object.__setattr__(self, "times", _frozen(self.times, np.float64).reshape(-1))
        object.__setattr__(self, "values", _frozen(self.values, np.float64))
        if self.path not in ("translation", "rotation", "scale"):
            raise ValueError(f"track path {self.path!r}")
        if self.interpolation not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise ValueError(f"track interpolation {self.interpolation!r}")


@dataclass(frozen=True)
class Clip:
    """A named animation: tracks over the joints of one skeleton.

    Attributes
    ----------
    name : str
        As in the file (unnamed clips get ``clip_<index>``).
    tracks : tuple of Track
    """

    name: str
    tracks: tuple[Track, ...]

    def __post_init__(self):
        object.__setattr__(self, "tracks", tuple(self.tracks))

    @property
    def start(self) -> float:
        return min((float(t.times[0]) for t in self.tracks if len(t.times)), default=0.0)

    @property
    def end(self) -> float:
        return max((float(t.times[-1]) for t in self.tracks if len(t.times)), default=0.0)

    @property
    def duration(self) -> float:
        return self.end - self.start


@dataclass(frozen=True)
class Character:
    """A rigged, skinned, animated character: (M, W, S, A) of the method, plus materials.

    Attributes
    ----------
    name : str
    skeleton : Skeleton
        May have zero joints for a static file (then ``skinned`` is False).
    meshes : tuple of Mesh
        Skinned meshes (joints index ``skeleton``), several per skin allowed.
    clips : tuple of Clip
    materials : tuple of Material
    props : tuple of Prop
        Unskinned meshes: rigid props following a joint, or static meshes.
    source : str
        The file it was read from (for messages), ``""`` if built in code.
    warnings : tuple of str
        Defects repaired on load, each naming the file and the object.
    mirrored : bool
        Reflected by :func:`rigmix.operations.mirror.mirror_character` an odd number of times:
        its clips are its file's clips reflected, so a joint named for one side moves as the
        file's joint of the other side moves (animation completion tells a mirrored copy of an
        asset from a second copy by it).
    """

    name: str
    skeleton: Skeleton
    meshes: tuple[Mesh, ...] = ()
    clips: tuple[Clip, ...] = ()
    materials: tuple[Material, ...] = ()
    props: tuple[Prop, ...] = ()
    source: str = ""
    warnings: tuple[str, ...] = ()
    mirrored: bool = False

    def __post_init__(self):
        for attr in ("meshes", "clips", "materials", "props", "warnings"):
            object.__setattr__(self, attr, tuple(getattr(self, attr)))

    @property
    def skinned(self) -> bool:
        return self.skeleton.num_joints > 0 and any(m.skinned for m in self.meshes)

    @property
    def label(self) -> str:
        """The character in messages: its file's name (the folders left out, so that no message
        says where a file lives), or its name when it was built in code."""
        return Path(self.source).name if self.source else self.name

    def require_skinned(self, stage: str = "compose") -> "Character":
        """Return self, or raise UnsupportedError if there is nothing to compose."""
        if not self.skinned:
            where = self.label
            raise UnsupportedError(
                f"{stage}: {where} has no skinned mesh (no glTF skin); composition needs a "
                "rigged character: export it with its armature and skin weights"
            )
        return self

    def clip(self, name: str) -> Clip:
        for c in self.clips:
            if c.name == name:
                return c
        raise KeyError(name)
