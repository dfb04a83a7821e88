"""Synthetic shapes for the fusion tests (made in code, answers known)."""

from __future__ import annotations

import numpy as np


def sphere(subdivisions=3):
    """Unit icosphere ``(V, F)`` (libigl icosahedron, upsampled and projected)."""
    import igl

    V, F = igl.icosahedron()
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    for _ in range(subdivisions):
        V, F = igl.upsample(V, F)
        V = V / np.linalg.norm(V, axis=1, keepdims=True)
    return np.ascontiguousarray(V), np.ascontiguousarray(F, dtype=np.int64)


def ellipsoid(axes, center=(0.0, 0.0, 0.0), subdivisions=3):
    V, F = sphere(subdivisions)
    return V * np.asarray(axes, float) + np.asarray(center, float), F


def two_joint_weights(V, x0=0.0, width=0.15):
    """Weights ``(n, 2)`` blending joint 0 into joint 1 along +x around ``x0``."""
    t = 1.0 / (1.0 + np.exp(-(V[:, 0] - x0) / width))
    return np.stack([1.0 - t, t], axis=1)


def split_faces(V, F):
    """Every face gets its own three vertices (flat-shaded glTF style)."""
    return V[F.ravel()], np.arange(3 * len(F), dtype=np.int64).reshape(-1, 3)
