"""The built-in example characters (rigmix.examples): geometry, skin, skeleton, clips, files."""

from __future__ import annotations

import numpy as np
import pytest

from rigmix import examples
from rigmix.animation import sample_clip
from rigmix.errors import UnsupportedError
from rigmix.geometry import weld
from rigmix.skinning import skin_character, skinning_matrices


@pytest.fixture(scope="module")
def humanoid():
    return examples.humanoid()


@pytest.fixture(scope="module")
def quadruped():
    return examples.quadruped()


@pytest.fixture(scope="module", params=["humanoid", "quadruped"])
def character(request, humanoid, quadruped):
    return {"humanoid": humanoid, "quadruped": quadruped}[request.param]


def _edges(F):
    return np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])


def _components(n, F):
    """Connected components of the vertex graph (union-find)."""
    parent = np.arange(n)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in _edges(F):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    return len({find(i) for i in range(n)})


def test_mesh_is_one_closed_oriented_genus0_surface(character):
    (mesh,) = character.meshes
    V, index, F = weld(mesh.positions, mesh.faces)
    assert len(V) == len(mesh.positions)  # already welded: no duplicate positions
    E = _edges(F)
    # every directed edge once and its opposite once: closed, 2-manifold, consistently oriented
    assert len(np.unique(E, axis=0)) == len(E)
    assert {tuple(e) for e in E[:, ::-1].tolist()} == {tuple(e) for e in E.tolist()}
    euler = len(V) - len(E) // 2 + len(F)
    assert euler == 2
    assert _components(len(V), F) == 1
    # outward orientation: positive signed volume
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 0
    # no degenerate triangles
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    assert area.min() > 1e-7
    # normals are unit and point outward (agree with the face normals around each vertex)
    N = mesh.normals
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-9)
    fn = np.cross(b - a, c - a)
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    assert np.mean(np.einsum("ij,ij->i", N[F[:, 0]], fn) > 0.5) > 0.99


def test_sizes_axes_and_facing(humanoid, quadruped):
    V = humanoid.meshes[0].positions
    ext = V.max(0) - V.min(0)
    assert 1.7 < ext[1] < 1.9 and abs(V[:, 1].min()) < 0.01  # ~1.8 m tall, feet on the ground
    assert abs(V[:, 0].max() + V[:, 0].min()) < 0.02  # symmetric in x
    head = V[V[:, 1] > 1.55]
    nose = head[np.argmax(head[:, 2])]
    assert nose[2] > 0.1 and abs(nose[0]) < 0.02 and head[:, 2].min() > -0.1  # nose at +Z
    feet = V[V[:, 1] < 0.05]
    assert feet[:, 2].max() > 0.15 > -feet[:, 2].min()  # toes point to +Z
    Q = quadruped.meshes[0].positions
    qext = Q.max(0) - Q.min(0)
    assert 1.1 < qext[1] < 1.45 and 1.9 < qext[2] < 2.3 and abs(Q[:, 1].min()) < 0.01
    sk = quadruped.skeleton
    assert sk.rest_worlds()[sk.index("Head"), 2, 3] > 0 > sk.rest_worlds()[sk.index("Tail.3"), 2, 3]


def test_skeleton_names_and_topology(humanoid, quadruped):
    assert humanoid.skeleton.names == examples.HUMANOID_JOINTS
    assert quadruped.skeleton.names == examples.QUADRUPED_JOINTS
    for c in (humanoid, quadruped):
        sk = c.skeleton
        assert np.all(sk.parents < np.arange(sk.num_joints))
        assert list(sk.roots) == [sk.index("Hips")]
        # bind pose = rest pose: skinning matrices are identity
        M = skinning_matrices(sk, sk.translations, sk.rotations, sk.scales)
        np.testing.assert_allclose(M, np.broadcast_to(np.eye(4), M.shape), atol=1e-12)
    hs = humanoid.skeleton
    for side in "LR":
        chain = [f"Shoulder.{side}", f"UpperArm.{side}", f"LowerArm.{side}", f"Hand.{side}"]
        assert [hs.names[hs.parents[hs.index(n)]] for n in chain] == ["Chest"] + chain[:-1]
        chain = [f"UpperLeg.{side}", f"LowerLeg.{side}", f"Foot.{side}"]
        assert [hs.names[hs.parents[hs.index(n)]] for n in chain] == ["Hips"] + chain[:-1]
    qs = quadruped.skeleton
    for end, parent in (("Front", "Chest"), ("Back", "Hips")):
        for side in "LR":
            chain = [f"{end}UpperLeg.{side}", f"{end}LowerLeg.{side}", f"{end}Foot.{side}"]
            assert [qs.names[qs.parents[qs.index(n)]] for n in chain] == [parent] + chain[:-1]


