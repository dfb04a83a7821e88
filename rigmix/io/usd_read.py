"""USD (UsdSkel) -> :class:`rigmix.character.Character`: the reader paired with :mod:`rigmix.io.usd`.

Reads what :func:`rigmix.io.usd.write_usd` writes, and ordinary UsdSkel assets of the same shape:

* **Skeleton.** The first ``Skeleton`` under the default prim (or the first ``SkelRoot``).
  Parents from the joint paths (UsdSkel orders parents before children, as we do); names from
  ``customData["rigmix:jointNames"]``, else ``jointNames``, else the last path element.
  Rest locals from ``restTransforms`` (or, when absent, from ``bindTransforms``). The Skeleton
  prim's local-to-world matrix ``A`` becomes one anchor ``"SkelRoot"`` above every root, and
  ``inverse_binds = inverse(A @ bindTransforms)``.
* **Meshes.** Every ``Mesh`` bound to that skeleton is a skinned ``Mesh`` with positions in bind
  space ``A @ geomBindTransform @ p`` (polygons fanned into triangles; a left-handed mesh's
  faces are flipped); ``constant`` joint influences are expanded to every vertex. A rigidly
  bound mesh with ``customData["rigmix:propJoint"]`` (a written prop) becomes a ``Prop`` on that
  joint. Unbound meshes are static props at their world matrix. ``st``/``st<n>`` primvars
  become uvs ``(s, 1 - t)``; ``displayColor``/``displayOpacity`` become colours. A mesh whose
  primvars are ``faceVarying`` is split into one vertex per face corner.
* **Clips.** Every ``SkelAnimation`` prim under the default prim is a clip (name from
  ``customData["rigmix:clipName"]``, else the prim name), one LINEAR track per joint and
  property at its time samples (seconds = time code / ``timeCodesPerSecond``); joints the
  animation does not list keep their rest pose.
* **Materials.** ``UsdPreviewSurface`` inputs (``diffuseColor``, ``opacity``, ``metallic``,
  ``roughness``, ``emissiveColor``); a ``diffuseColor`` driven by a ``UsdUVTexture`` gives the
  base colour texture (file bytes as they are, from a folder or inside a ``.usdz``) and its
  ``scale`` the base colour factor.
* **Confinement** (as :mod:`rigmix.io.accessors` for glTF). The file is a regular file of at
  most :data:`rigmix.io.accessors.MAX_FILE_BYTES`, checked before USD opens it; every layer it
  composes (sublayers, references, payloads, recursively) and every texture must be a file
  inside the folder of the file given (or inside the ``.usdz`` itself), checked before the stage
  is composed; textures larger than :data:`rigmix.io.accessors.MAX_IMAGE_BYTES` are dropped.
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..character import Anchor, Character, Clip, Material, Mesh, Prop, Skeleton, Texture, Track
from ..errors import InputError, UnsupportedError
from ..transforms import matrix_to_trs
from .accessors import MAX_FILE_BYTES, MAX_IMAGE_BYTES, read_regular_file

__all__ = ["read_usd"]

logger = logging.getLogger(__name__)

_WRAP = {"clamp": 33071, "mirror": 33648, "repeat": 10497}


def _np_matrices(value):
    """``Vt.Matrix4dArray`` (row vectors) -> ``(N, 4, 4)`` column-vector matrices."""
    return np.swapaxes(np.array(value, dtype=np.float64).reshape(-1, 4, 4), -1, -2)


def _np_matrix(value):
    return np.array(value, dtype=np.float64).reshape(4, 4).T


def read_usd(path) -> Character:
    """Read a UsdSkel asset (``.usda``, ``.usdc``, ``.usd``, ``.usdz``) into a Character.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Character

    Raises
    ------
    InputError
        A file USD cannot open, or a skeleton with malformed joints.
    UnsupportedError
        More than one skeleton, or meshes bound with their own ``skel:joints`` order.
    """
    from pxr import Usd, UsdGeom, UsdSkel

    path = Path(path)
    read_regular_file(path, limit=MAX_FILE_BYTES, name=path.name, at_most=0)  # no device, FIFO, folder
    _check_layers(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:  # pxr raises Tf.ErrorException
        raise InputError(f"usd: {path.name}: cannot open the file ({str(exc).strip().splitlines()[-1]})") from None
    if stage is None:
        raise InputError(f"usd: {path.name}: cannot open the file")
    top = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    prims = list(Usd.PrimRange(top))
    skels = [p for p in prims if p.IsA(UsdSkel.Skeleton)]
    if len(skels) > 1:
        raise UnsupportedError(f"usd: {path.name} has {len(skels)} skeletons; rigmix reads one per file")
    tcps = stage.GetTimeCodesPerSecond() or 24.0
    warnings = []

    skeleton, base = _skeleton(path, skels[0]) if skels else (_empty_skeleton(), np.eye(4))
    materials, mat_of = _materials(path, prims)
    meshes, props = [], []
    for prim in prims:
        if not prim.IsA(UsdGeom.Mesh):
            continue
        binding = UsdSkel.BindingAPI(prim)
        bound = skels and prim.HasAPI(UsdSkel.BindingAPI) and binding.GetJointIndicesPrimvar()
        mesh, point_of_vertex = _mesh(path, prim, mat_of.get(prim.GetPath(), -1))
        if point_of_vertex is not None:  # vertex order changes: say so (Character.warnings)
            note = (f"{path.name}: mesh '{mesh.name}': faceVarying primvars: {len(mesh.positions)} vertices, one "
                    f"per face corner, from {int(point_of_vertex.max()) + 1 if len(point_of_vertex) else 0} points")
            logger.info("usd: %s", note)
            warnings.append(note)
        if not bound:
            M = _np_matrix(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
            props.append(Prop(mesh, -1, M))
            continue
        if binding.GetJointsAttr().HasAuthoredValue():
            raise UnsupportedError(f"usd: {path.name} mesh {prim.GetPath()} has its own skel:joints order; "
                                   "bind it to the skeleton's joint order")
        G = binding.GetGeomBindTransformAttr().Get()
        to_bind = base @ (_np_matrix(G) if G is not None else np.eye(4))
        joints, weights = _influences(binding, len(prim.GetAttribute("points").Get() or []))
        if point_of_vertex is not None:
            joints, weights = joints[point_of_vertex], weights[point_of_vertex]
        mesh = _transformed(mesh, to_bind)
        prop_joint = prim.GetCustomDataByKey("rigmix:propJoint")
        if prop_joint is not None and prop_joint in skeleton.names:
            j = skeleton.index(prop_joint)
            props.append(Prop(mesh, j, skeleton.inverse_binds[j]))
            continue
        meshes.append(Mesh(mesh.name, mesh.positions, mesh.faces, mesh.normals, mesh.uvs, mesh.colors,
                           joints, weights, mesh.material))
    clips = _clips(path, prims, skeleton, skels[0], tcps) if skels else ()
    # glTF keeps doubleSided on the material, USD on the mesh
    for prim in prims:
        i = mat_of.get(prim.GetPath(), -1)
        if i >= 0 and UsdGeom.Mesh(prim).GetDoubleSidedAttr().Get():
            materials[i] = replace(materials[i], double_sided=True)
    name = top.GetCustomDataByKey("rigmix:name") if top.IsValid() and top != stage.GetPseudoRoot() else None
    return Character(name or (top.GetName() if top != stage.GetPseudoRoot() else path.stem), skeleton,
                     tuple(meshes), clips, tuple(materials), tuple(props), str(path), tuple(warnings))


def _inside(folder: str, resolved: str) -> bool:
    """Whether a resolved USD asset path (``file`` or ``package.usdz[inner]``) lies in ``folder``."""
    outer = resolved.split("[", 1)[0] if resolved.endswith("]") else resolved
    real = os.path.realpath(outer)
    return os.path.commonpath([folder, real]) == folder


def _check_layers(path: Path) -> None:
    """Refuse a layer stack that composes a file outside the folder of ``path``.

    Each layer is opened alone (``Sdf.Layer``, no composition) and its sublayers, references and
    payloads are resolved and checked before any of them is opened; the stage is composed only
    once every layer is known to be inside.
    """
    from pxr import Sdf

    folder = os.path.realpath(path.parent)
    seen, todo = set(), [str(path)]
    while todo:
        ident = todo.pop()
        if ident in seen:
            continue
        seen.add(ident)
        try:
            layer = Sdf.Layer.FindOrOpen(ident)
        except Exception as exc:  # pxr raises Tf.ErrorException
            if ident == str(path):
                raise InputError(f"usd: {path.name}: cannot open the file "
                                 f"({str(exc).strip().splitlines()[-1]})") from None
            raise InputError(f"usd: {path.name}: a layer it composes cannot be opened") from None
        if layer is None:
            if ident == str(path):
                raise InputError(f"usd: {path.name}: cannot open the file")
            continue  # a missing layer: USD reports it as it composes
        for dep in layer.GetCompositionAssetDependencies():
            resolved = layer.ComputeAbsolutePath(dep)
            if "://" in dep or not _inside(folder, resolved):
                raise InputError(
                    f"usd: {path.name}: a sublayer, reference or payload leads outside the file's folder: "
                    "only files inside it are read; copy or flatten the layers next to it")
            outer = resolved.split("[", 1)[0] if resolved.endswith("]") else resolved
            if os.path.exists(outer):
                read_regular_file(outer, limit=MAX_FILE_BYTES, name=path.name,
                                  label=f"layer {dep!r}", at_most=0)
                todo.append(resolved)


def _empty_skeleton():
    return Skeleton((), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 4, 4)))


def _skeleton(path, prim):
    from pxr import Usd, UsdGeom, UsdSkel

    skel = UsdSkel.Skeleton(prim)
    tokens = [str(t) for t in (skel.GetJointsAttr().Get() or [])]
    J = len(tokens)
    index = {t: j for j, t in enumerate(tokens)}
    parents = np.full(J, -1)
    for j, t in enumerate(tokens):
        parent = t.rsplit("/", 1)[0] if "/" in t else None
        if parent is not None and parent in index:
            parents[j] = index[parent]
            if parents[j] >= j:
                raise InputError(f"usd: {path.name} skeleton {prim.GetPath()}: joint {t!r} comes before its parent")
    names = prim.GetCustomDataByKey("rigmix:jointNames")
    if names is None or len(names) != J:
        names = skel.GetJointNamesAttr().Get()
    if names is None or len(names) != J or len(set(names)) != J:
        names = [t.rsplit("/", 1)[-1] for t in tokens]
    bind = skel.GetBindTransformsAttr().Get()
    rest = skel.GetRestTransformsAttr().Get()
    if bind is None or len(bind) != J:
        raise InputError(f"usd: {path.name} skeleton {prim.GetPath()} has {0 if bind is None else len(bind)} "
                         f"bind transforms for {J} joints")
    bind = _np_matrices(bind)
    if rest is None or len(rest) != J:
        rest = np.array([bind[j] if parents[j] < 0 else np.linalg.inv(bind[parents[j]]) @ bind[j]
                         for j in range(J)]).reshape(J, 4, 4)
    else:
        rest = _np_matrices(rest)
    base = _np_matrix(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    T, R, S = matrix_to_trs(rest)
    root_anchor = np.where(parents < 0, 0, -1)
    sk = Skeleton(tuple(str(n) for n in names), parents, T, R, S, np.linalg.inv(base @ bind),
                  (Anchor("SkelRoot", base),), root_anchor)
    return sk, base


def _primvar_array(pv, n_points, n_corners, corner_index):
    """A primvar's values per vertex ``(n, C)`` or per face corner ``(n_corners, C)``, and which."""
    value = pv.ComputeFlattened()
    if value is None:
        return None, None
    arr = np.array(value, dtype=np.float64)
    arr = arr.reshape(len(arr), -1)
    interp = pv.GetInterpolation()
    if interp == "constant" or len(arr) == 1:
        return np.broadcast_to(arr[0], (n_points, arr.shape[1])).copy(), "vertex"
    if interp == "uniform":  # per face: expand to corners
        counts_face = corner_index
        return arr[counts_face], "corner"
    if interp == "faceVarying" and len(arr) == n_corners:
        return arr, "corner"
    if len(arr) == n_points:
        return arr, "vertex"
    return None, None


