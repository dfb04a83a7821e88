"""glTF/GLB reading and writing: the shared characters, a synthetic file exercising the layout
features, round trips, repairs, and unreadable inputs."""

from __future__ import annotations

import base64
import io
import json
import struct

import numpy as np
import pytest
from conftest import CHARACTERS, asset

from rigmix.animation import sample_clip, sample_track
from rigmix.character import Character, Clip, Mesh
from rigmix.errors import InputError, UnsupportedError
from rigmix.geometry import bounding_box_diagonal
from rigmix.io import load_character
from rigmix.io.gltf import read_gltf, repair_weights, sparsify_weights, write_gltf
from rigmix.skinning import linear_blend_skinning, skinning_matrices
from rigmix.transforms import quat_normalize, trs_to_matrix

# Counts from ../shared/data/characters/README.md (measured there with other tools).
EXPECTED = {  # joints, vertices, triangles, clips, roots, rest-pose world extent
    "CesiumMan": (19, 3273, 4672, 1, 1, [1.138, 1.507, 0.312]),
    "RiggedFigure": (19, 370, 256, 1, 1, [1.178, 1.45, 0.326]),
    "Knight": (31, 2058, 956, 12, 1, [2.213, 5.587, 1.365]),
    "Fox": (24, 1728, 576, 3, 1, [25.186, 79.029, 154.72]),
    "Horse": (50, 4400, 2182, 13, 5, [1.412, 4.833, 5.691]),
    "Wasp": (29, 7472, 3734, 3, 1, [3.856, 3.528, 2.491]),
    "Velociraptor": (29, 2576, 1248, 6, 1, [2.636, 6.075, 12.74]),
    "SimpleSkin": (2, 10, 8, 1, 1, [1.0, 2.0, 0.0]),
}

_READ: dict = {}


def original(name: str) -> Character:
    if name not in _READ:
        _READ[name] = read_gltf(asset(name))
    return _READ[name]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """name -> (path of the GLB written from the original, the character read back)."""
    out, folder = {}, tmp_path_factory.mktemp("roundtrip")

    def get(name):
        if name not in out:
            path = folder / f"{name}.glb"
            write_gltf(original(name), path)
            out[name] = (path, read_gltf(path))
        return out[name]

    return get


def skinned_frames(character: Character, clip: Clip, times) -> list[np.ndarray]:
    """World positions ``(F, n, 3)`` of every skinned mesh at ``times``."""
    T, R, S = sample_clip(character.skeleton, clip, times)
    M = skinning_matrices(character.skeleton, T, R, S)
    return [linear_blend_skinning(m.positions, m.joints, m.weights, M) for m in character.meshes]


# --------------------------------------------------------------------------- shared characters


@pytest.mark.parametrize("name", sorted(CHARACTERS))
def test_read_shared_character(name):
    c = original(name)
    J, nv, nt, nclips, nroots, extent = EXPECTED[name]
    sk = c.skeleton
    assert sk.num_joints == J and len(set(sk.names)) == J
    assert np.all(sk.parents < np.arange(J))
    assert len(sk.roots) == nroots
    assert sum(len(m.positions) for m in c.meshes) == nv
    assert sum(len(m.faces) for m in c.meshes) == nt
    assert len(c.clips) == nclips and c.skinned
    np.testing.assert_allclose(np.linalg.norm(sk.rotations, axis=1), 1.0, atol=1e-6)
    M = skinning_matrices(sk, sk.translations, sk.rotations, sk.scales)
    rest = [linear_blend_skinning(m.positions, m.joints, m.weights, M) for m in c.meshes]
    allrest = np.concatenate(rest)
    axes = [0, 2] if name == "Wasp" else [0, 1, 2]  # README's Wasp y-min of 0 is its 6 NaN
    # vertices collapsed to the origin; ours are repaired (bound to their nearest joint)
    np.testing.assert_allclose(np.ptp(allrest, axis=0)[axes], np.array(extent)[axes], atol=2e-3 * max(extent))
    for m, U in zip(c.meshes, rest):
        assert m.faces.min() >= 0 and m.faces.max() < len(m.positions)
        assert np.all(np.isfinite(m.weights)) and m.weights.min() >= 0
        np.testing.assert_allclose(m.weights.sum(axis=1), 1.0, atol=1e-9)
        assert m.joints.min() >= 0 and m.joints.max() < J
        assert np.all(m.joints[m.weights == 0] == 0)  # unused slots: joint 0
    for clip in c.clips:
        for tr in clip.tracks:
            assert np.all(np.diff(tr.times) > 0) and 0 <= tr.joint < J


def test_known_defects_are_repaired_and_reported():
    wasp = original("Wasp")
    nan_msgs = [w for w in wasp.warnings if "NaN" in w]
    assert {w.split("'")[1] for w in nan_msgs} == {"Wasp.0", "Wasp.2"}
    assert all(w.startswith("Wasp.glb: mesh 'Wasp.") and " 3 vertices " in w for w in nan_msgs)
    horse = original("Horse")
    assert any("skeleton" in w and "Body" in w and w.startswith("Horse.glb:") for w in horse.warnings)
    assert [horse.skeleton.names[r] for r in horse.skeleton.roots] == [
        "Body", "IKBackLeg.L", "IKFrontLeg.L", "IKBackLeg.R", "IKFrontLeg.R"]
    assert not original("Fox").warnings and not original("CesiumMan").warnings


