"""Reading and writing triangle meshes for the dfd command line and tests.

OBJ, PLY, OFF and STL go through ``igl.read_triangle_mesh`` / ``igl.write_triangle_mesh``; glTF
and GLB through ``pygltflib``: every triangle primitive of every mesh instanced in the default
scene, with the node transforms applied (a skinned mesh in its bind pose), merged into one mesh.
Appearance comes along: one shared base colour texture with its UVs, or else per-vertex colours
(``COLOR_0`` times the material's base colour factor). This is deliberately small: rigmix has
the full glTF reader; dfd stays independent of it.
"""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dfd.errors import DfdInputError

__all__ = ["MeshData", "read_mesh", "write_mesh"]

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_COUNT = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh and its optional appearance.

    Attributes
    ----------
    V : (n, 3) float64
    F : (m, 3) int64
    uvs : (n, 2) float64 or None
        glTF convention (v = 0 at the top of the texture).
    vertex_colors : (n, 3) float64 or None
        Linear RGB in [0, 1].
    texture : (h, w, 3) uint8 or None
    """

    V: np.ndarray
    F: np.ndarray
    uvs: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    texture: np.ndarray | None = None


def read_mesh(path) -> MeshData:
    """Read a triangle mesh (OBJ, PLY, OFF, STL, glTF, GLB).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MeshData
    """
    path = Path(path)
    if not path.is_file():
        raise DfdInputError(f"io: no mesh file at {path}")
    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb"):
        return _read_gltf(path)
    if suffix in (".obj", ".ply", ".off", ".stl"):
        import igl

        try:
            V, F = igl.read_triangle_mesh(str(path))
        except Exception as exc:
            raise DfdInputError(f"io: cannot read {path}: {exc}") from exc
        V = np.asarray(V, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        if len(F) == 0:
            raise DfdInputError(f"io: {path} has no triangles")
        return MeshData(V=V, F=F)
    raise DfdInputError(f"io: unsupported mesh format {suffix!r} for {path}; use OBJ, PLY, OFF, STL, glTF or GLB")


def write_mesh(path, V, F):
    """Write a triangle mesh (OBJ, PLY, OFF or STL by suffix).

    Parameters
    ----------
    path : str or Path
    V : (n, 3) float array
    F : (m, 3) int array
    """
    import igl

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".ply", ".off", ".stl"):
        raise DfdInputError(f"io: cannot write {path.suffix!r} ({path}); use .obj, .ply, .off or .stl")
    path.parent.mkdir(parents=True, exist_ok=True)
    ok = igl.write_triangle_mesh(str(path), np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64))
    if ok is False:
        raise DfdInputError(f"io: writing {path} failed")


def _node_matrix(node):
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores column-major
    T = np.eye(4)
    if node.translation is not None:
        T[:3, 3] = node.translation
    R = np.eye(4)
    if node.rotation is not None:
        x, y, z, w = node.rotation
        R[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    S = np.eye(4)
    if node.scale is not None:
        S[0, 0], S[1, 1], S[2, 2] = node.scale
    return T @ R @ S


class _Gltf:
    """Accessor decoding for one pygltflib document."""

    def __init__(self, path):
        import pygltflib

        try:
            self.doc = pygltflib.GLTF2().load(str(path))
        except Exception as exc:
            raise DfdInputError(f"io: cannot read glTF {path}: {exc}") from exc
        self.path = path
        self._buffers = {}

    def buffer(self, i):
        if i not in self._buffers:
            buf = self.doc.buffers[i]
            if buf.uri is None:
                data = self.doc.binary_blob()
            elif buf.uri.startswith("data:"):
                data = base64.b64decode(buf.uri.split(",", 1)[1])
            else:
                data = (self.path.parent / buf.uri).read_bytes()
            self._buffers[i] = data
        return self._buffers[i]

    def view_bytes(self, index):
        view = self.doc.bufferViews[index]
        data = self.buffer(view.buffer)
        start = view.byteOffset or 0
        return data[start : start + view.byteLength], view.byteStride

    def accessor(self, index):
        acc = self.doc.accessors[index]
        dtype = np.dtype(_COMPONENT[acc.componentType])
        cols = _COUNT[acc.type]
        if acc.bufferView is None:
            out = np.zeros((acc.count, cols), dtype=dtype)
        else:
            data, stride = self.view_bytes(acc.bufferView)
            offset = acc.byteOffset or 0
            item = dtype.itemsize * cols
            stride = stride or item
            raw = np.frombuffer(data, dtype=np.uint8, count=stride * (acc.count - 1) + item, offset=offset)
            rows = np.lib.stride_tricks.as_strided(raw, shape=(acc.count, item), strides=(stride, 1))
            out = np.ascontiguousarray(rows).view(dtype).reshape(acc.count, cols)
        if acc.sparse is not None:
            raise DfdInputError(f"io: {self.path.name} accessor {index} is sparse, which dfd's reader does not handle")
        out = out.astype(np.float64) if dtype == np.float32 else out
        if acc.normalized and dtype != np.float32:
            out = out.astype(np.float64) / np.iinfo(dtype).max
        return out

    def image(self, index):
        from PIL import Image

        img = self.doc.images[index]
        if img.bufferView is not None:
            data = bytes(self.view_bytes(img.bufferView)[0])
        elif img.uri.startswith("data:"):
            data = base64.b64decode(img.uri.split(",", 1)[1])
        else:
            data = (self.path.parent / img.uri).read_bytes()
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def _read_gltf(path) -> MeshData:
    g = _Gltf(path)
    doc = g.doc
    scene = doc.scenes[doc.scene or 0] if doc.scenes else None
    roots = scene.nodes if scene is not None else range(len(doc.nodes))
    stack = [(int(n), np.eye(4)) for n in roots]
    parts = []  # (V, F, uv or None, colour (n,3), texture index or None)
    while stack:
        ni, parent = stack.pop()
        node = doc.nodes[ni]
        world = parent @ _node_matrix(node)
        stack.extend((int(c), world) for c in (node.children or []))
        if node.mesh is None:
            continue
        for prim in doc.meshes[node.mesh].primitives:
            if prim.mode not in (None, 4) or prim.attributes.POSITION is None:
                continue  # points, lines and strips carry no triangles we render
            P = g.accessor(prim.attributes.POSITION)[:, :3]
            P = P @ world[:3, :3].T + world[:3, 3]
            idx = g.accessor(prim.indices).reshape(-1) if prim.indices is not None else np.arange(len(P))
            F = idx[: len(idx) // 3 * 3].reshape(-1, 3).astype(np.int64)
            factor = np.ones(3)
            tex = None
            if prim.material is not None:
                pbr = doc.materials[prim.material].pbrMetallicRoughness
                if pbr is not None:
                    if pbr.baseColorFactor is not None:
                        factor = np.asarray(pbr.baseColorFactor[:3], dtype=np.float64)
                    if pbr.baseColorTexture is not None:
                        tex = doc.textures[pbr.baseColorTexture.index].source
            colour = np.broadcast_to(factor, (len(P), 3)).copy()
            if prim.attributes.COLOR_0 is not None:
                colour *= g.accessor(prim.attributes.COLOR_0)[:, :3]
            uv = g.accessor(prim.attributes.TEXCOORD_0)[:, :2] if prim.attributes.TEXCOORD_0 is not None else None
            parts.append((P, F, uv, colour, tex if uv is not None else None))
    if not parts:
        raise DfdInputError(f"io: {path} has no triangle primitives in its scene")
    offsets = np.cumsum([0] + [len(p[0]) for p in parts])
    V = np.concatenate([p[0] for p in parts])
    F = np.concatenate([p[1] + o for p, o in zip(parts, offsets)])
    textures = {p[4] for p in parts}
    if len(textures) == 1 and None not in textures:
        uvs = np.concatenate([p[2] for p in parts])
        return MeshData(V=V, F=F, uvs=uvs, texture=g.image(textures.pop()))
    colours = np.concatenate([p[3] for p in parts])
    has_colour = not np.allclose(colours, 1.0)
    return MeshData(V=V, F=F, vertex_colors=colours if has_colour else None)
