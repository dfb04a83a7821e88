"""Skinning: LBS and DQS against slow per-vertex references and known invariants."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import asset
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

import rigmix.skinning as skinning
from rigmix.character import Anchor, Character, Clip, Mesh, Skeleton, Track
from rigmix.io.gltf import read_gltf
from rigmix.skinning import (
    dual_quaternion_skinning,
    linear_blend_skinning,
    rest_pose,
    rest_skinning_matrices,
    skin_character,
    skinning_matrices,
)
from rigmix.transforms import trs_to_matrix

# ---------------------------------------------------------------------------------------------
# synthetic data


def random_rigid(rng, shape=()):
    """Random rigid 4x4 matrices ``shape + (4, 4)``."""
    n = int(np.prod(shape)) if shape else 1
    M = np.zeros((n, 4, 4))
    M[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    M[:, :3, 3] = rng.normal(size=(n, 3))
    M[:, 3, 3] = 1
    return M.reshape(shape + (4, 4))


def random_influences(rng, n, K, J):
    joints = rng.integers(0, J, size=(n, K))
    weights = rng.random((n, K))
    weights[rng.random((n, K)) < 0.3] = 0.0
    weights[:, 0] += 1e-3
    return joints, weights / weights.sum(axis=1, keepdims=True)


def chain_character(anchor=True):
    """A 3-joint bent chain with a tube skinned to it, one clip of every interpolation.

    The chain hangs from a Z-up-to-Y-up anchor (like CesiumMan's ``Z_UP``) when ``anchor``.
    Inverse binds match the rest pose.
    """
    rot = Rotation.from_euler
    names = ("root", "mid", "tip")
    parents = np.array([-1, 0, 1])
    T = np.array([[0.1, 0.0, 0.2], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    R = np.stack([rot("y", 10, degrees=True).as_quat(), rot("z", 30, degrees=True).as_quat(),
                  rot("x", -20, degrees=True).as_quat()])
    S = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    anchors = ()
    root_anchor = None
    if anchor:
        zup = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
        anchors = (Anchor("Z_UP", zup), Anchor("Armature", trs_to_matrix([0, 0, 0.5], [0, 0, 0, 1], [1, 1, 1]), 0))
        root_anchor = np.array([1, -1, -1])
    sk = Skeleton(names, parents, T, R, S, np.eye(4)[None].repeat(3, 0), anchors, root_anchor)
    worlds = sk.rest_worlds()
    sk = Skeleton(names, parents, T, R, S, np.linalg.inv(worlds), anchors, root_anchor)
    # a tube around the bones: rings along each segment root->mid->tip->tip+(0,0.8,0)
    ends = np.concatenate([worlds[:, :3, 3], (worlds[2] @ [0, 0.8, 0, 1])[None, :3]])
    rings, ring_n = 12, 8
    V, W = [], []
    for s in range(3):
        a, b = ends[s], ends[s + 1]
        axis = (b - a) / np.linalg.norm(b - a)
        u = np.cross(axis, [0.3, 0.1, 0.9])
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        for i in range(rings):
            f = (i + 0.5) / rings
            c = a + f * (b - a)
            for k in range(ring_n):
                ang = 2 * np.pi * k / ring_n
                V.append(c + 0.15 * (np.cos(ang) * u + np.sin(ang) * v))
                w = np.zeros(3)
                if s < 2 and f > 0.6:  # blend into the next joint near the end of the segment
                    w[s + 1] = (f - 0.6) / 0.8
                    w[s] = 1 - w[s + 1]
                elif s > 0 and f < 0.4:
                    w[s - 1] = (0.4 - f) / 0.8
                    w[s] = 1 - w[s - 1]
                else:
                    w[s] = 1.0
                W.append(w)
    V, W = np.array(V), np.array(W)
    order = np.argsort(-W, axis=1, kind="stable")
    joints = order[:, :2]
    weights = np.take_along_axis(W, joints, axis=1)
    joints = np.concatenate([joints, np.zeros((len(V), 2), int)], axis=1)  # padded slots
    weights = np.concatenate([weights, np.zeros((len(V), 2))], axis=1)
    faces = []
    for s in range(3):
        for i in range(rings - 1):
            for k in range(ring_n):
                a0 = (s * rings + i) * ring_n + k
                a1 = (s * rings + i) * ring_n + (k + 1) % ring_n
                faces += [[a0, a1, a1 + ring_n], [a0, a1 + ring_n, a0 + ring_n]]
    mesh = Mesh("tube", V, np.array(faces), joints=joints, weights=weights)
    kt = np.array([0.0, 0.5, 1.0, 1.5])
    tracks = (
        Track(0, "translation", kt, [[0.1, 0, 0.2], [0.2, 0.1, 0.2], [0.1, 0.3, 0.1], [0.1, 0, 0.2]], "STEP"),
        Track(1, "rotation", kt, rot("z", [[30], [80], [-20], [30]], degrees=True).as_quat(), "LINEAR"),
        Track(2, "rotation", kt[:3], rot("xy", [[-20, 0], [40, 30], [-20, 0]], degrees=True).as_quat(), "LINEAR"),
        Track(2, "scale", kt[:2], np.array([[[0, 0, 0], [1, 1, 1], [0.5, 0, 0]],
                                            [[0, 0.2, 0], [1.2, 0.9, 1.0], [0, 0, 0]]]), "CUBICSPLINE"),
    )
    return Character("chain", sk, (mesh,), (Clip("bend", tracks),))


# ---------------------------------------------------------------------------------------------
# slow, obviously correct references (loop over vertices)


def lbs_reference(V, joints, weights, M):
    out = np.zeros((len(V), 3))
    for i in range(len(V)):
        acc = np.zeros(4)
        for j, w in zip(joints[i], weights[i]):
            acc += w * (M[j] @ np.append(V[i], 1.0))
        out[i] = acc[:3]
    return out


def dqs_reference(V, joints, weights, M):
    """Per vertex: polar split, blend scaled parts linearly, blend (q, t) as dual quaternions."""

    def qmul(a, b):  # wxyz
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])

    out = np.zeros((len(V), 3))
    for i in range(len(V)):
        pivot = joints[i][np.argmax(weights[i])]
        Qp, _ = polar(M[pivot][:3, :3])
        qp = Rotation.from_matrix(Qp).as_quat(scalar_first=True)
        real, dual, Pb = np.zeros(4), np.zeros(4), np.zeros((3, 3))
        for j, w in zip(joints[i], weights[i]):
            Q, P = polar(M[j][:3, :3])
            if np.linalg.det(Q) < 0:
                Q, P = -Q, -P
            q = Rotation.from_matrix(Q).as_quat(scalar_first=True)
            if q @ qp < 0:
                q = -q
            d = 0.5 * qmul(np.append(0.0, M[j][:3, 3]), q)
            real += w * q
            dual += w * d
            Pb += w * P
        nrm = np.linalg.norm(real)
        real, dual = real / nrm, dual / nrm
        t = 2 * qmul(dual, real * [1, -1, -1, -1])[1:]
        out[i] = Rotation.from_quat(real, scalar_first=True).apply(Pb @ V[i]) + t
    return out


# ---------------------------------------------------------------------------------------------
# tests


@pytest.mark.parametrize("method", [linear_blend_skinning, dual_quaternion_skinning])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rigid_transform_on_every_joint(method, seed):
    """gpytoolbox's invariant: the same rigid transform on every joint moves the mesh rigidly."""
    rng = np.random.default_rng(seed)
    V = rng.normal(size=(200, 3))
    joints, weights = random_influences(rng, 200, 4, 7)
    M = np.broadcast_to(random_rigid(rng), (7, 4, 4))
    U = method(V, joints, weights, M)
    np.testing.assert_allclose(U, V @ M[0, :3, :3].T + M[0, :3, 3], atol=1e-12)


def test_lbs_matches_reference_on_affine_frames():
    rng = np.random.default_rng(3)
    V = rng.normal(size=(60, 3))
    joints, weights = random_influences(rng, 60, 4, 5)
    M = random_rigid(rng, (3, 2, 5))
    M[..., :3, :3] *= rng.uniform(0.5, 2.0, size=(3, 2, 5, 1, 3))  # non-uniform scale
    U = linear_blend_skinning(V, joints, weights, M)
    assert U.shape == (3, 2, 60, 3)
    for a in range(3):
        for b in range(2):
            np.testing.assert_allclose(U[a, b], lbs_reference(V, joints, weights, M[a, b]), atol=1e-12)


def test_skinning_operator_is_linear_blend_skinning():
    """The sparse form gives the reference's positions, and its row differences the posed edges."""
    from rigmix.skinning import skinning_columns, skinning_operator

    rng = np.random.default_rng(7)
    V = rng.normal(size=(60, 3))
    joints, weights = random_influences(rng, 60, 4, 5)
    M = random_rigid(rng, (7, 5))
    M[..., :3, :3] *= rng.uniform(0.5, 2.0, size=(7, 5, 1, 3))
    B = skinning_operator(V, joints, weights, 5)
    U = (B @ skinning_columns(M)).reshape(60, 7, 3).transpose(1, 0, 2)
    for f in range(7):
        np.testing.assert_allclose(U[f], lbs_reference(V, joints, weights, M[f]), atol=1e-12)
    edges = ((B[1:] - B[:-1]) @ skinning_columns(M)).reshape(59, 7, 3).transpose(1, 0, 2)
    np.testing.assert_allclose(edges, U[:, 1:] - U[:, :-1], atol=1e-12)
    with pytest.raises(ValueError, match="out of range"):
        skinning_operator(V, joints, weights, 4)


@pytest.mark.parametrize("scaled", [False, True])
def test_dqs_matches_reference(scaled):
    rng = np.random.default_rng(4)
    V = rng.normal(size=(60, 3))
    joints, weights = random_influences(rng, 60, 4, 5)
    M = random_rigid(rng, (4, 5))
    if scaled:
        M[..., :3, :3] = M[..., :3, :3] @ (rng.uniform(0.5, 2.0, size=(4, 5, 3, 1)) * np.eye(3))
    U = dual_quaternion_skinning(V, joints, weights, M)
    for f in range(4):
        np.testing.assert_allclose(U[f], dqs_reference(V, joints, weights, M[f]), atol=1e-10)


def test_dqs_equals_lbs_for_single_influence():
    rng = np.random.default_rng(5)
    V = rng.normal(size=(100, 3))
    joints = rng.integers(0, 6, size=(100, 4))
    weights = np.zeros((100, 4))
    weights[np.arange(100), rng.integers(0, 4, size=100)] = 1.0
    M = random_rigid(rng, (3, 6))
    for scale in ([1.0, 1.0, 1.0], [2.5, 2.5, 2.5], [0.5, 1.5, 3.0]):
        Ms = M.copy()
        Ms[..., :3, :3] = Ms[..., :3, :3] * np.asarray(scale)  # scale applied first (T R S)
        np.testing.assert_allclose(dual_quaternion_skinning(V, joints, weights, Ms),
                                   linear_blend_skinning(V, joints, weights, Ms), atol=1e-10)


def test_frame_chunking_gives_the_same_result(monkeypatch):
    rng = np.random.default_rng(6)
    V = rng.normal(size=(50, 3))
    joints, weights = random_influences(rng, 50, 4, 5)
    M = random_rigid(rng, (13, 5))
    full_l = linear_blend_skinning(V, joints, weights, M)
    full_d = dual_quaternion_skinning(V, joints, weights, M)
    monkeypatch.setattr(skinning, "_CHUNK_ELEMENTS", 50 * 4 * 20)  # about one frame per chunk
    np.testing.assert_array_equal(linear_blend_skinning(V, joints, weights, M), full_l)
    np.testing.assert_allclose(dual_quaternion_skinning(V, joints, weights, M), full_d, atol=1e-14)


@pytest.mark.parametrize("anchor", [False, True])
def test_rest_pose_reproduces_bind_mesh(anchor):
    ch = chain_character(anchor)
    np.testing.assert_allclose(rest_skinning_matrices(ch.skeleton), np.eye(4)[None].repeat(3, 0), atol=1e-12)
    for method in ("lbs", "dqs"):
        (U,) = rest_pose(ch, method=method)
        np.testing.assert_allclose(U, ch.meshes[0].positions, atol=1e-12)


def test_rest_pose_differs_when_inverse_binds_do_not_match():
    ch = chain_character()
    sk = ch.skeleton
    ib = sk.inverse_binds.copy()
    ib[1] = ib[1] @ trs_to_matrix([0, 0.1, 0], [0, 0, 0, 1], [1, 1, 1])
    ch2 = replace(ch, skeleton=replace(sk, inverse_binds=ib))
    (U,) = rest_pose(ch2)
    mesh = ch.meshes[0]
    M = sk.rest_worlds() @ ib
    np.testing.assert_allclose(U, lbs_reference(mesh.positions, mesh.joints, mesh.weights, M), atol=1e-12)
    assert np.abs(U - mesh.positions).max() > 0.05


def test_skinning_matrices_compose_world_and_inverse_bind():
    ch = chain_character()
    sk = ch.skeleton
    rng = np.random.default_rng(7)
    T = sk.translations + rng.normal(scale=0.1, size=(4, 3, 3))
    R = Rotation.random(12, random_state=rng).as_quat().reshape(4, 3, 4)
    S = rng.uniform(0.8, 1.2, size=(4, 3, 3))
    M = skinning_matrices(sk, T, R, S)
    for f in range(4):
        L = [trs_to_matrix(T[f, j], R[f, j], S[f, j]) for j in range(3)]
        A = sk.anchor_worlds()
        W0 = A[1] @ L[0]
        W1 = W0 @ L[1]
        W2 = W1 @ L[2]
        np.testing.assert_allclose(M[f], np.stack([W0, W1, W2]) @ sk.inverse_binds, atol=1e-12)


def _cylinder(rings=41, ring_n=16, length=2.0, radius=0.2):
    x = np.linspace(0, length, rings)
    ang = 2 * np.pi * np.arange(ring_n) / ring_n
    X, A = np.meshgrid(x, ang, indexing="ij")
    V = np.stack([X, radius * np.cos(A), radius * np.sin(A)], axis=-1).reshape(-1, 3)
    w1 = np.clip((V[:, 0] - 0.5) / 1.0, 0, 1)  # linear blend over x in [0.5, 1.5]
    joints = np.tile([0, 1], (len(V), 1))
    weights = np.stack([1 - w1, w1], axis=1)
    return V, joints, weights


def test_dqs_avoids_candy_wrapper():
    """Twisting the second joint 170 degrees about the bone: LBS collapses, DQS keeps radius."""
    V, joints, weights = _cylinder()
    M = np.eye(4)[None].repeat(2, 0)
    R = Rotation.from_euler("x", 170, degrees=True).as_matrix()
    M[1, :3, :3] = R  # rotation about the x axis (the bone), which passes through the origin
    radius_lbs = np.linalg.norm(linear_blend_skinning(V, joints, weights, M)[:, 1:], axis=1)
    radius_dqs = np.linalg.norm(dual_quaternion_skinning(V, joints, weights, M)[:, 1:], axis=1)
    assert radius_lbs.min() < 0.2 * 0.1  # candy wrapper: the mid ring nearly collapses
    np.testing.assert_allclose(radius_dqs, 0.2, atol=1e-12)
    U = dual_quaternion_skinning(V, joints, weights, M)
    np.testing.assert_allclose(U[:, 0], V[:, 0], atol=1e-12)  # no sliding along the bone


def test_skin_character_clip_frames_match_reference():
    from rigmix.animation import clip_times, sample_clip

    ch = chain_character()
    t = clip_times(ch.clips[0])
    T, R, S = sample_clip(ch.skeleton, ch.clips[0], t)
    (U,) = skin_character(ch, T, R, S)
    (D,) = skin_character(ch, T, R, S, method="dqs")
    M = skinning_matrices(ch.skeleton, T, R, S)
    mesh = ch.meshes[0]
    assert U.shape == (len(t), len(mesh.positions), 3)
    for f in (0, len(t) // 2, len(t) - 1):
        np.testing.assert_allclose(U[f], lbs_reference(mesh.positions, mesh.joints, mesh.weights, M[f]), atol=1e-12)
        np.testing.assert_allclose(D[f], dqs_reference(mesh.positions, mesh.joints, mesh.weights, M[f]), atol=1e-10)
    with pytest.raises(ValueError):
        skin_character(ch, T, R, S, method="cor")


def test_bad_joint_index_is_reported():
    with pytest.raises(ValueError, match="joint index out of range"):
        linear_blend_skinning(np.zeros((2, 3)), [[0], [3]], [[1.0], [1.0]], np.eye(4)[None].repeat(3, 0))


# ---------------------------------------------------------------------------------------------
# real characters


def _read(name):
    return read_gltf(asset(name))


@pytest.mark.parametrize("name", ["CesiumMan", "Fox", "Horse"])
def test_real_character_lbs_matches_reference(name):
    from rigmix.animation import sample_clip

    ch = _read(name)
    clip = ch.clips[0]
    t = np.linspace(clip.start, clip.end, 3)
    T, R, S = sample_clip(ch.skeleton, clip, t)
    M = skinning_matrices(ch.skeleton, T, R, S)
    posed = skin_character(ch, T, R, S)
    rng = np.random.default_rng(8)
    for mesh, U in zip(ch.meshes, posed):
        if not mesh.skinned:
            continue
        idx = rng.choice(len(mesh.positions), size=min(60, len(mesh.positions)), replace=False)
        for f in range(3):
            ref = lbs_reference(mesh.positions[idx], mesh.joints[idx], mesh.weights[idx], M[f])
            np.testing.assert_allclose(U[f, idx], ref, atol=1e-9)
        # DQS on a real rig stays close to LBS (no vertex flies off): within 10% of the extent
        D = dual_quaternion_skinning(mesh.positions, mesh.joints, mesh.weights, M)
        diag = np.linalg.norm(np.ptp(U.reshape(-1, 3), axis=0))
        assert np.abs(D - U).max() < 0.1 * diag


def test_rest_at_bind_keeps_every_animation_exact():
    """The Knight is bound in another pose than its stored rest (arms): composed in its bind
    pose, every clip skins to the same vertices, and at rest all weighted joints share one
    skinning matrix (the mesh is one similarity of its bind-space positions)."""
    from conftest import asset

    from rigmix.animation.sampling import clip_times, sample_clip
    from rigmix.io import load_character
    from rigmix.skinning import rest_at_bind, skin_character

    knight = load_character(asset("Knight"))
    bound = rest_at_bind(knight)
    assert bound is not knight and bound.meshes == knight.meshes
    M = bound.skeleton.rest_worlds() @ bound.skeleton.inverse_binds
    mass = np.zeros(bound.skeleton.num_joints)
    for m in bound.meshes:
        np.add.at(mass, m.joints.ravel(), m.weights.ravel())
    weighted = np.flatnonzero(mass > 0)
    assert np.abs(M[weighted] - M[weighted[0]]).max() < 1e-3  # float32 inverse binds
    M0 = knight.skeleton.rest_worlds() @ knight.skeleton.inverse_binds
    assert np.abs(M0[weighted] - M0[weighted[0]]).max() > 1.0  # the stored rest is another pose
    for before, after in zip(knight.clips, bound.clips):
        t = clip_times(before, 30.0)[::7]
        for a, b in zip(skin_character(knight, *sample_clip(knight.skeleton, before, t)),
                        skin_character(bound, *sample_clip(bound.skeleton, after, t))):
            assert np.allclose(a, b, atol=1e-9)


def test_rest_at_bind_leaves_a_rig_bound_at_rest():
    from conftest import asset

    from rigmix.io import load_character
    from rigmix.skinning import rest_at_bind

    cesium = load_character(asset("CesiumMan"))
    assert rest_at_bind(cesium) is cesium


def test_positioning_pose_chooses_the_pose_composed_in(tmp_path):
    from conftest import asset

    from rigmix.config import load_config
    from rigmix.io import load_character
    from rigmix.pipeline import load_characters

    path = asset("Knight")
    stored = load_character(path).skeleton.rotations
    for pose, same in (("bind", False), ("rest", True)):
        cfg = tmp_path / f"{pose}.toml"
        cfg.write_text(f'[characters.k]\npath = "{path}"\n[positioning]\npose = "{pose}"\n')
        rotations = load_characters(load_config(cfg))["k"].skeleton.rotations
        assert np.array_equal(rotations, stored) is same, pose
