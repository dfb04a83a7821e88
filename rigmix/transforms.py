"""Rigid-body and affine transform helpers, vectorized over leading axes.

Conventions (the project's, stated once in :mod:`rigmix.character`):

* 4x4 matrices act on column vectors: ``p' = M @ p``; translation in ``M[..., :3, 3]``.
* Quaternions are ``(..., 4)`` arrays in ``(x, y, z, w)`` order (glTF and scipy), unit length.
* A local transform is translation ``T``, rotation ``R`` (quaternion), scale ``S`` and its
  matrix is ``T @ R @ S`` (glTF's order).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "quat_normalize",
    "quat_multiply",
    "quat_conjugate",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_slerp",
    "quat_angle",
    "trs_to_matrix",
    "matrix_to_trs",
    "transform_points",
    "polar_decomposition",
    "unit_scale",
]


def quat_normalize(q):
    """Unit quaternions; a zero quaternion becomes identity.

    Parameters
    ----------
    q : (..., 4) float array, xyzw.

    Returns
    -------
    (..., 4) float64 array of unit length.
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.where(n > 1e-12, q / np.where(n > 1e-12, n, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    return out


def quat_conjugate(q):
    """Inverse of unit quaternions ``(..., 4)`` xyzw."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_multiply(a, b):
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``), broadcast over ``(..., 4)``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_to_matrix(q):
    """Rotation matrices ``(..., 3, 3)`` from quaternions ``(..., 4)`` xyzw (normalized first)."""
    x, y, z, w = np.moveaxis(quat_normalize(q), -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = np.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        axis=-1,
    )
    return m.reshape(m.shape[:-1] + (3, 3))


def matrix_to_quat(m):
    """Quaternions ``(..., 4)`` xyzw with ``w >= 0`` from rotation matrices ``(..., 3, 3)``.

    Uses the numerically stable branch per element (Shepperd's method).
    """
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    q = np.empty((m.shape[0], 4))
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    case = np.where(tr > diag.max(axis=1), 3, diag.argmax(axis=1))
    for c in range(4):
        sel = case == c
        if not sel.any():
            continue
        r = m[sel]
        if c == 3:
            s = np.sqrt(1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]) * 2
            q[sel] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                               (r[:, 1, 0] - r[:, 0, 1]) / s, 0.25 * s], axis=1)
        elif c == 0:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[sel] = np.stack([0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s,
                               (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 2, 1] - r[:, 1, 2]) / s], axis=1)
        elif c == 1:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[sel] = np.stack([(r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s,
                               (r[:, 1, 2] + r[:, 2, 1]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s], axis=1)
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[sel] = np.stack([(r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s,
                               0.25 * s, (r[:, 1, 0] - r[:, 0, 1]) / s], axis=1)
    q = quat_normalize(q)
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(shape + (4,))


def quat_slerp(a, b, t):
    """Spherical linear interpolation along the shorter arc.

    Parameters
    ----------
    a, b : (..., 4) unit quaternions xyzw.
    t : (...,) or scalar, 0 gives ``a`` and 1 gives ``b``.

    Returns
    -------
    (..., 4) unit quaternions.
    """
    a = quat_normalize(a)
    b = quat_normalize(b)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-8
    safe = np.where(near, 1.0, sin)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(near, t, np.sin(t * theta) / safe)
    return quat_normalize(wa * a + wb * b)


def quat_angle(a, b):
    """Rotation angle in radians between unit quaternions ``(..., 4)``, in ``[0, pi]``."""
    d = np.abs(np.sum(quat_normalize(a) * quat_normalize(b), axis=-1))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def trs_to_matrix(t, r, s):
    """Local matrices ``T @ R @ S``.

    Parameters
    ----------
    t : (..., 3) translation.
    r : (..., 4) rotation quaternion xyzw.
    s : (..., 3) scale.

    Returns
    -------
    (..., 4, 4) float64 matrices acting on column vectors.
    """
    t = np.asarray(t, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    rm = quat_to_matrix(r)
    shape = np.broadcast_shapes(t.shape[:-1], rm.shape[:-2], s.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = rm * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def matrix_to_trs(m):
    """Decompose affine matrices ``(..., 4, 4)`` into translation, rotation (xyzw), scale.

    Scale is positive per axis unless the matrix mirrors, in which case the x scale is
    negated. Shear is lost (glTF local transforms cannot hold it either).
    """
    m = np.asarray(m, dtype=np.float64)
    t = m[..., :3, 3].copy()
    a = m[..., :3, :3]
    s = np.linalg.norm(a, axis=-2)
    det = np.linalg.det(a)
    s[..., 0] = np.where(det < 0, -s[..., 0], s[..., 0])
    rm = a / np.where(np.abs(s) > 1e-12, s, 1.0)[..., None, :]
    return t, matrix_to_quat(rm), s


def transform_points(m, p):
    """Apply ``(..., 4, 4)`` matrices to points ``(..., n, 3)``: ``p' = M[:3,:3] p + M[:3,3]``."""
    m = np.asarray(m, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    return p @ np.swapaxes(m[..., :3, :3], -1, -2) + m[..., None, :3, 3]


def polar_decomposition(A):
    """Polar decomposition ``A = Q @ P`` of ``(..., 3, 3)`` matrices.

    ``Q`` is a rotation (det +1) and ``P`` is symmetric; a mirroring ``A`` puts the reflection
    into ``P`` so that ``Q`` stays a proper rotation.
    """
    U, s, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    s = s.copy()
    s[..., 2] *= d
    Q = U @ Vt
    P = np.swapaxes(Vt, -1, -2) @ (s[..., :, None] * Vt)
    return Q, P


def unit_scale(M):
    """Affine matrices ``(..., 4, 4)`` with their scale (and shear) removed: ``[Q | t]``, ``Q``
    the rotation of :func:`polar_decomposition`, ``t`` the translation unchanged."""
    M = np.asarray(M, dtype=np.float64)
    out = M.copy()
    out[..., :3, :3] = polar_decomposition(M[..., :3, :3])[0]
    return out