def _mesh(path, prim, material):
    """The mesh in its own local space (points as authored), triangulated, primvars attached.

    Returns the Mesh and, when faceVarying primvars made it split one vertex per face corner,
    the ``(n,)`` index of the authored point of each vertex (else None).
    """
    from pxr import UsdGeom

    geom = UsdGeom.Mesh(prim)
    P = np.array(geom.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
    counts = np.array(geom.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.array(geom.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if counts.sum() != len(idx) or (len(idx) and (idx.min() < 0 or idx.max() >= len(P))):
        raise InputError(f"usd: {path.name} mesh {prim.GetPath()}: face indices do not match its points")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face_of_corner = np.repeat(np.arange(len(counts)), counts)
    # fan triangulation over corners: (start, start + k, start + k + 1)
    tri_corners = np.array([[s, s + k, s + k + 1] for s, c in zip(starts, counts) for k in range(1, c - 1)],
                           dtype=np.int64).reshape(-1, 3)
    if geom.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tri_corners = tri_corners[:, ::-1]
    pvs = UsdGeom.PrimvarsAPI(prim)
    fields = {}
    normals_attr = geom.GetNormalsAttr().Get()
    if normals_attr is not None and len(normals_attr):
        N = np.array(normals_attr, dtype=np.float64).reshape(-1, 3)
        interp = geom.GetNormalsInterpolation()
        fields["normals"] = (N, "corner" if interp == "faceVarying" and len(N) == len(idx) else "vertex")
        if fields["normals"][1] == "vertex" and len(N) != len(P):
            del fields["normals"]
    uvs = []
    for i in range(8):
        pv = pvs.GetPrimvar("st" if i == 0 else f"st{i}")
        if not pv or not pv.HasValue():
            break
        arr, kind = _primvar_array(pv, len(P), len(idx), face_of_corner)
        if arr is None:
            break
        uvs.append((np.column_stack([arr[:, 0], 1.0 - arr[:, 1]]), kind))
    color = None
    dc = pvs.GetPrimvar("displayColor")
    if dc and dc.HasValue() and dc.GetInterpolation() != "constant":
        rgb, kind = _primvar_array(dc, len(P), len(idx), face_of_corner)
        if rgb is not None:
            alpha = np.ones((len(rgb), 1))
            do = pvs.GetPrimvar("displayOpacity")
            if do and do.HasValue():
                a, akind = _primvar_array(do, len(P), len(idx), face_of_corner)
                if a is not None and akind == kind:
                    alpha = a[:, :1]
            color = (np.column_stack([rgb[:, :3], alpha]), kind)
    corner_fields = [f for f in [fields.get("normals"), color, *uvs] if f is not None and f[1] == "corner"]
    name = prim.GetCustomDataByKey("rigmix:name") or prim.GetName()
    if corner_fields:  # split: one vertex per face corner
        def per_corner(f):
            return f[0] if f[1] == "corner" else f[0][idx]

        return Mesh(name, P[idx], tri_corners,
                    per_corner(fields["normals"]) if "normals" in fields else None,
                    tuple(per_corner(u) for u in uvs), per_corner(color) if color else None,
                    material=material), idx
    return Mesh(name, P, idx[tri_corners], fields["normals"][0] if "normals" in fields else None,
                tuple(u[0] for u in uvs), color[0] if color else None, material=material), None


def _transformed(mesh, M):
    """Positions and normals of a mesh mapped by ``M`` (4, 4)."""
    lin = M[:3, :3]
    N = None
    if mesh.normals is not None:
        N = mesh.normals @ np.linalg.inv(lin)
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    return Mesh(mesh.name, mesh.positions @ lin.T + M[:3, 3], mesh.faces, N, mesh.uvs, mesh.colors,
                mesh.joints, mesh.weights, mesh.material)


def _influences(binding, n):
    """``(n, K)`` joint indices and weights of a bound mesh (constant influences expanded)."""
    ji, jw = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    K = max(ji.GetElementSize(), 1)
    J = np.array(ji.Get(), dtype=np.int64).reshape(-1, K)
    W = np.array(jw.Get(), dtype=np.float64).reshape(-1, K)
    if ji.GetInterpolation() == "constant" or len(J) == 1:
        J, W = np.broadcast_to(J[0], (n, K)).copy(), np.broadcast_to(W[0], (n, K)).copy()
    return J, W


def _materials(path, prims):
    """Materials under the default prim and the material bound to each mesh path."""
    from pxr import Ar, Sdf, UsdGeom, UsdShade

    mats, index = [], {}
    for prim in prims:
        if not prim.IsA(UsdShade.Material):
            continue
        index[prim.GetPath()] = len(mats)
        mats.append(_material(path, UsdShade.Material(prim), Ar, Sdf))
    bound = {}
    for prim in prims:
        if prim.IsA(UsdGeom.Mesh):
            mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
            if mat and mat.GetPath() in index:
                bound[prim.GetPath()] = index[mat.GetPath()]
    return mats, bound


def _input_value(shader, name, default):
    inp = shader.GetInput(name)
    if not inp:
        return default
    value = inp.Get()
    return default if value is None else value


def _material(path, mat, Ar, Sdf):
    from pxr import UsdShade

    name = mat.GetPrim().GetCustomDataByKey("rigmix:name") or mat.GetPrim().GetName()
    surface = mat.ComputeSurfaceSource()[0]
    if not surface or surface.GetIdAttr().Get() != "UsdPreviewSurface":
        return Material(name)
    rgb = np.array(_input_value(surface, "diffuseColor", (0.18, 0.18, 0.18)), dtype=np.float64)
    alpha = float(_input_value(surface, "opacity", 1.0))
    texture, texcoord = None, 0
    diffuse = surface.GetInput("diffuseColor")
    sources = diffuse.GetConnectedSources()[0] if diffuse else []
    if sources and UsdShade.Shader(sources[0].source.GetPrim()).GetIdAttr().Get() == "UsdUVTexture":
        tex = UsdShade.Shader(sources[0].source.GetPrim())
        scale = np.array(_input_value(tex, "scale", (1, 1, 1, 1)), dtype=np.float64)
        rgb, alpha = scale[:3], float(scale[3])
        asset = _input_value(tex, "file", None)
        data = _asset_bytes(path, asset, Ar) if asset is not None else None
        if data is not None:
            mime = ("image/png" if data[:8] == b"\x89PNG\r\n\x1a\n"
                    else "image/jpeg" if data[:3] == b"\xff\xd8\xff" else None)
            if mime is not None:
                sampler = {k: _WRAP[str(_input_value(tex, k, "repeat"))] for k in ("wrapS", "wrapT")
                           if str(_input_value(tex, k, "repeat")) in _WRAP}
                texture = Texture(data, mime, Path(asset.path).stem, sampler)
        st = tex.GetInput("st")
        st_src = st.GetConnectedSources()[0] if st else []
        if st_src:
            varname = str(_input_value(UsdShade.Shader(st_src[0].source.GetPrim()), "varname", "st"))
            texcoord = int(varname[2:]) if varname[2:].isdigit() else 0
    threshold = surface.GetInput("opacityThreshold")
    mode = "MASK" if threshold and threshold.Get() else "BLEND" if alpha < 1 or (
        surface.GetInput("opacity") and surface.GetInput("opacity").HasConnectedSource()) else "OPAQUE"
    return Material(name, np.append(rgb, alpha), float(_input_value(surface, "metallic", 0.0)),
                    float(_input_value(surface, "roughness", 0.5)), texture, texcoord,
                    alpha_mode=mode, alpha_cutoff=float(threshold.Get()) if mode == "MASK" else 0.5,
                    emissive=np.array(_input_value(surface, "emissiveColor", (0, 0, 0)), dtype=np.float64))


def _asset_bytes(path, asset, Ar):
    """Bytes of a resolved asset (a plain file or a file inside a .usdz), None if missing.

    An asset outside the folder of ``path`` is refused (:class:`InputError`, without its path);
    one that is not a regular file or is larger than :data:`MAX_IMAGE_BYTES` is refused too.
    """
    resolved = asset.resolvedPath
    if not resolved:
        return None
    if not _inside(os.path.realpath(path.parent), resolved):
        raise InputError(f"usd: {path.name}: a texture leads outside the file's folder: only files inside it are "
                         "read; copy the image next to the file")
    outer = resolved.split("[", 1)[0] if resolved.endswith("]") else resolved
    if outer == resolved:  # a plain file: regular and within the limit, checked before opening
        read_regular_file(outer, limit=MAX_IMAGE_BYTES, name=path.name, label="a texture", at_most=0)
    handle = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved))
    if handle is None:
        return None
    if handle.GetSize() > MAX_IMAGE_BYTES:
        raise InputError(f"usd: {path.name}: a texture has {handle.GetSize()} bytes, more than the "
                         f"{MAX_IMAGE_BYTES}-byte limit")
    return bytes(memoryview(handle.GetBuffer())) if hasattr(handle, "GetBuffer") else None


def _clips(path, prims, skeleton, skel_prim, tcps):
    from pxr import UsdSkel

    tokens = [str(t) for t in (UsdSkel.Skeleton(skel_prim).GetJointsAttr().Get() or [])]
    index = {t: j for j, t in enumerate(tokens)}
    clips = []
    for prim in prims:
        if not prim.IsA(UsdSkel.Animation):
            continue
        anim = UsdSkel.Animation(prim)
        joints = [index.get(str(t), -1) for t in (anim.GetJointsAttr().Get() or [])]
        tracks = []
        for attr, path_name in ((anim.GetTranslationsAttr(), "translation"), (anim.GetRotationsAttr(), "rotation"),
                                (anim.GetScalesAttr(), "scale")):
            codes = attr.GetTimeSamples()
            if codes:
                values = np.stack([np.array(attr.Get(c), dtype=np.float64) for c in codes])  # (k, Ja, C)
            elif attr.HasAuthoredValue():
                codes, values = [0.0], np.array(attr.Get(), dtype=np.float64)[None]
            else:
                continue
            times = np.array(codes, dtype=np.float64) / tcps
            for a, j in enumerate(joints):
                if j >= 0:
                    tracks.append(Track(j, path_name, times, values[:, a], "LINEAR"))
        if tracks:
            clips.append(Clip(str(prim.GetCustomDataByKey("rigmix:clipName") or prim.GetName()), tuple(tracks)))
    return tuple(clips)