def test_skin_weights(character):
    (mesh,) = character.meshes
    J = character.skeleton.num_joints
    assert mesh.joints.shape == mesh.weights.shape == (len(mesh.positions), 4)
    assert mesh.weights.min() >= 0
    np.testing.assert_allclose(mesh.weights.sum(axis=1), 1.0, atol=1e-12)
    assert mesh.joints.min() >= 0 and mesh.joints.max() < J
    assert np.all(mesh.joints[mesh.weights == 0] == 0)  # unused slots: joint 0, weight 0
    # every joint drives some vertices; some vertices blend (smooth weights, not rigid)
    W = mesh.dense_weights(J)
    assert np.all(W.max(axis=0) > 0.5)
    assert np.mean(W.max(axis=1) < 0.9) > 0.1
    # weights follow the geometry: hand vertices are driven by the hand
    if "Hand.L" in character.skeleton.names:
        x = mesh.positions[:, 0]
        tip = x > x.max() - 0.05
        assert np.all(W[tip, character.skeleton.index("Hand.L")] > 0.9)


def test_colors_uvs_material(character):
    (mesh,) = character.meshes
    assert mesh.colors.shape == (len(mesh.positions), 4)
    assert mesh.colors.min() >= 0 and mesh.colors.max() <= 1
    assert len(np.unique(np.round(mesh.colors, 2), axis=0)) > 3  # several colours
    (uv,) = mesh.uvs
    assert uv.min() >= 0 and uv.max() <= 1
    assert mesh.material == 0 and len(character.materials) == 1


def _joint_positions(character, clip, times):
    from rigmix.transforms import trs_to_matrix

    T, R, S = sample_clip(character.skeleton, clip, times)
    return character.skeleton.world_matrices(trs_to_matrix(T, R, S))[..., :3, 3]


@pytest.mark.parametrize("name", ["walk", "idle"])
def test_humanoid_clips_move_the_limbs(humanoid, name):
    clip = humanoid.clip(name)
    assert all(t.interpolation == "LINEAR" for t in clip.tracks)
    assert clip.duration > 0.5
    times = np.linspace(clip.start, clip.end, 61)
    P = _joint_positions(humanoid, clip, times)
    sk = humanoid.skeleton
    # loops: the first and last frames agree
    np.testing.assert_allclose(P[0], P[-1], atol=1e-9)
    if name == "walk":
        for side in "LR":
            foot = P[:, sk.index(f"Foot.{side}")]
            hand = P[:, sk.index(f"Hand.{side}")]
            assert np.ptp(foot[:, 2]) > 0.3  # the legs swing forward and back
            assert np.ptp(hand[:, 2]) > 0.2  # so do the arms
            assert hand[:, 1].max() < 1.1  # arms hang down (T pose at rest)
        # arms swing opposite to the leg of the same side
        foot_l = P[:, sk.index("Foot.L"), 2]
        hand_l = P[:, sk.index("Hand.L"), 2]
        assert np.corrcoef(foot_l, hand_l)[0, 1] < -0.8
        # the left and right legs alternate
        assert np.corrcoef(foot_l, P[:, sk.index("Foot.R"), 2])[0, 1] < -0.8
    else:
        head = P[:, sk.index("Head")]
        assert 0.0 < np.ptp(head, axis=0).max() < 0.05  # breathing and looking: small motion
        feet = P[:, [sk.index("Foot.L"), sk.index("Foot.R")]]
        assert np.ptp(feet[..., 1], axis=0).max() < 0.02  # feet stay on the ground


