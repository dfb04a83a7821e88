"""Small synthetic meshes whose answers are known by construction (tests, benchmarks, examples)."""

from __future__ import annotations

import numpy as np

__all__ = ["icosphere", "ellipsoids", "grid"]

_T = (1.0 + 5.0**0.5) / 2.0
_ICO_V = np.array(
    [[-1, _T, 0], [1, _T, 0], [-1, -_T, 0], [1, -_T, 0], [0, -1, _T], [0, 1, _T],
     [0, -1, -_T], [0, 1, -_T], [_T, 0, -1], [_T, 0, 1], [-_T, 0, -1], [-_T, 0, 1]],
    dtype=np.float64,
)
_ICO_F = np.array(
    [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
     [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
     [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
    dtype=np.int64,
)


def icosphere(subdivisions=2):
    """Unit sphere, ``20 * 4**subdivisions`` faces, symmetric about the three axis planes."""
    import igl

    V, F = _ICO_V.copy(), _ICO_F.copy()
    for _ in range(subdivisions):
        V, F = igl.upsample(V, F)
    return V / np.linalg.norm(V, axis=1, keepdims=True), np.asarray(F, dtype=np.int64)


def ellipsoids(parts, subdivisions=3):
    """Union (as separate components) of ellipsoids ``[(centre, radii), ...]``."""
    S, SF = icosphere(subdivisions)
    V = np.concatenate([S * np.asarray(r, float) + np.asarray(c, float) for c, r in parts])
    F = np.concatenate([SF + k * len(S) for k in range(len(parts))])
    return V, F


def grid(n=21, size=1.0):
    """Flat square ``[0, size]^2`` in the z = 0 plane, ``(n - 1)^2 * 2`` triangles."""
    x = np.linspace(0.0, size, n)
    X, Y = np.meshgrid(x, x, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    F = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return V, F