def test_cesium_man_anchor_and_simple_skin_names():
    sk = original("CesiumMan").skeleton
    assert [a.name for a in sk.anchors] == ["Z_UP", "Armature"]
    z_up = sk.anchors[0].matrix
    np.testing.assert_allclose(z_up[:3, :3] @ [0, 0, 1], [0, 1, 0], atol=1e-6)  # Z-up to Y-up
    assert list(sk.root_anchor[sk.roots]) == [1]
    simple = original("SimpleSkin")
    assert simple.skeleton.names == ("joint_1", "joint_2")
    assert [c.name for c in simple.clips] == ["clip_0"]


# --------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("name", sorted(CHARACTERS))
def test_round_trip(name, written):
    a = original(name)
    _, b = written(name)
    sa, sb = a.skeleton, b.skeleton
    assert sb.names == sa.names
    np.testing.assert_array_equal(sb.parents, sa.parents)
    np.testing.assert_array_equal(sb.root_anchor, sa.root_anchor)
    assert [x.name for x in sb.anchors] == [x.name for x in sa.anchors]
    np.testing.assert_allclose(sb.anchor_worlds(), sa.anchor_worlds(), atol=1e-6)
    np.testing.assert_allclose(sb.translations, sa.translations, atol=1e-6)
    np.testing.assert_allclose(sb.rotations, sa.rotations, atol=1e-6)
    np.testing.assert_allclose(sb.scales, sa.scales, atol=1e-6)
    np.testing.assert_allclose(sb.rest_worlds(), sa.rest_worlds(), atol=1e-6, rtol=1e-6)
    np.testing.assert_allclose(sb.inverse_binds, sa.inverse_binds, atol=1e-6, rtol=1e-6)
    assert [m.name for m in b.meshes] == [m.name for m in a.meshes]
    for ma, mb in zip(a.meshes, b.meshes):
        np.testing.assert_array_equal(mb.positions, ma.positions)  # float32 in, float32 out
        np.testing.assert_array_equal(mb.faces, ma.faces)
        np.testing.assert_allclose(mb.dense_weights(sa.num_joints), ma.dense_weights(sa.num_joints), atol=1e-6)
        assert len(mb.uvs) == len(ma.uvs) and mb.material == ma.material
        for ua, ub in zip(ma.uvs, mb.uvs):
            np.testing.assert_array_equal(ub, ua)
        if ma.normals is not None:
            na = ma.normals / np.linalg.norm(ma.normals, axis=1, keepdims=True)
            np.testing.assert_allclose(mb.normals, na, atol=1e-6)
    assert len(b.materials) == len(a.materials)
    for xa, xb in zip(a.materials, b.materials):
        np.testing.assert_allclose(xb.base_color, xa.base_color, atol=1e-7)
        assert (xa.base_color_texture is None) == (xb.base_color_texture is None)
        if xa.base_color_texture is not None:
            assert xb.base_color_texture.data == xa.base_color_texture.data
            assert xb.base_color_texture.mime_type == xa.base_color_texture.mime_type
    assert [c.name for c in b.clips] == [c.name for c in a.clips]
    assert not b.warnings  # what rigmix writes needs no repair
    for ca, cb in zip(a.clips, b.clips):
        assert [(t.joint, t.path, t.interpolation) for t in cb.tracks] == [
            (t.joint, t.path, t.interpolation) for t in ca.tracks]
        for ta, tb in zip(ca.tracks, cb.tracks):
            np.testing.assert_allclose(tb.times, ta.times, atol=1e-6)
            np.testing.assert_allclose(tb.values, ta.values, atol=1e-6)


@pytest.mark.parametrize("name", sorted(CHARACTERS))
def test_round_trip_skinned_vertices(name, written):
    """Skinned positions at every 1/30 s of every clip agree within 1e-5 x bbox diagonal."""
    a = original(name)
    _, b = written(name)
    diag = bounding_box_diagonal(np.concatenate([m.positions for m in a.meshes]))
    for ca, cb in zip(a.clips, b.clips):
        times = np.arange(ca.start, ca.end + 1e-9, 1.0 / 30.0)
        for Ua, Ub in zip(skinned_frames(a, ca, times), skinned_frames(b, cb, times)):
            assert np.abs(Ua - Ub).max() <= 1e-5 * diag, ca.name