@pytest.mark.parametrize("name", ["walk", "trot", "idle"])
def test_quadruped_clips_move_the_limbs(quadruped, name):
    clip = quadruped.clip(name)
    assert all(t.interpolation == "LINEAR" for t in clip.tracks)
    times = np.linspace(clip.start, clip.end, 49)
    P = _joint_positions(quadruped, clip, times)
    sk = quadruped.skeleton
    np.testing.assert_allclose(P[0], P[-1], atol=1e-9)
    feet = P[:, [sk.index(f"{e}Foot.{s}") for e in ("Front", "Back") for s in "LR"], 2]
    if name == "idle":
        assert np.ptp(feet, axis=0).max() < 0.02
        assert np.ptp(P[:, sk.index("Head")], axis=0).max() > 0.05  # looks around
    else:
        assert np.all(np.ptp(feet, axis=0) > 0.2)
        c = np.corrcoef(feet.T)  # order: FL, FR, BL, BR
        assert c[0, 1] < -0.8 and c[2, 3] < -0.8  # left and right alternate
        if name == "trot":
            assert c[0, 3] > 0.7 and c[1, 2] > 0.7  # diagonal pairs move together


def test_skinned_mesh_follows_the_pose(humanoid):
    clip = humanoid.clip("walk")
    T, R, S = sample_clip(humanoid.skeleton, clip, [0.25, 0.75])
    (Vs,) = skin_character(humanoid, T, R, S)
    rest = humanoid.meshes[0].positions
    moved = np.linalg.norm(Vs - rest, axis=-1)
    assert moved.max() > 0.3  # hands and feet move a lot
    # the head barely moves relative to the hips' bob
    head = humanoid.meshes[0].dense_weights(humanoid.skeleton.num_joints)[:, humanoid.skeleton.index("Head")] > 0.99
    assert moved[:, head].max() < 0.15
    # no vertex flies away: skinned edge lengths stay within a factor of the rest ones
    F = humanoid.meshes[0].faces
    e_rest = np.linalg.norm(rest[F[:, 0]] - rest[F[:, 1]], axis=1)
    e_pose = np.linalg.norm(Vs[:, F[:, 0]] - Vs[:, F[:, 1]], axis=-1)
    assert np.all(e_pose < 3 * e_rest + 0.01)


def test_deterministic():
    a, b = examples.quadruped(), examples.quadruped()
    for ma, mb in zip(a.meshes, b.meshes):
        for attr in ("positions", "faces", "normals", "colors", "joints", "weights"):
            assert np.array_equal(getattr(ma, attr), getattr(mb, attr)), attr
        assert np.array_equal(ma.uvs[0], mb.uvs[0])
    assert np.array_equal(a.skeleton.inverse_binds, b.skeleton.inverse_binds)
    for ca, cb in zip(a.clips, b.clips):
        assert ca.name == cb.name
        for ta, tb in zip(ca.tracks, cb.tracks):
            assert np.array_equal(ta.values, tb.values) and np.array_equal(ta.times, tb.times)


def test_static_box():
    box = examples.static_box((1.0, 2.0, 3.0))
    assert not box.skinned and box.skeleton.num_joints == 0 and not box.meshes
    (prop,) = box.props
    V, _, F = weld(prop.mesh.positions, prop.mesh.faces)
    assert len(V) == 8 and len(F) == 12
    np.testing.assert_allclose(V.max(0) - V.min(0), [1.0, 2.0, 3.0])
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    assert np.isclose(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6, 6.0)  # outward
    # flat normals agree with the faces' orientation
    P, N, Fs = prop.mesh.positions, prop.mesh.normals, prop.mesh.faces
    fn = np.cross(P[Fs[:, 1]] - P[Fs[:, 0]], P[Fs[:, 2]] - P[Fs[:, 0]])
    assert np.all(np.einsum("ij,ij->i", fn, N[Fs[:, 0]]) > 0)
    with pytest.raises(UnsupportedError):
        box.require_skinned()


def test_written_files_read_back_and_validate(tmp_path, humanoid, quadruped):
    from rigmix.io import load_character
    from rigmix.io.gltf import write_gltf
    from rigmix.io.validator import validate_gltf, validator_available

    for c in (humanoid, quadruped, examples.static_box()):
        path = tmp_path / f"{c.name}.glb"
        write_gltf(c, path)
        back = load_character(path)
        assert back.skeleton.names == c.skeleton.names
        assert [k.name for k in back.clips] == [k.name for k in c.clips]
        assert back.skinned == c.skinned
        if c.meshes:
            np.testing.assert_allclose(back.meshes[0].positions, c.meshes[0].positions, atol=1e-6)
        if validator_available():
            assert validate_gltf(path)["issues"]["numErrors"] == 0
