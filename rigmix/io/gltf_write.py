""":class:`rigmix.character.Character` -> glTF 2.0 (``.glb``, or ``.gltf`` with one embedded
data-URI buffer). The layout written is described in :mod:`rigmix.io.gltf`.

Every file written has 0 errors in the Khronos glTF-Validator (checked by the tests on every
shared character): float32 data, POSITION and animation-input min/max, unit normals and
rotations, at most 4 influences per vertex with float32 sums of exactly 1. Every number written
(accessor data and JSON) is checked finite in float32 first: a NaN or a value beyond 3.4e38 is
an :class:`~rigmix.errors.InputError` naming the mesh, accessor, joint or clip, never a
``NaN``/``Infinity`` literal in the file.
"""

from __future__ import annotations

import base64
import json
import logging
import struct
from pathlib import Path

import numpy as np

from dfd.mesh import vertex_normals

from ..character import Character, Material, Mesh
from ..errors import InputError, UnsupportedError
from ..geometry import check_float32
from ..safety import atomic_write_bytes
from ..transforms import quat_normalize

__all__ = ["write_gltf", "sparsify_weights"]

logger = logging.getLogger(__name__)

ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
FLOAT, UNSIGNED_BYTE, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5121, 5123, 5125
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def sparsify_weights(joints, weights, k: int = 4):
    """At most ``k`` influences per vertex, as glTF wants them.

    Parameters
    ----------
    joints : (n, K) int array
    weights : (n, K) float array, non-negative (NaN and negatives are treated as 0).
    k : int

    Returns
    -------
    joints : (n, k) int64
        The ``k`` largest influences, largest first; unused slots joint 0.
    weights : (n, k) float32
        Non-negative, unused slots 0; each row summed slot by slot in float32 (as the Khronos
        validator does) gives 1, the largest weight absorbing the rounding (never off by more
        than the validator's 2e-7 per non-zero weight); a row without weight gets 1 on its
        first joint.
    """
    J = np.asarray(joints, dtype=np.int64)
    W = np.nan_to_num(np.asarray(weights, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    W = np.maximum(W, 0.0)
    n, K = W.shape
    J, W = J.copy(), W.copy()
    for b in range(1, K):  # merge duplicate joints before choosing the largest
        for a in range(b):
            same = J[:, a] == J[:, b]
            W[same, a] += W[same, b]
            W[same, b] = 0.0
    if K < k:
        J = np.pad(J, ((0, 0), (0, k - K)))
        W = np.pad(W, ((0, 0), (0, k - K)))
    order = np.argsort(-W, axis=1, kind="stable")[:, :k]
    J = np.take_along_axis(J, order, axis=1)
    W = np.take_along_axis(W, order, axis=1)
    s = W.sum(axis=1)
    empty = s <= 0
    W[empty, 0], s[empty] = 1.0, 1.0
    W /= s[:, None]
    W32 = W.astype(np.float32)
    for _ in range(3):  # the largest weight absorbs the float32 rounding of the sum
        W32[:, 0] += (1.0 - _sum32(W32)).astype(np.float32)
    J[W32 == 0] = 0
    return J, W32


def _sum32(W32: np.ndarray) -> np.ndarray:
    """Row sums accumulated slot by slot in float32, as the Khronos validator adds them."""
    s = np.zeros(len(W32), dtype=np.float32)
    for k in range(W32.shape[1]):
        s = (s + W32[:, k]).astype(np.float32)
    return s.astype(np.float64)


class _Blob:
    """The binary buffer under construction: buffer views and accessors."""

    def __init__(self, where: str = "write_gltf"):
        self.where = where  # start of error messages: the writer and the file
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, raw: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        v = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target is not None:
            v["target"] = target
        self.data += raw
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, a: np.ndarray, ctype: int, *, target=None, minmax=False, what: str = "") -> int:
        """Append ``a`` (count, n) (or (count,)) as one tightly packed accessor; FLOAT data is
        checked finite in float32 (``what`` names it in the error)."""
        dtype = {FLOAT: "<f4", UNSIGNED_BYTE: "u1", UNSIGNED_SHORT: "<u2", UNSIGNED_INT: "<u4"}[ctype]
        if ctype == FLOAT:
            a = check_float32(a, f"{self.where}: {what or f'accessor {len(self.accessors)}'}")
        a = np.ascontiguousarray(a, dtype=dtype)
        a2 = a.reshape(len(a), -1)
        acc = {
            "bufferView": self.view(a.tobytes(), target),
            "componentType": ctype,
            "count": len(a2),
            "type": _TYPES[a2.shape[1]],
        }
        if minmax:
            acc["min"] = a2.min(axis=0).tolist()
            acc["max"] = a2.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _unit_normals(N: np.ndarray, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Normalize; degenerate normals take the area-weighted face normal, else +Z."""
    N = np.nan_to_num(np.asarray(N, dtype=np.float64))
    length = np.linalg.norm(N, axis=1)
    bad = length < 1e-12
    if bad.any():
        N = N.copy()
        N[bad] = vertex_normals(V, F)[bad]
        N[bad & (np.linalg.norm(N, axis=1) < 1e-12)] = (0.0, 0.0, 1.0)
        length = np.linalg.norm(N, axis=1)
    return N / length[:, None]


def _primitive(blob: _Blob, mesh: Mesh, num_materials: int, num_joints: int) -> dict:
    V = np.asarray(mesh.positions)
    F = np.asarray(mesh.faces)
    name = f"mesh {mesh.name!r}"
    attrs = {"POSITION": blob.accessor(V, FLOAT, target=ARRAY_BUFFER, minmax=True, what=f"{name} POSITION")}
    if mesh.normals is not None:
        check_float32(mesh.normals, f"{blob.where}: {name} NORMAL")
        attrs["NORMAL"] = blob.accessor(_unit_normals(mesh.normals, V, F), FLOAT, target=ARRAY_BUFFER,
                                        what=f"{name} NORMAL")
    for i, uv in enumerate(mesh.uvs):
        attrs[f"TEXCOORD_{i}"] = blob.accessor(uv, FLOAT, target=ARRAY_BUFFER, what=f"{name} TEXCOORD_{i}")
    if mesh.colors is not None:
        attrs["COLOR_0"] = blob.accessor(np.clip(mesh.colors, 0.0, 1.0), FLOAT, target=ARRAY_BUFFER,
                                         what=f"{name} COLOR_0")
    if mesh.joints is not None and num_joints > 0:
        J, W = sparsify_weights(mesh.joints, mesh.weights)
        if J.max() >= num_joints:
            raise InputError(f"write_gltf: mesh '{mesh.name}' refers to joint {int(J.max())}, "
                             f"the skeleton has {num_joints}")
        jt = UNSIGNED_BYTE if num_joints <= 256 else UNSIGNED_SHORT
        attrs["JOINTS_0"] = blob.accessor(J, jt, target=ARRAY_BUFFER)
        attrs["WEIGHTS_0"] = blob.accessor(W, FLOAT, target=ARRAY_BUFFER, what=f"{name} WEIGHTS_0")
    it = UNSIGNED_SHORT if len(V) < 65535 else UNSIGNED_INT
    prim = {
        "attributes": attrs,
        "indices": blob.accessor(F.reshape(-1), it, target=ELEMENT_ARRAY_BUFFER),
        "mode": 4,
        "extras": {"name": mesh.name},
    }
    if 0 <= mesh.material < num_materials:
        prim["material"] = int(mesh.material)
    return prim


def _writable(mesh: Mesh) -> bool:
    if len(mesh.positions) and len(mesh.faces):
        return True
    logger.warning("write_gltf: mesh '%s' has no triangles: not written", mesh.name)
    return False


def _materials(blob: _Blob, materials: tuple[Material, ...], gl: dict) -> None:
    images, textures, samplers = [], [], []
    tex_index: dict[int, int] = {}
    out = []
    for m in materials:
        for key in ("base_color", "metallic", "roughness", "emissive", "alpha_cutoff"):
            check_float32(getattr(m, key), f"{blob.where}: material {m.name!r} {key}")
        pbr = {
            "baseColorFactor": np.clip(m.base_color, 0.0, 1.0).tolist(),
            "metallicFactor": float(np.clip(m.metallic, 0.0, 1.0)),
            "roughnessFactor": float(np.clip(m.roughness, 0.0, 1.0)),
        }
        t = m.base_color_texture
        if t is not None and t.mime_type in ("image/png", "image/jpeg"):
            if id(t) not in tex_index:
                images.append({"bufferView": blob.view(bytes(t.data)), "mimeType": t.mime_type})
                if t.name:
                    images[-1]["name"] = t.name
                tex = {"source": len(images) - 1}
                if t.sampler:
                    smp = {k: int(v) for k, v in t.sampler.items() if k in ("magFilter", "minFilter", "wrapS", "wrapT")}
                    if smp not in samplers:
                        samplers.append(smp)
                    tex["sampler"] = samplers.index(smp)
                textures.append(tex)
                tex_index[id(t)] = len(textures) - 1
            pbr["baseColorTexture"] = {"index": tex_index[id(t)]}
            if m.base_color_texcoord:
                pbr["baseColorTexture"]["texCoord"] = int(m.base_color_texcoord)
        mat = {"pbrMetallicRoughness": pbr}
        if m.name:
            mat["name"] = m.name
        if m.double_sided:
            mat["doubleSided"] = True
        if m.alpha_mode in ("MASK", "BLEND"):
            mat["alphaMode"] = m.alpha_mode
        if m.alpha_mode == "MASK":
            mat["alphaCutoff"] = float(max(m.alpha_cutoff, 0.0))
        if np.any(np.asarray(m.emissive) != 0):
            mat["emissiveFactor"] = np.clip(m.emissive, 0.0, 1.0).tolist()
        if m.extra.get("extras"):
            mat["extras"] = m.extra["extras"]
        out.append(mat)
    for key, value in (("materials", out), ("images", images), ("textures", textures), ("samplers", samplers)):
        if value:
            gl[key] = value


def _matrix_list(m: np.ndarray) -> list[float]:
    return np.asarray(m, dtype=np.float64).T.reshape(16).tolist()  # column-major


def _animations(blob: _Blob, character: Character, joint_nodes: list[int]) -> list[dict]:
    out = []
    times_cache: dict[bytes, int] = {}
    for clip in character.clips:
        samplers, channels = [], []
        for tr in clip.tracks:
            if not 0 <= tr.joint < len(joint_nodes):
                raise InputError(f"write_gltf: clip '{clip.name}' has a track on joint {tr.joint}, "
                                 f"the skeleton has {len(joint_nodes)} joints")
            what = f"clip {clip.name!r} {tr.path} track of joint {character.skeleton.names[tr.joint]!r}"
            times = check_float32(tr.times, f"{blob.where}: {what} times")
            key = times.tobytes()
            if key not in times_cache:
                times_cache[key] = blob.accessor(times, FLOAT, minmax=True, what=f"{what} times")
            vals = np.asarray(tr.values, dtype=np.float64)
            check_float32(vals, f"{blob.where}: {what} values")
            if tr.interpolation == "CUBICSPLINE":
                vals = vals.reshape(-1, vals.shape[-1])  # (k, 3, C) -> (3k, C): in, value, out
            elif tr.path == "rotation":
                vals = quat_normalize(vals)
            samplers.append({"input": times_cache[key], "output": blob.accessor(vals, FLOAT, what=f"{what} values"),
                             "interpolation": tr.interpolation})
            channels.append({"sampler": len(samplers) - 1,
                             "target": {"node": joint_nodes[tr.joint], "path": tr.path}})
        if not channels:
            logger.warning("write_gltf: clip '%s' has no tracks: not written", clip.name)
            continue
        out.append({"name": clip.name, "samplers": samplers, "channels": channels})
    return out


def _check_skeleton(sk, where: str) -> None:
    """The skeleton's JSON numbers and matrices, finite in float32 (vectorized), by joint."""
    for key in ("translations", "rotations", "scales", "inverse_binds") if sk.num_joints else ():
        values = np.asarray(getattr(sk, key), dtype=np.float64).reshape(sk.num_joints, -1)
        with np.errstate(over="ignore", invalid="ignore"):
            bad = ~np.isfinite(values.astype(np.float32)).all(axis=1)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            label = {"translations": "translation", "rotations": "rotation", "scales": "scale",
                     "inverse_binds": "inverse bind matrix"}[key]
            check_float32(values[j], f"{where}: joint {sk.names[j]!r} {label}")
    for a in sk.anchors:
        check_float32(a.matrix, f"{where}: node {a.name!r} matrix")


def _document(character: Character, where: str = "write_gltf") -> tuple[dict, bytes]:
    """The glTF JSON (without buffers) and the binary blob; ``where`` starts error messages."""
    sk = character.skeleton
    J = sk.num_joints
    _check_skeleton(sk, where)
    blob = _Blob(where)
    gl: dict = {"asset": {"version": "2.0", "generator": "rigmix"}}
    nodes: list[dict] = []
    roots: list[int] = []

    def add_node(node: dict, parent: int | None) -> int:
        nodes.append(node)
        i = len(nodes) - 1
        if parent is None:
            roots.append(i)
        else:
            nodes[parent].setdefault("children", []).append(i)
        return i

    anchor_nodes: list[int] = []
    for a in sk.anchors:
        node = {"name": a.name}
        if not np.allclose(a.matrix, np.eye(4), atol=0, rtol=0):
            node["matrix"] = _matrix_list(a.matrix)
        anchor_nodes.append(add_node(node, anchor_nodes[a.parent] if a.parent >= 0 else None))
    joint_nodes: list[int] = []
    q = quat_normalize(sk.rotations)
    for j in range(J):
        node = {"name": sk.names[j], "translation": sk.translations[j].tolist(),
                "rotation": q[j].tolist(), "scale": sk.scales[j].tolist()}
        p = sk.parents[j]
        parent = joint_nodes[p] if p >= 0 else (anchor_nodes[sk.root_anchor[j]] if sk.root_anchor[j] >= 0 else None)
        joint_nodes.append(add_node(node, parent))

    _materials(blob, character.materials, gl)
    nmat = len(character.materials)
    meshes = []
    skinned = [m for m in character.meshes if m.joints is not None and J > 0 and _writable(m)]
    loose = [m for m in character.meshes if (m.joints is None or J == 0) and _writable(m)]
    if any(m.joints is not None for m in character.meshes) and J == 0:
        raise UnsupportedError(f"write_gltf: {character.name}: skinned meshes but a skeleton without joints")
    if J:
        ibm = blob.accessor(np.asarray(sk.inverse_binds).transpose(0, 2, 1).reshape(J, 16), FLOAT,
                            what="skin inverseBindMatrices")
        gl["skins"] = [{"joints": joint_nodes, "inverseBindMatrices": ibm}]
    if skinned:
        meshes.append({"name": character.name or "mesh",
                       "primitives": [_primitive(blob, m, nmat, J) for m in skinned]})
        add_node({"name": character.name or "mesh", "mesh": 0, "skin": 0}, None)
    statics = [(m, -1, np.eye(4)) for m in loose] + [
        (p.mesh, p.joint, p.matrix) for p in character.props if _writable(p.mesh)
    ]
    for mesh, joint, matrix in statics:
        check_float32(matrix, f"{where}: node {mesh.name!r} matrix")
        meshes.append({"name": mesh.name, "primitives": [_primitive(blob, mesh, nmat, 0)]})
        node = {"name": mesh.name, "mesh": len(meshes) - 1}
        if not np.allclose(matrix, np.eye(4), atol=0, rtol=0):
            node["matrix"] = _matrix_list(matrix)
        add_node(node, joint_nodes[joint] if joint >= 0 else None)
    if meshes:
        gl["meshes"] = meshes
    anims = _animations(blob, character, joint_nodes)
    if anims:
        gl["animations"] = anims
    gl["nodes"] = nodes
    gl["scenes"] = [{"nodes": roots}]
    gl["scene"] = 0
    if blob.accessors:
        gl["accessors"] = blob.accessors
    if blob.views:
        gl["bufferViews"] = blob.views
    blob.data += b"\0" * (-len(blob.data) % 4)
    if not nodes:
        del gl["nodes"]
        gl["scenes"] = [{}]
    return gl, bytes(blob.data)


def _glb(gl: dict, data: bytes) -> bytes:
    if data:
        gl = dict(gl, buffers=[{"byteLength": len(data)}])
    text = json.dumps(gl, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if data:
        chunks += struct.pack("<II", len(data), 0x004E4942) + data
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _gltf(gl: dict, data: bytes) -> bytes:
    if data:
        uri = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
        gl = dict(gl, buffers=[{"byteLength": len(data), "uri": uri}])
    return json.dumps(gl, indent=1, allow_nan=False).encode("utf-8")


def write_gltf(character: Character, path) -> None:
    """Write ``character`` as glTF 2.0: binary ``.glb`` or ``.gltf`` with embedded buffers.

    Parameters
    ----------
    character : Character
    path : str or Path
        Ends in ``.glb`` or ``.gltf``. Written to a temporary file in the same folder and then
        renamed over ``path``, so a failure never leaves a partial file.

    Raises
    ------
    InputError
        Unknown suffix, meshes referring to joints the skeleton lacks, or a number that is NaN
        or beyond float32 (naming the mesh, accessor, joint or clip).
    UnsupportedError
        Skinned meshes with a skeleton of zero joints.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise InputError(f"write_gltf: {path.name}: unknown suffix {path.suffix!r}, expected .glb or .gltf")
    gl, data = _document(character, f"write_gltf: {path.name}")
    try:
        payload = _glb(gl, data) if suffix == ".glb" else _gltf(gl, data)
    except ValueError as e:  # json's allow_nan=False: a NaN or infinity left in extras
        raise InputError(f"write_gltf: {path.name}: {e} (NaN or infinity in the glTF JSON, e.g. in extras)") from None
    atomic_write_bytes(path, payload)  # temporary file beside path, renamed over it