@pytest.mark.parametrize("name", ["SimpleSkin", "CesiumMan"])
def test_gltf_embedded_output(name, tmp_path):
    path = tmp_path / f"{name}.gltf"
    write_gltf(original(name), path)
    gl = json.loads(path.read_text())
    assert gl["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    back = load_character(path)
    assert back.skeleton.names == original(name).skeleton.names
    for ma, mb in zip(original(name).meshes, back.meshes):
        np.testing.assert_array_equal(mb.positions, ma.positions)


# --------------------------------------------------------------------------- synthetic file

PNG = None


def png_bytes() -> bytes:
    global PNG
    if PNG is None:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(np.arange(48, dtype=np.uint8).reshape(4, 4, 3)).save(buf, format="PNG")
        PNG = buf.getvalue()
    return PNG


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.append(axis * np.sin(angle / 2), np.cos(angle / 2))


class Synth:
    """A small skinned glTF built in code, whose every value the test knows.

    Joints Root > Mid > Tip under a non-joint ``Anchor`` (matrix node), listed in the skin as
    ``[Tip, Mid, Root]`` (not parents-first). One skinned mesh (interleaved POSITION/NORMAL,
    sparse POSITION, UNSIGNED_BYTE indices, JOINTS_0 u8 + WEIGHTS_0 normalized u8, JOINTS_1 u16 +
    WEIGHTS_1 float, COLOR_0 normalized u16 VEC3, a texture), one rigid prop under Mid, and clips
    with STEP, CUBICSPLINE and LINEAR (normalized short quaternions) samplers.
    """

    anchor = trs_to_matrix([0.0, 0.0, 1.0], _rot([1, 0, 0], -np.pi / 2), [1.0, 1.0, 1.0])
    T = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # Root, Mid, Tip
    R = np.array([[0, 0, 0, 1.0], _rot([0, 0, 1], 0.3), [0, 0, 0, 1.0]])
    n = 8

    def __init__(self):
        rng = np.random.default_rng(7)
        n = self.n
        self.V = np.column_stack(
            [rng.uniform(-0.3, 0.3, n), np.linspace(0, 2, n), rng.uniform(-0.1, 0.1, n)]).astype(np.float32)
        self.sparse_idx = np.array([3, 5])
        self.sparse_val = np.array([[0.5, 0.6, 0.7], [-0.5, 1.6, 0.2]], np.float32)
        self.V_expected = self.V.astype(float).copy()
        self.V_expected[self.sparse_idx] = self.sparse_val
        N = rng.normal(size=(n, 3))
        self.N = (N / np.linalg.norm(N, axis=1, keepdims=True)).astype(np.float32)
        self.F = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4], [4, 5, 6], [5, 7, 6]], np.uint8)
        # skin-local joints: 0 Tip, 1 Mid, 2 Root
        self.J0 = np.tile(np.array([2, 1, 0, 0], np.uint8), (n, 1))
        self.W0 = np.tile(np.array([51, 102, 0, 0], np.uint8), (n, 1))  # 0.2, 0.4 normalized
        self.J1 = np.tile(np.array([0, 0, 0, 0], np.uint16), (n, 1))
        self.W1 = np.tile(np.array([0.4, 0, 0, 0], np.float32), (n, 1))
        self.J1[0, 0] = 2  # vertex 0: Root twice (0.2 + 0.4): a duplicate slot, summed
        self.C = rng.integers(0, 65536, size=(n, 3)).astype(np.uint16)
        self.UV = rng.uniform(0, 1, size=(n, 2)).astype(np.float32)
        self.q_short = np.round(quat_normalize([[0.1, 0.2, 0.3, 0.9], [0.0, 0.0, 0.6, 0.8]]) * 32767).astype(np.int16)
        self.cubic = np.array([  # 2 keys x (in, value, out) x xyzw
            [[0, 0, 0, 0], [0, 0, 0, 1], [0.1, 0, 0, 0]],
            [[0, 0.2, 0, 0], _rot([0, 1, 0], 0.5), [0, 0, 0, 0]],
        ], np.float32)

    # expected model values (joint order Root, Mid, Tip)
    def dense_expected(self):
        W = np.zeros((self.n, 3))
        W[:, 0], W[:, 1], W[:, 2] = 0.2, 0.4, 0.4  # skin-local Root=2 -> 0, Mid -> 1, Tip -> 2
        W[0] = [0.6, 0.4, 0.0]
        return W / W.sum(1, keepdims=True)

    def build(self, tmp_path, kind="glb", mutate=None, faces=None):
        """Write the file; ``kind`` in glb, gltf-octet, gltf-buffer, external."""
        data = bytearray()
        views, accs = [], []

        def view(raw, stride=None, target=None):
            data.extend(b"\0" * (-len(data) % 4))
            v = {"buffer": 0, "byteOffset": len(data), "byteLength": len(raw)}
            if stride:
                v["byteStride"] = stride
            if target:
                v["target"] = target
            data.extend(raw)
            views.append(v)
            return len(views) - 1

        def acc(arr, ctype, typ, *, v=None, offset=0, normalized=False, minmax=False, count=None):
            arr = np.asarray(arr)
            if v is None:
                v = view(np.ascontiguousarray(arr).tobytes())
            a = {"bufferView": v, "byteOffset": offset, "componentType": ctype,
                 "count": count or len(arr), "type": typ}
            if normalized:
                a["normalized"] = True
            if minmax:
                a["min"] = arr.reshape(len(arr), -1).min(0).tolist()
                a["max"] = arr.reshape(len(arr), -1).max(0).tolist()
            accs.append(a)
            return len(accs) - 1

        inter = np.zeros(self.n, dtype=[("p", "<f4", 3), ("nrm", "<f4", 3)])
        inter["p"], inter["nrm"] = self.V, self.N
        iv = view(inter.tobytes(), stride=24, target=34962)
        pos = acc(self.V_expected.astype(np.float32), 5126, "VEC3", v=iv, minmax=True)
        accs[pos]["sparse"] = {
            "count": 2,
            "indices": {"bufferView": view(self.sparse_idx.astype(np.uint16).tobytes()), "componentType": 5123},
            "values": {"bufferView": view(self.sparse_val.tobytes())},
        }
        nrm = acc(self.N, 5126, "VEC3", v=iv, offset=12)
        F = self.F if faces is None else faces
        ind = acc(F.reshape(-1), 5121, "SCALAR")
        # worlds of the joints at rest, for the inverse binds
        L = trs_to_matrix(self.T, self.R, np.ones((3, 3)))
        W_root = self.anchor @ L[0]
        W_mid = W_root @ L[1]
        W_tip = W_mid @ L[2]
        ibm = np.linalg.inv(np.stack([W_tip, W_mid, W_root])).transpose(0, 2, 1).reshape(3, 16).astype(np.float32)
        step_vals = np.array([[0, 1, 0], [0, 1.5, 0], [0, 1, 0]], np.float32)
        t3 = acc(np.array([0.0, 0.5, 1.0], np.float32), 5126, "SCALAR", minmax=True)
        t2 = acc(np.array([0.0, 1.0], np.float32), 5126, "SCALAR", minmax=True)
        gl = {
            "asset": {"version": "2.0"},
            "scene": 0,
            "scenes": [{"nodes": [0, 4]}],
            "nodes": [
                {"name": "Anchor", "matrix": self.anchor.T.reshape(16).tolist(), "children": [3]},
                {"name": "Tip", "translation": self.T[2].tolist()},
                {"name": "Mid", "translation": self.T[1].tolist(), "rotation": self.R[1].tolist(), "children": [1, 5]},
                {"name": "Root", "children": [2]},
                {"name": "Body", "mesh": 0, "skin": 0},
                {"name": "Hat", "mesh": 1, "translation": [0.0, 0.5, 0.0]},
            ],
            "skins": [{"joints": [1, 2, 3], "inverseBindMatrices": acc(ibm, 5126, "MAT4"), "skeleton": 0}],
            "meshes": [
                {"name": "Body", "primitives": [{
                    "attributes": {
                        "POSITION": pos, "NORMAL": nrm,
                        "TEXCOORD_0": acc(self.UV, 5126, "VEC2"),
                        "COLOR_0": acc(self.C, 5123, "VEC3", normalized=True),
                        "JOINTS_0": acc(self.J0, 5121, "VEC4"),
                        "WEIGHTS_0": acc(self.W0, 5121, "VEC4", normalized=True),
                        "JOINTS_1": acc(self.J1, 5123, "VEC4"),
                        "WEIGHTS_1": acc(self.W1, 5126, "VEC4"),
                    },
                    "indices": ind, "material": 0,
                }]},
                {"name": "Hat", "primitives": [{
                    "attributes": {"POSITION": acc(self.V[:3], 5126, "VEC3", minmax=True)}, "mode": 4}]},
            ],
            "materials": [{"name": "skin", "pbrMetallicRoughness": {
                "baseColorFactor": [1, 0.5, 0.25, 1], "baseColorTexture": {"index": 0}}}],
            "textures": [{"source": 0, "sampler": 0}],
            "samplers": [{"magFilter": 9729, "wrapS": 33071}],
            "animations": [
                {"name": "steps",
                 "samplers": [{"input": t3, "output": acc(step_vals, 5126, "VEC3"), "interpolation": "STEP"}],
                 "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}]},
                {"samplers": [
                    {"input": t2, "output": acc(self.cubic.reshape(6, 4), 5126, "VEC4"),
                     "interpolation": "CUBICSPLINE"},
                    {"input": t2, "output": acc(self.q_short, 5122, "VEC4", normalized=True)},
                    {"input": t2, "output": acc(step_vals[:2], 5126, "VEC3")},
                ], "channels": [
                    {"sampler": 0, "target": {"node": 2, "path": "rotation"}},
                    {"sampler": 1, "target": {"node": 3, "path": "rotation"}},
                    {"sampler": 2, "target": {"node": 0, "path": "translation"}},  # not a joint
                ]},
            ],
        }
        png = png_bytes()
        if kind == "glb":
            gl["images"] = [{"bufferView": view(png), "mimeType": "image/png"}]
        elif kind == "external":
            gl["images"] = [{"uri": "tex%20ture.png"}]
            (tmp_path / "tex ture.png").write_bytes(png)
        else:
            gl["images"] = [{"uri": "data:image/png;base64," + base64.b64encode(png).decode()}]
        data.extend(b"\0" * (-len(data) % 4))
        gl["bufferViews"], gl["accessors"] = views, accs
        gl["buffers"] = [{"byteLength": len(data)}]
        if kind == "gltf-octet":
            gl["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(data)).decode()
        elif kind == "gltf-buffer":
            gl["buffers"][0]["uri"] = "data:application/gltf-buffer;base64," + base64.b64encode(bytes(data)).decode()
        elif kind == "external":
            gl["buffers"][0]["uri"] = "data.bin"
            (tmp_path / "data.bin").write_bytes(bytes(data))
        if mutate:
            mutate(gl)
        if kind == "glb":
            return _glb(tmp_path / "synth.glb", gl, bytes(data))
        path = tmp_path / "synth.gltf"
        path.write_text(json.dumps(gl))
        return path


def _glb(path, gl, data):
    text = json.dumps(gl).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(data), 0x004E4942) + data
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def check_synth(c: Character, s: Synth):
    sk = c.skeleton
    assert sk.names == ("Root", "Mid", "Tip")
    np.testing.assert_array_equal(sk.parents, [-1, 0, 1])
    assert [a.name for a in sk.anchors] == ["Anchor"] and list(sk.root_anchor) == [0, -1, -1]
    np.testing.assert_allclose(sk.anchors[0].matrix, s.anchor, atol=1e-12)
    np.testing.assert_allclose(sk.translations, s.T, atol=1e-7)
    np.testing.assert_allclose(sk.rotations, s.R, atol=1e-7)
    (m,) = c.meshes
    np.testing.assert_allclose(m.positions, s.V_expected, atol=1e-7)
    np.testing.assert_allclose(m.normals, s.N, atol=1e-7)
    np.testing.assert_array_equal(m.faces, s.F)
    np.testing.assert_allclose(m.dense_weights(3), s.dense_expected(), atol=1e-7)
    np.testing.assert_allclose(m.colors, np.column_stack([s.C / 65535.0, np.ones(s.n)]), atol=1e-7)
    np.testing.assert_allclose(m.uvs[0], s.UV, atol=1e-7)
    assert m.material == 0
    tex = c.materials[0].base_color_texture
    assert tex.data == png_bytes() and tex.mime_type == "image/png"
    (prop,) = c.props
    assert prop.joint == 1 and prop.mesh.name == "Hat"
    np.testing.assert_allclose(prop.matrix, trs_to_matrix([0, 0.5, 0], [0, 0, 0, 1], [1, 1, 1]), atol=1e-12)
    steps, spline = c.clips
    assert (steps.name, spline.name) == ("steps", "clip_1")
    (t,) = steps.tracks
    assert (t.joint, t.path, t.interpolation) == (2, "translation", "STEP")
    np.testing.assert_allclose(sample_track(t, [0.25, 0.75]), [[0, 1, 0], [0, 1.5, 0]], atol=1e-7)
    cub, lin = spline.tracks  # the channel on the Anchor is ignored
    assert (cub.joint, cub.interpolation, cub.values.shape) == (1, "CUBICSPLINE", (2, 3, 4))
    np.testing.assert_allclose(cub.values, s.cubic, atol=1e-7)
    assert lin.joint == 0 and lin.interpolation == "LINEAR"
    np.testing.assert_allclose(lin.values, quat_normalize(s.q_short / 32767.0), atol=1e-7)
    np.testing.assert_allclose(lin.values, quat_normalize([[0.1, 0.2, 0.3, 0.9], [0, 0, 0.6, 0.8]]), atol=1e-4)
    assert any("1 vertices with duplicate joint slots" in w for w in c.warnings)
    assert any("non-joint nodes 'Anchor'" in w for w in c.warnings)
    # rest pose reproduces the bind mesh: inverse binds, anchor and reordering agree
    M = skinning_matrices(sk, sk.translations, sk.rotations, sk.scales)
    np.testing.assert_allclose(linear_blend_skinning(m.positions, m.joints, m.weights, M), m.positions, atol=1e-6)


@pytest.mark.parametrize("kind", ["glb", "gltf-octet", "gltf-buffer", "external"])
def test_synthetic_layouts(kind, tmp_path):
    s = Synth()
    c = read_gltf(s.build(tmp_path, kind))
    check_synth(c, s)
    assert c.meshes[0].joints.shape == (s.n, 8)  # JOINTS_0 + JOINTS_1 concatenated


def test_synthetic_round_trip_keeps_cubic_spline(tmp_path):
    from rigmix.io.validator import validate_gltf, validator_available

    s = Synth()
    c = read_gltf(s.build(tmp_path, "glb"))
    out = tmp_path / "out.glb"
    write_gltf(c, out)
    b = read_gltf(out)
    assert b.meshes[0].joints.shape == (s.n, 4)
    np.testing.assert_allclose(b.meshes[0].dense_weights(3), c.meshes[0].dense_weights(3), atol=1e-6)
    np.testing.assert_allclose(b.meshes[0].colors, c.meshes[0].colors, atol=1e-7)
    assert b.props[0].joint == 1 and b.props[0].mesh.name == "Hat"
    assert b.materials[0].base_color_texture.sampler == {"magFilter": 9729, "wrapS": 33071}
    times = np.linspace(0, 1, 31)
    for ca, cb in zip(c.clips, b.clips):
        for ta, tb in zip(ca.tracks, cb.tracks):
            assert tb.interpolation == ta.interpolation
            np.testing.assert_allclose(sample_track(tb, times), sample_track(ta, times), atol=1e-6)
    if validator_available():
        assert validate_gltf(out)["issues"]["numErrors"] == 0


def test_primitive_modes(tmp_path):
    s = Synth()
    strip = np.array([0, 1, 2, 3, 4], np.uint8)

    def to_strip(gl):
        prim = gl["meshes"][0]["primitives"][0]
        prim["mode"] = 5
        gl["accessors"][prim["indices"]]["count"] = 5

    c = read_gltf(s.build(tmp_path, "glb", mutate=to_strip, faces=np.pad(strip, (0, 13))))
    np.testing.assert_array_equal(c.meshes[0].faces, [[0, 1, 2], [2, 1, 3], [2, 3, 4]])

    def to_fan(gl):
        to_strip(gl)
        gl["meshes"][0]["primitives"][0]["mode"] = 6

    c = read_gltf(s.build(tmp_path, "glb", mutate=to_fan, faces=np.pad(strip, (0, 13))))
    np.testing.assert_array_equal(c.meshes[0].faces, [[1, 2, 0], [2, 3, 0], [3, 4, 0]])

    def to_lines(gl):
        gl["meshes"][1]["primitives"][0]["mode"] = 1

    c = read_gltf(s.build(tmp_path, "glb", mutate=to_lines))
    assert not c.props and any("mesh 'Hat': points/lines primitive (mode 1) skipped" in w for w in c.warnings)


def test_static_gltf_reads_as_props(tmp_path):
    s = Synth()

    def unskin(gl):
        del gl["skins"], gl["animations"], gl["nodes"][4]["skin"]
        gl["nodes"][4]["translation"] = [1.0, 2.0, 3.0]

    c = read_gltf(s.build(tmp_path, "glb", mutate=unskin))
    assert c.skeleton.num_joints == 0 and not c.skinned and not c.meshes
    assert {p.mesh.name for p in c.props} == {"Body", "Hat"} and all(p.joint == -1 for p in c.props)
    body = next(p for p in c.props if p.mesh.name == "Body")
    np.testing.assert_allclose(body.matrix[:3, 3], [1, 2, 3])
    hat = next(p for p in c.props if p.mesh.name == "Hat")  # world = Anchor @ Root @ Mid @ Hat
    L = trs_to_matrix(s.T, s.R, np.ones((3, 3)))
    np.testing.assert_allclose(hat.matrix, s.anchor @ L[0] @ L[1] @ trs_to_matrix([0, .5, 0], [0, 0, 0, 1], [1, 1, 1]),
                               atol=1e-12)
    with pytest.raises(UnsupportedError, match="no skinned mesh"):
        c.require_skinned()
    out = tmp_path / "static.glb"
    write_gltf(c, out)
    assert {p.mesh.name for p in read_gltf(out).props} == {"Body", "Hat"}


def test_node_between_joints_becomes_a_joint_and_names_are_made_unique(tmp_path):
    def bend(gl):
        gl["nodes"].append({"name": "Mid", "translation": [0.0, 0.25, 0.0]})  # node 6, a 2nd 'Mid'
        gl["nodes"][2]["children"] = [6, 5]
        gl["nodes"][6]["children"] = [1]

    c = read_gltf(Synth().build(tmp_path, "glb", mutate=bend))
    assert c.skeleton.names == ("Root", "Mid", "Mid.1", "Tip")
    np.testing.assert_array_equal(c.skeleton.parents, [-1, 0, 1, 2])
    np.testing.assert_allclose(c.skeleton.translations[2], [0, 0.25, 0])
    assert any("node 'Mid' lies between joints but is not in the skin: added as a joint" in w for w in c.warnings)
    assert any("joint name 'Mid' is used twice: renamed 'Mid.1'" in w for w in c.warnings)
    W = c.meshes[0].dense_weights(4)
    assert np.all(W[:, 2] == 0)  # the added joint carries no weight
    np.testing.assert_allclose(W[:, [0, 1, 3]], Synth().dense_expected(), atol=1e-7)
    assert c.props[0].joint == 1


def test_second_skin_subset_is_merged_and_disjoint_skin_is_refused(tmp_path):
    s = Synth()

    def two_skins(gl):
        gl["skins"].append(dict(gl["skins"][0]))
        gl["nodes"].append({"name": "Body2", "mesh": 0, "skin": 1})
        gl["scenes"][0]["nodes"].append(6)

    c = read_gltf(s.build(tmp_path, "glb", mutate=two_skins))
    assert len(c.meshes) == 2 and c.meshes[1].name == "Body.1"
    np.testing.assert_allclose(c.meshes[1].positions, c.meshes[0].positions)

    def disjoint(gl):
        gl["skins"].append({"joints": [0]})
        gl["nodes"].append({"name": "Body2", "mesh": 0, "skin": 1})

    with pytest.raises(UnsupportedError, match="synth.glb: skins\\[1\\] uses joints outside"):
        read_gltf(s.build(tmp_path, "glb", mutate=disjoint))


# --------------------------------------------------------------------------- repairs


def test_repair_weights_rules():
    J = np.array([[3, 1, 0, 0], [2, 2, 5, 0], [1, 4, 0, 0], [0, 0, 0, 0], [1, 2, 0, 0]])
    W = np.array([[np.nan, np.nan, np.nan, np.nan], [0.25, 0.25, 0.5, 0], [-0.5, 2.0, 0, 0],
                  [0, 0, 0, 0], [0.3, 0.3, 0, 0]])
    J2, W2, empty, counts = repair_weights(J, W)
    np.testing.assert_array_equal(empty, [True, False, False, True, False])
    assert counts == {"nonfinite": 1, "negative": 1, "duplicate": 1, "unnormalized": 2}
    np.testing.assert_allclose(W2[1], [0.5, 0, 0.5, 0])
    np.testing.assert_array_equal(J2[1], [2, 0, 5, 0])
    np.testing.assert_allclose(W2[2], [0, 1, 0, 0])
    np.testing.assert_array_equal(J2[2], [0, 4, 0, 0])
    np.testing.assert_allclose(W2[4], [0.5, 0.5, 0, 0])


def test_empty_rows_take_colocated_weights_else_nearest_joint(tmp_path):
    s = Synth()

    s.W0[2] = 0  # vertex 2: WEIGHTS_0 zero; WEIGHTS_1 float -> NaN below
    s.W1[2] = np.nan
    s.W0[6] = 0
    s.W1[6] = 0
    s.V[6] = s.V[7]  # vertex 6 co-located with vertex 7
    s.V_expected[6] = s.V_expected[7]
    c = read_gltf(s.build(tmp_path, "glb"))
    m = c.meshes[0]
    W = m.dense_weights(3)
    np.testing.assert_allclose(W[6], W[7])
    bind = np.linalg.inv(c.skeleton.inverse_binds)[:, :3, 3]
    nearest = np.argmin(np.linalg.norm(bind - m.positions[2], axis=1))
    np.testing.assert_allclose(W[2], np.eye(3)[nearest])
    assert any("mesh 'Body': 1 vertices with NaN or infinite weights bound with weight 1 to the joint nearest" in w
               for w in c.warnings)
    assert any("mesh 'Body': 1 vertices with zero or negative weights given the weights of a vertex" in w
               for w in c.warnings)


def test_sparsify_weights_top4_float32_exact():
    rng = np.random.default_rng(3)
    W = rng.uniform(0, 1, size=(500, 7))
    W[:, 5] = 0
    J = np.tile(np.arange(7), (500, 1))
    J[:, 6] = J[:, 0]  # duplicate of slot 0: merged before choosing
    J4, W4 = sparsify_weights(J, W)
    assert W4.dtype == np.float32 and J4.shape == (500, 4)
    s32 = np.zeros(500, np.float32)  # the validator's check: float32 running sum
    for k in range(4):
        s32 = (s32 + W4[:, k]).astype(np.float32)
    assert np.all(np.abs(s32.astype(np.float64) - 1.0) <= 2e-7 * (W4 > 0).sum(axis=1))
    assert np.abs(s32.astype(np.float64) - 1.0).max() <= 2.0**-23  # within one float32 ulp
    assert np.all(J4[W4 == 0] == 0) and W4.min() >= 0
    dense = np.zeros((500, 6))
    np.add.at(dense, (np.repeat(np.arange(500), 7), np.minimum(J.ravel(), 5)), W.ravel())
    top = np.sort(dense, axis=1)[:, ::-1][:, :4]
    np.testing.assert_allclose(W4, top / top.sum(1, keepdims=True), atol=1e-6)


def test_writer_refuses_bad_suffix_and_leaves_no_partial_file(tmp_path):
    c = original("SimpleSkin")
    with pytest.raises(InputError, match="expected .glb or .gltf"):
        write_gltf(c, tmp_path / "x.obj")
    target = tmp_path / "keep.glb"
    target.write_bytes(b"old")
    m = c.meshes[0]
    bad = Character("bad", c.skeleton, (Mesh("m", m.positions, m.faces, joints=m.joints + 7, weights=m.weights),))
    with pytest.raises(InputError, match="refers to joint"):
        write_gltf(bad, target)
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["keep.glb"]


# --------------------------------------------------------------------------- unreadable inputs


def _one_line(exc_info, name):
    msg = str(exc_info.value)
    assert "\n" not in msg and name in msg
    return msg


def test_truncated_glb(tmp_path):
    raw = asset("Fox").read_bytes()
    for cut in (10, 100, len(raw) // 2):
        p = tmp_path / "Fox_cut.glb"
        p.write_bytes(raw[:cut])
        with pytest.raises(InputError, match="truncated") as e:
            read_gltf(p)
        _one_line(e, "Fox_cut.glb")


def test_corrupted_json_chunk(tmp_path):
    raw = bytearray(asset("Fox").read_bytes())
    raw[40:60] = b"\xff{{{{{{{{{{{{{{{{{{\x00"
    p = tmp_path / "Fox_json.glb"
    p.write_bytes(bytes(raw))
    with pytest.raises(InputError, match="corrupted GLB JSON chunk") as e:
        read_gltf(p)
    _one_line(e, "Fox_json.glb")


def test_not_gltf(tmp_path):
    p = tmp_path / "noise.glb"
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="not a glTF file") as e:
        load_character(p)
    _one_line(e, "noise.glb")
    q = tmp_path / "data.gltf"
    q.write_text('{"hello": 1}')
    with pytest.raises(InputError, match="no 'asset'"):
        read_gltf(q)
    with pytest.raises(InputError, match="supported: .glb, .gltf"):
        load_character(tmp_path / "thing.fbx")
    with pytest.raises(InputError, match="cannot read"):
        read_gltf(tmp_path / "missing.glb")


def test_huge_declared_buffer_is_not_allocated(tmp_path):
    s = Synth()

    def huge(gl):
        gl["buffers"][0]["byteLength"] = 1 << 40

    with pytest.raises(InputError, match="declares byteLength 1099511627776") as e:
        read_gltf(s.build(tmp_path, "glb", mutate=huge))
    _one_line(e, "synth.glb")
    with pytest.raises(InputError, match="declares 1099511627776 bytes but 'data.bin' has"):
        read_gltf(s.build(tmp_path, "external", mutate=huge))
    (tmp_path / "data.bin").unlink()
    with pytest.raises(InputError, match="'data.bin' which was not found"):
        read_gltf(tmp_path / "synth.gltf")


@pytest.mark.parametrize("case, match", [
    ("count", "out of range"),
    ("offset", "out of range"),
    ("view", "bufferViews\\[1\\] spans bytes"),
    ("sparse", "sparse index 9 is past the accessor count 8"),
    ("ref", "accessors\\[999\\] does not exist"),
])
def test_accessor_ranges_are_checked(case, match, tmp_path):
    s = Synth()

    def corrupt(gl):
        if case == "sparse":
            s.sparse_idx[1] = 9
            return
        body = gl["meshes"][0]["primitives"][0]["attributes"]
        if case == "count":
            gl["accessors"][body["TEXCOORD_0"]]["count"] = 10**9
        elif case == "offset":
            gl["accessors"][body["WEIGHTS_1"]]["byteOffset"] = 64
        elif case == "view":
            gl["bufferViews"][1]["byteLength"] = 10**7
        elif case == "ref":
            body["NORMAL"] = 999

    if case == "sparse":
        corrupt(None)  # the sparse indices are packed from the Synth's arrays
    with pytest.raises(InputError, match=match) as e:
        read_gltf(s.build(tmp_path, "glb", mutate=None if case == "sparse" else corrupt))
    _one_line(e, "synth.glb")


def test_indices_and_joints_past_their_range(tmp_path):
    s = Synth()
    F = s.F.copy()
    F[2, 1] = 200
    with pytest.raises(InputError, match="index 200 is past the vertex count 8"):
        read_gltf(s.build(tmp_path, "glb", faces=F))
    s.J1[4, 1] = 3
    with pytest.raises(InputError, match="refer to joint 3 but the skin has 3 joints"):
        read_gltf(s.build(tmp_path, "glb"))


def test_compressed_geometry_is_refused(tmp_path):
    def draco(gl):
        gl["extensionsUsed"] = gl["extensionsRequired"] = ["KHR_draco_mesh_compression"]

    with pytest.raises(UnsupportedError, match="synth.glb: compressed geometry"):
        read_gltf(Synth().build(tmp_path, "glb", mutate=draco))


def test_written_file_mode_is_not_private(tmp_path):
    path = tmp_path / "f.glb"
    write_gltf(original("SimpleSkin"), path)
    ref = tmp_path / "ref"
    ref.write_bytes(b"")
    assert path.stat().st_mode & 0o777 == ref.stat().st_mode & 0o777  # as open() makes, not mkstemp's 0600


def test_hierarchy_cycle_is_refused(tmp_path):
    def cycle(gl):
        gl["nodes"][0]["children"] = []
        gl["nodes"][1]["children"] = [3]  # Tip -> Root -> Mid -> Tip

    with pytest.raises(InputError, match="cycle"):
        read_gltf(Synth().build(tmp_path, "glb", mutate=cycle))
