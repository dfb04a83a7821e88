"""Small mesh helpers used by every dfd stage: checks, normalization, hashing, welding.

Rendering and the feature field work in a normalized frame (bounding-box centre at the origin,
largest half-extent 1, PIPELINE.md section 6); everything public takes and returns the mesh's
own coordinates, and stores the :class:`Normalization` needed to go between the two.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from dfd.errors import DfdInputError

__all__ = [
    "Normalization",
    "check_mesh",
    "normalization",
    "mesh_hash",
    "weld",
    "face_normals",
    "vertex_normals",
    "face_areas",
    "surface_samples",
]


@dataclass(frozen=True)
class Normalization:
    """Similarity that maps mesh coordinates to the normalized frame: ``p_n = (p - center) * scale``.

    Attributes
    ----------
    center : (3,) float64
        Centre of the axis-aligned bounding box, in mesh units.
    scale : float
        ``1 / largest half-extent``, so the normalized mesh fits in ``[-1, 1]^3``.
    """

    center: np.ndarray
    scale: float

    def apply(self, P):
        """Mesh coordinates ``(n, 3)`` -> normalized coordinates ``(n, 3)`` float64."""
        return (np.asarray(P, dtype=np.float64) - self.center) * self.scale

    def invert(self, Q):
        """Normalized coordinates ``(n, 3)`` -> mesh coordinates ``(n, 3)`` float64."""
        return np.asarray(Q, dtype=np.float64) / self.scale + self.center


def check_mesh(V, F, *, stage="dfd"):
    """Validate and convert a triangle mesh.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Indices into ``V``.
    stage : str
        Named in error messages.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise DfdInputError(f"{stage}: vertices must be a non-empty (n, 3) array, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise DfdInputError(f"{stage}: faces must be a non-empty (m, 3) array of triangles, got shape {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise DfdInputError(f"{stage}: faces must be integer indices, got dtype {F.dtype}")
    F = F.astype(np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise DfdInputError(f"{stage}: face indices must lie in [0, {len(V)}), got [{F.min()}, {F.max()}]")
    if not np.isfinite(V).all():
        raise DfdInputError(f"{stage}: vertex positions contain NaN or infinity")
    return V, F


def normalization(V) -> Normalization:
    """The normalization of section 6: bounding-box centre to the origin, half-extent 1.

    Parameters
    ----------
    V : (n, 3) float array

    Returns
    -------
    Normalization
    """
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    half = float((hi - lo).max()) / 2.0
    if half <= 0:
        raise DfdInputError("dfd: the mesh has zero extent (all vertices coincide)")
    return Normalization(center=(lo + hi) / 2.0, scale=1.0 / half)


def mesh_hash(V, F) -> str:
    """SHA-256 hex digest of the positions (float64) and triangles (int64)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(V, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(F, dtype=np.int64).tobytes())
    return h.hexdigest()


def weld(V, F):
    """Merge vertices at exactly the same position (glTF meshes are split at every seam).

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array

    Returns
    -------
    Vw : (k, 3) float64
        Welded positions, in order of first appearance.
    index : (n,) int64
        Welded vertex of each input vertex: ``Vw[index] == V``.
    Fw : (m, 3) int64
        ``index[F]``.
    """
    V = np.asarray(V, dtype=np.float64)
    _, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse].astype(np.int64)
    return V[np.sort(first)], index, index[np.asarray(F, dtype=np.int64)]


def face_normals(V, F):
    """Unit normals ``(m, 3)`` of the triangles (zero for degenerate ones)."""
    V = np.asarray(V, dtype=np.float64)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    length = np.linalg.norm(N, axis=1, keepdims=True)
    return np.divide(N, length, out=np.zeros_like(N), where=length > 0)


def face_areas(V, F):
    """Areas ``(m,)`` of the triangles."""
    V = np.asarray(V, dtype=np.float64)
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def surface_samples(V, F, n, rng):
    """``n`` points drawn uniformly by area on the triangles, ``(n, 3)``.

    Independent of the tessellation: a remeshed region and a coarse original one are sampled
    equally densely. ``rng`` is a :class:`numpy.random.Generator`.

    Raises
    ------
    DfdInputError
        The mesh has zero area.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    A = face_areas(V, F)
    if len(F) == 0 or A.sum() <= 0:
        raise DfdInputError("mesh: cannot sample a surface with zero area")
    face = rng.choice(len(F), n, p=A / A.sum())
    s, r = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1 - s, s * (1 - r), s * r], axis=1)
    return np.einsum("nk,nkj->nj", bary, V[F[face]])


def vertex_normals(V, F):
    """Area-weighted unit vertex normals ``(n, 3)`` (zero for isolated vertices)."""
    V = np.asarray(V, dtype=np.float64)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    out = np.zeros_like(V)
    for k in range(3):
        np.add.at(out, F[:, k], N)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=np.zeros_like(out), where=length > 0)
