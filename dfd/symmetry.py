"""Mirror symmetry detection with a feature field (PIPELINE.md section 6).

Candidate planes: the three axis planes of the mesh's own frame (normals +X, +Y, +Z) through the
surface centroid (area-weighted when faces are given, else the mean vertex). For each, points
on the surface are reflected across the plane; when faces are given the reflected points are
moved to the closest surface point (the field is trained on the surface, and off it its values
are an extrapolation). The plane is a symmetry when the mean feature distance
``||f(p) - f(reflect(p))||`` is below the threshold (0.1 in the DFD prototype).

Symmetric parts (the left and right legs) can then borrow each other's weights: the reflection
of a point across a detected plane is its counterpart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfd.errors import DfdInputError
from dfd.mesh import face_areas, surface_samples

__all__ = ["SymmetryPlane", "detect_symmetry", "symmetry_scores", "reflect", "AXES"]

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class SymmetryPlane:
    """A mirror plane ``{p : normal . (p - point) = 0}``.

    Attributes
    ----------
    axis : str
        ``"x"``, ``"y"`` or ``"z"``: the axis the plane is normal to.
    normal : (3,) float64
        Unit normal.
    point : (3,) float64
        A point of the plane (the centroid), mesh coordinates.
    score : float
        Mean feature distance between points and their reflections (lower is more symmetric).
    """

    axis: str
    normal: np.ndarray
    point: np.ndarray
    score: float

    def reflect(self, P):
        """Mirror images ``(n, 3)`` of points ``(n, 3)``."""
        return reflect(P, self.normal, self.point)


def reflect(P, normal, point):
    """Reflect points ``(n, 3)`` across the plane through ``point`` with unit ``normal``."""
    P = np.asarray(P, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return P - 2.0 * ((P - point) @ n)[:, None] * n


def _samples(V, F, n_samples, rng):
    """Surface samples (area-uniform when faces are given) and the centroid."""
    if F is None:
        centroid = V.mean(axis=0)
        P = V if len(V) <= n_samples else V[rng.choice(len(V), n_samples, replace=False)]
        return P, centroid
    A = face_areas(V, F)
    if A.sum() <= 0:
        raise DfdInputError("symmetry: the mesh has zero area")
    centroid = (A[:, None] * V[F].mean(axis=1)).sum(axis=0) / A.sum()
    return surface_samples(V, F, n_samples, rng), centroid


def symmetry_scores(field, V, F=None, *, n_samples=4096, seed=0, snap=True):
    """Mean feature distance under reflection across each candidate axis plane.

    Parameters
    ----------
    field : dfd.field.FeatureField
        Distilled on this mesh (or anything with ``evaluate((n, 3)) -> (n, C)``).
    V : (n, 3) float array
    F : (m, 3) int array, optional
        With faces, points are area-uniform surface samples and reflections are snapped to the
        surface; without, vertices are used as they are.
    n_samples : int
    seed : int
        Seeds the sampling.
    snap : bool
        Move reflected points to the closest surface point (needs ``F``).

    Returns
    -------
    list of SymmetryPlane
        One per axis, in x, y, z order.
    """
    V = np.asarray(V, dtype=np.float64)
    F = None if F is None else np.asarray(F, dtype=np.int64)
    rng = np.random.default_rng(seed)
    P, centroid = _samples(V, F, n_samples, rng)
    fP = field.evaluate(P)
    planes = []
    for k, axis in enumerate(AXES):
        normal = np.eye(3)[k]
        Q = reflect(P, normal, centroid)
        if snap and F is not None:
            import igl

            Q = igl.point_mesh_squared_distance(Q, V, F)[2]
        score = float(np.linalg.norm(field.evaluate(Q) - fP, axis=1).mean())
        planes.append(SymmetryPlane(axis=axis, normal=normal, point=centroid, score=score))
    return planes


def detect_symmetry(field, V, F=None, *, threshold=0.1, n_samples=4096, seed=0, snap=True):
    """Mirror planes of a mesh under which its feature field is (nearly) invariant.

    Parameters
    ----------
    field : dfd.field.FeatureField
    V : (n, 3) float array
    F : (m, 3) int array, optional
    threshold : float
        Largest mean feature distance of a symmetry plane (0.1, the DFD prototype's value).
    n_samples, seed, snap
        See :func:`symmetry_scores`.

    Returns
    -------
    list of SymmetryPlane
        The planes scoring below ``threshold``, best first; empty for an asymmetric mesh.
    """
    planes = symmetry_scores(field, V, F, n_samples=n_samples, seed=seed, snap=snap)
    return sorted((p for p in planes if p.score < threshold), key=lambda p: p.score)
