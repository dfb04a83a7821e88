"""Linear blend skinning and dual quaternion skinning, vectorized over vertices and frames.

Skinning follows glTF (see :mod:`rigmix.character`): the skinning matrix of joint ``j`` is
``world[j] @ inverse_bind[j]`` and a skinned vertex is ``sum_k w_k M[joint_k] @ v``. Both
methods take the skinning matrices as input so that callers can build them once per pose and
reuse them for every mesh of a character.

Memory: the per-vertex blended transforms are ``(F, n, 3, 4)``; frames are processed in chunks
so that a long clip on a dense mesh never needs more than about ``_CHUNK_ELEMENTS`` floats of
temporary storage at once.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .geometry import check_coordinates, check_transforms, check_unmirrored
from .transforms import matrix_to_quat, polar_decomposition, quat_conjugate, quat_multiply, trs_to_matrix

__all__ = [
    "skinning_matrices",
    "rest_skinning_matrices",
    "linear_blend_skinning",
    "skinning_operator",
    "skinning_columns",
    "dual_quaternion_skinning",
    "skin_character",
    "rest_pose",
    "rest_at_bind",
    "check_rig",
]

logger = logging.getLogger(__name__)

#: Upper bound on the number of float64 temporaries per chunk of frames (about 256 MB).
_CHUNK_ELEMENTS = 1 << 25


def skinning_matrices(skeleton, T, R, S):
    """Skinning matrices ``world @ inverse_bind`` from local joint poses.

    Parameters
    ----------
    skeleton : rigmix.character.Skeleton
        J joints; its anchors are applied to the roots.
    T : (..., J, 3) float array
        Local translations.
    R : (..., J, 4) float array
        Local rotations, quaternions xyzw.
    S : (..., J, 3) float array
        Local scales.

    Returns
    -------
    M : (..., J, 4, 4) float64 array
        Skinning matrices (column vectors), mapping bind-space points to world space.
    """
    locals_ = trs_to_matrix(T, R, S)
    worlds = skeleton.world_matrices(locals_)
    return worlds @ skeleton.inverse_binds


def rest_skinning_matrices(skeleton):
    """Skinning matrices of the rest pose, ``(J, 4, 4)``.

    Identity for every joint when the inverse bind matrices match the rest pose.
    """
    return skinning_matrices(skeleton, skeleton.translations, skeleton.rotations, skeleton.scales)


def _check_influences(V, joints, weights, M):
    V = np.asarray(V, dtype=np.float64).reshape(-1, 3)
    joints = np.asarray(joints, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float64)
    M = np.asarray(M, dtype=np.float64)
    n = len(V)
    joints = joints.reshape(n, -1)
    weights = weights.reshape(n, -1)
    if joints.shape != weights.shape:
        raise ValueError(f"skinning: joints {joints.shape} and weights {weights.shape} differ")
    if M.shape[-2:] != (4, 4):
        raise ValueError(f"skinning: matrices must be (..., J, 4, 4), got {M.shape}")
    if joints.size and (joints.min() < 0 or joints.max() >= M.shape[-3]):
        raise ValueError(
            f"skinning: joint index out of range [0, {M.shape[-3]}) "
            f"(min {joints.min()}, max {joints.max()})"
        )
    return V, joints, weights, M


def _frame_chunks(num_frames, per_frame):
    """Slices over flattened frames so that one chunk holds about ``_CHUNK_ELEMENTS`` floats."""
    step = max(1, _CHUNK_ELEMENTS // max(1, per_frame))
    for start in range(0, num_frames, step):
        yield slice(start, min(num_frames, start + step))


def linear_blend_skinning(V, joints, weights, M):
    """Linear blend skinning.

    Parameters
    ----------
    V : (n, 3) float array
        Bind-pose vertex positions.
    joints : (n, K) int array
        Joint index of each influence slot.
    weights : (n, K) float array
        Weight of each slot (rows normally sum to 1; they are used as given).
    M : (..., J, 4, 4) float array
        Skinning matrices, e.g. from :func:`skinning_matrices`; leading axes are frames.

    Returns
    -------
    U : (..., n, 3) float64 array
        ``U[..., i, :] = sum_k weights[i, k] * (M[..., joints[i, k]] @ [V[i], 1])[:3]``.
    """
    V, joints, weights, M = _check_influences(V, joints, weights, M)
    lead = M.shape[:-3]
    Mf = M.reshape((-1,) + M.shape[-3:])[..., :3, :]  # (F, J, 3, 4)
    n, K = joints.shape
    out = np.empty((Mf.shape[0], n, 3))
    for sl in _frame_chunks(Mf.shape[0], n * K * 12):
        # blend the affine matrices first (one (n, 3, 4) per frame), then apply once
        A = np.einsum("nk,fnkij->fnij", weights, Mf[sl][:, joints], optimize=True)  # (f, n, 3, 4)
        out[sl] = np.einsum("fnij,nj->fni", A[..., :3], V) + A[..., 3]
    return out.reshape(lead + (n, 3))


def skinning_operator(V, joints, weights, num_joints):
    """Linear blend skinning as one sparse matrix: posed positions are
    ``skinning_operator(...) @ skinning_columns(M)``.

    Row ``i`` holds ``weights[i, k] * [V[i], 1]`` in the four columns of joint ``joints[i, k]``,
    so that the product with a pose's matrix rows gives ``sum_k w_k M[joint_k] @ [v, 1]`` (the
    same sums as :func:`linear_blend_skinning`, added in another order). Linear maps of the
    positions (edge vectors, differences) are rows of it: ``B[F[:, 1]] - B[F[:, 0]]``.

    Parameters
    ----------
    V : (n, 3) float array
        Bind-pose positions.
    joints, weights : (n, K) int and float arrays
        Influences (weights used as given).
    num_joints : int
        J, the skeleton's joint count.

    Returns
    -------
    scipy.sparse.csr_matrix, (n, 4 J) float64
    """
    import scipy.sparse as sp

    V = np.asarray(V, np.float64).reshape(-1, 3)
    joints = np.asarray(joints, np.int64).reshape(len(V), -1)
    weights = np.asarray(weights, np.float64).reshape(len(V), -1)
    n, K = joints.shape
    if joints.size and (joints.min() < 0 or joints.max() >= num_joints):
        raise ValueError(f"skinning: joint index out of range [0, {num_joints})")
    Vh = np.concatenate([V, np.ones((n, 1))], axis=1)
    rows = np.repeat(np.arange(n), K * 4)
    cols = (joints[:, :, None] * 4 + np.arange(4)).ravel()
    vals = (weights[:, :, None] * Vh[:, None, :]).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, 4 * num_joints))


def skinning_columns(M):
    """The skinning matrices ``M`` ``(k, J, 4, 4)`` (column vectors) as the right-hand side of
    :func:`skinning_operator`: ``(4 J, 3 k)`` float64, contiguous; column ``3 f + c`` gives the
    coordinate ``c`` of frame ``f``."""
    M = np.asarray(M, np.float64)
    k, J = M.shape[:2]
    return np.ascontiguousarray(M[..., :3, :].transpose(1, 3, 0, 2).reshape(4 * J, 3 * k))


def _matrix_to_dual_quat(M):
    """Rigid part of ``(..., 4, 4)`` matrices as dual quaternions, plus the non-rigid part.

    Returns
    -------
    real : (..., 4) unit quaternion xyzw (rotation Q of ``M[:3, :3] = Q @ P``).
    dual : (..., 4) quaternion ``0.5 * t * real`` (translation ``t = M[:3, 3]``).
    P : (..., 3, 3) symmetric matrix (scale/shear applied before the rigid motion).
    """
    Q, P = polar_decomposition(M[..., :3, :3])
    real = matrix_to_quat(Q)
    t = np.concatenate([M[..., :3, 3], np.zeros(M.shape[:-2] + (1,))], axis=-1)
    dual = 0.5 * quat_multiply(t, real)
    return real, dual, P


def dual_quaternion_skinning(V, joints, weights, M):
    """Dual quaternion skinning (Kavan, Collins, Zara, O'Sullivan 2008).

    The rotation and translation of each skinning matrix are blended as unit dual quaternions
    (no candy-wrapper collapse under twist). Scale and shear are handled the common two-phase
    way: each matrix is split by polar decomposition into ``M = [Q | t] @ P``; the vertex is
    first deformed by the linear blend of the non-rigid parts ``sum_k w_k P_k`` and then moved
    by the blended dual quaternion. With unit scale ``P = I`` (plain DQS), and a vertex with a
    single influence gets exactly ``M @ v`` as with linear blend skinning.

    Antipodality: every influence is flipped into the hemisphere of the vertex's pivot, the
    influence with the largest weight, before blending.

    Parameters
    ----------
    V : (n, 3) float array
        Bind-pose vertex positions.
    joints : (n, K) int array
    weights : (n, K) float array
    M : (..., J, 4, 4) float array
        Skinning matrices; leading axes are frames.

    Returns
    -------
    U : (..., n, 3) float64 array
        Skinned positions.
    """
    V, joints, weights, M = _check_influences(V, joints, weights, M)
    lead = M.shape[:-3]
    Mf = M.reshape((-1,) + M.shape[-3:])  # (F, J, 4, 4)
    real, dual, P = _matrix_to_dual_quat(Mf)  # (F, J, 4), (F, J, 4), (F, J, 3, 3)
    n, K = joints.shape
    pivot = joints[np.arange(n), np.argmax(weights, axis=1)] if K else np.zeros(n, np.int64)
    out = np.empty((Mf.shape[0], n, 3))
    for sl in _frame_chunks(Mf.shape[0], n * K * 17):
        r = real[sl][:, joints]  # (f, n, K, 4)
        d = dual[sl][:, joints]
        sign = np.where(np.sum(r * real[sl][:, pivot][:, :, None, :], axis=-1) < 0, -1.0, 1.0)
        w = weights * sign  # (f, n, K)
        b0 = np.einsum("fnk,fnkc->fnc", w, r)
        be = np.einsum("fnk,fnkc->fnc", w, d)
        norm = np.linalg.norm(b0, axis=-1, keepdims=True)
        norm = np.where(norm > 1e-12, norm, 1.0)
        b0 = b0 / norm
        be = be / norm
        # non-rigid phase: linear blend of the polar scale/shear factors
        Pb = np.einsum("nk,fnkij->fnij", weights, P[sl][:, joints])
        v = np.einsum("fnij,nj->fni", Pb, V)
        # rigid phase: rotate by b0, translate by 2 * vec(be * conj(b0))
        vq = np.concatenate([v, np.zeros(v.shape[:-1] + (1,))], axis=-1)
        rot = quat_multiply(quat_multiply(b0, vq), quat_conjugate(b0))[..., :3]
        trans = 2.0 * quat_multiply(be, quat_conjugate(b0))[..., :3]
        out[sl] = rot + trans
    return out.reshape(lead + (n, 3))


_METHODS = {"lbs": linear_blend_skinning, "dqs": dual_quaternion_skinning}


def skin_character(character, T, R, S, *, method="lbs"):
    """Skinned positions of every mesh of a character for one pose or a stack of frames.

    Parameters
    ----------
    character : rigmix.character.Character
    T : (..., J, 3) float array
        Local joint translations (e.g. from :func:`rigmix.animation.sample_clip`).
    R : (..., J, 4) float array
        Local joint rotations, xyzw.
    S : (..., J, 3) float array
        Local joint scales.
    method : {"lbs", "dqs"}
        Linear blend skinning (the reference) or dual quaternion skinning.

    Returns
    -------
    list of (..., n_i, 3) float64 arrays
        One per ``character.meshes``, in world space. An unskinned mesh is returned at its
        bind positions, broadcast over the leading axes.
    """
    if method not in _METHODS:
        raise ValueError(f"skinning: unknown method {method!r}, expected one of {sorted(_METHODS)}")
    skin = _METHODS[method]
    M = skinning_matrices(character.skeleton, T, R, S)
    lead = M.shape[:-3]
    out = []
    for mesh in character.meshes:
        if mesh.skinned:
            out.append(skin(mesh.positions, mesh.joints, mesh.weights, M))
        else:
            out.append(np.broadcast_to(mesh.positions, lead + mesh.positions.shape).copy())
    return out


def rest_pose(character, *, method="lbs"):
    """Positions of every mesh skinned at the skeleton's rest pose, ``list of (n_i, 3)``.

    Equal to the raw ``POSITION`` data only when the inverse bind matrices match the rest pose
    (true for most assets, not for all).
    """
    sk = character.skeleton
    return skin_character(character, sk.translations, sk.rotations, sk.scales, method=method)


def rest_at_bind(character, *, rtol=1e-6):
    """The same character with its rest pose moved to its bind pose where the two differ per joint.

    Many exported rigs (every Quaternius character) are bound in one pose and stored in another:
    ``rest_world[j] @ inverse_bind[j]`` differs from joint to joint. Composing needs one pose in
    which mesh and skeleton agree; moving the mesh to the rest pose by skinning (and binding it
    there) changes how it deforms, since blend skinning does not compose, while moving the rest
    pose to the bind pose changes nothing an animation shows: the skinned mesh at every frame
    is the same.

    The reference is the skinning matrix ``M`` of the weighted joint with the most skin weight at
    or below it (the body's root): each weighted joint's new rest world is
    ``M @ inv(inverse_bind[j])``, so the rest mesh is ``M``
    applied to the bind-space mesh (one similarity). Joints that deform nothing keep their rest
    local transform (IK and pole targets stay where they were relative to their parent). Clips
    keep their keys; a joint whose rest local transform changed gets a one-key track holding
    its old rest value for every property a clip leaves unanimated, so the clip poses it as
    before.

    Parameters
    ----------
    character : rigmix.character.Character
    rtol : float
        Skinning matrices within ``rtol`` times their largest entry of the reference count as
        the same pose.

    Returns
    -------
    Character
        ``character`` itself when every weighted joint's rest is its bind pose (up to one
        transform); otherwise the skeleton's rest TRS and the clips change, meshes and inverse
        bind matrices are kept.
    """
    from .character import Clip, Track
    from .transforms import matrix_to_trs

    sk = character.skeleton
    J = sk.num_joints
    mass = np.zeros(J)
    for m in character.meshes:
        if m.skinned and len(m.positions):
            np.add.at(mass, np.asarray(m.joints).ravel(), np.asarray(m.weights, np.float64).ravel())
    weighted = mass > 0
    if not weighted.any():
        return character
    W = sk.rest_worlds()
    M = W @ sk.inverse_binds
    tol = rtol * max(1.0, float(np.abs(M[weighted]).max()))
    # the reference: the weighted joint above the most skin weight (the body's root, not a
    # heavy head posed apart from it), so the body stays where its rest pose put it
    below = mass.copy()
    for j in range(J - 1, 0, -1):  # children first (parents[j] < j)
        if sk.parents[j] >= 0:
            below[sk.parents[j]] += below[j]
    ref = M[int(np.argmax(np.where(weighted, below, -1.0)))]
    if np.abs(M[weighted] - ref).max() <= tol:
        return character
    bind = ref @ np.linalg.inv(sk.inverse_binds)
    L = sk.rest_locals()
    base = sk.root_parent_worlds()
    worlds = np.empty_like(W)
    for j in range(J):  # parents first (Skeleton: parents[j] < j)
        p = sk.parents[j]
        worlds[j] = bind[j] if weighted[j] else (worlds[p] if p >= 0 else base[j]) @ L[j]
    parent_worlds = np.where(sk.parents[:, None, None] >= 0, worlds[np.maximum(sk.parents, 0)], base)
    L_new = np.linalg.inv(parent_worlds) @ worlds
    t, r, s = matrix_to_trs(L_new)
    scale = max(1.0, float(np.abs(L[:, :3, 3]).max()))
    changed = np.flatnonzero(np.abs(L_new - L).reshape(J, -1).max(axis=1) > 1e-6 * scale)  # above float32 noise
    if not len(changed):
        return character
    T, R, S = (np.array(a, np.float64) for a in (sk.translations, sk.rotations, sk.scales))
    T[changed], R[changed], S[changed] = t[changed], r[changed], s[changed]
    old = {"translation": sk.translations, "rotation": sk.rotations, "scale": sk.scales}
    clips = []
    for clip in character.clips:
        have = {(tr.joint, tr.path) for tr in clip.tracks}
        held = [Track(int(j), path, np.array([clip.start]), np.asarray(old[path][j], np.float64)[None])
                for j in changed for path in ("translation", "rotation", "scale") if (int(j), path) not in have]
        clips.append(Clip(clip.name, clip.tracks + tuple(held)) if held else clip)
    logger.info("%s: rest pose moved to the bind pose on %d joints", character.name, len(changed))
    return replace(character, skeleton=replace(sk, translations=T, rotations=R, scales=S), clips=tuple(clips))


def check_rig(character, *, where: str | None = None) -> None:
    """Refuse a rig that cannot be posed: a rest world or inverse bind matrix that is not finite,
    cannot be inverted (a zero scale, a zero matrix) or mirrors (:func:`check_unmirrored`), or a
    joint or vertex at rest beyond
    :data:`rigmix.geometry.MAX_COORDINATE` (native kernels crash on such values).

    Compose applies it to every file as stored (before :func:`rest_at_bind`, which would hide a
    singular rest pose) and ``rigmix inspect`` to the file it reads, so both refuse a file with
    the same line.

    Parameters
    ----------
    character : rigmix.character.Character
    where : str, optional
        Start of the message; default the file's name (:attr:`rigmix.character.Character.label`).

    Raises
    ------
    InputError
        Naming the file, the joint or the object, and the fix.
    """
    sk = character.skeleton
    where = character.label if where is None else where
    W = sk.rest_worlds()
    check_transforms(W, sk.names, where=where, what="rest world matrix",
                     fix="give the joint and its parents a non-zero scale (or matrix) in the file")
    check_transforms(sk.inverse_binds, sk.names, where=where, what="inverse bind matrix",
                     fix="re-export the skin with invertible inverse bind matrices")
    check_unmirrored(W, sk.names, where=where, what="rest world matrix")
    check_unmirrored(sk.inverse_binds, sk.names, where=where, what="inverse bind matrix")
    M = W @ sk.inverse_binds
    points = {"skeleton": W[:, :3, 3]}
    for k, mesh in enumerate(character.meshes):
        P = (linear_blend_skinning(mesh.positions, mesh.joints, mesh.weights, M) if mesh.skinned
             else np.asarray(mesh.positions))
        points[f"mesh {mesh.name or k!r} at rest"] = P
    check_coordinates(points, where=where, fix="the file's transforms or vertices are out of range")
