"""USD export with UsdSkel: skeleton, skinned meshes, every clip, materials, props.

This module and :mod:`rigmix.io.gltf` are the only places where conventions change. USD's
differences from rigmix's conventions (:mod:`rigmix.character`), and what we do:

* **Matrices.** USD matrices act on row vectors (``p' = p @ M``, translation in the last row);
  ours act on column vectors. Every matrix is transposed on the way out (:func:`_gf_matrices`).
* **Quaternions.** ``GfQuatf`` is ``(w, x, y, z)`` in its constructor but stored imaginary
  first, i.e. ``(x, y, z, w)`` in memory: our xyzw arrays are handed to ``Vt.QuatfArray``
  as they are (pinned by a test reading ``GetReal``/``GetImaginary`` back).
* **Texture coordinates.** USD's ``st`` has ``t`` up; glTF's ``v`` goes down: ``st = (u, 1 - v)``.
* **Scale precision.** ``SkelAnimation.scales`` is ``half3[]`` in the schema (about three
  significant digits); unit and power-of-two scales are exact, others are rounded (lossy).
* **Anchors.** A UsdSkel skeleton has one implicit root space (the Skeleton prim's world), while
  our roots each hang from an anchor (e.g. CesiumMan's ``Z_UP`` matrix). When all root joints
  share one anchor world ``A`` (every shared character), ``A`` becomes the ``SkelRoot``'s
  transform and the skeleton, bind transforms and mesh points are written in that skeleton
  space: points ``A^-1 p``, bind transforms ``A^-1 inverse(inverse_bind)``; rest and
  animated locals are unchanged. Otherwise the ``SkelRoot`` is identity and each root's anchor
  world is folded into that root's rest and animated local transforms. Either way
  ``SkelRoot world @ UsdSkel skinned points`` equals :func:`rigmix.skinning.linear_blend_skinning`
  of the same pose (checked in ``tests/test_usd.py`` against ``UsdSkel``'s own skinning).
* **Props.** A rigid prop follows its joint's *animated* world matrix, which a plain
  ``Xform`` child cannot express (UsdSkel joints are not prims). A prop on joint ``j`` is
  therefore written as a rigidly skinned mesh: ``jointIndices = [j]``, ``jointWeights = [1]``
  with ``constant`` interpolation, points in bind space ``inverse(inverse_bind[j]) @ matrix @ p``
  (then skeleton space), so that UsdSkel gives ``world[j] @ matrix @ p``. Static props
  (``joint == -1``) are ``Mesh`` prims with their matrix as a transform op.

Layout of the written stage (``<Root>`` = the character's name made a valid identifier)::

    /<Root>                 SkelRoot (Xform for a character without joints), default prim
        Skeleton            joints, bindTransforms, restTransforms; BindingAPI with an
                            ``animation`` variant set: one variant per clip, each setting
                            ``skel:animationSource`` to that clip's prim
        Animations/<clip>   one SkelAnimation per clip (outside the variants: all kept)
        <mesh>              one Mesh per Character.meshes (BindingAPI: jointIndices,
                            jointWeights with elementSize K, geomBindTransform identity)
        prop_<mesh>         props (rigidly skinned to their joint, or static)
        Materials/<mat>     UsdPreviewSurface networks (:mod:`rigmix.io.usd_shade`)

Stage metadata: ``upAxis = Y``, ``metersPerUnit = 1``, ``timeCodesPerSecond = fps`` (30 by
default; time code = seconds x fps). Joint paths are built from sanitized, unique joint names
(``Tf.MakeValidIdentifier``); the original names are in the Skeleton prim's
``customData["rigmix:jointNames"]``, each clip's original name in its SkelAnimation's
``customData["rigmix:clipName"]`` (variant names are the sanitized ones), and the SkelRoot's
``customData["rigmix:clipNames"]`` lists them in order.

Files are written atomically: the layer goes to a temporary file in the target folder that is
renamed over the target (textures likewise, before the layer), so an error never leaves a
partial file. ``.usda`` (text), ``.usdc`` and ``.usd`` (crate) write textures into a
``textures/`` folder next to the file; ``.usdz`` packages the layer and its textures.

:func:`rigmix.io.usd_read.read_usd` reads these files back (``tests/test_usd.py`` checks that
every frame of every clip poses the same after the round trip).

Not written: blend shapes (rigmix does not read morph targets), texture transforms, metallic /
roughness / normal / occlusion / emissive textures (the model keeps only the base colour one).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np

from ..animation.sampling import clip_times, sample_clip
from ..errors import InputError
from ..geometry import check_float32, check_transforms
from ..rig import unique_names
from ..safety import atomic_output
from ..transforms import matrix_to_trs, trs_to_matrix
from .usd_shade import define_materials, texture_files, write_texture_files

__all__ = ["USD_SUFFIXES", "joint_paths", "write_usd"]

logger = logging.getLogger(__name__)

#: Suffixes :func:`write_usd` writes.
USD_SUFFIXES = (".usda", ".usdc", ".usd", ".usdz")


def _pxr():
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise InputError("usd: the `pxr` module is missing; install usd-core (pip install usd-core)") from exc
    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt


def _unique_identifiers(names, taken=()):
    """Valid, unique USD prim names for ``names``: ``Tf.MakeValidIdentifier``, then
    :func:`rigmix.rig.unique_names` with ``_2``, ``_3``... (an identifier cannot hold a dot)."""
    _, _, Tf, _, _, _, _ = _pxr()
    return unique_names([Tf.MakeValidIdentifier(str(name) or "unnamed") for name in names],
                        suffix="_{}", start=2, taken=taken)


def joint_paths(skeleton):
    """UsdSkel joint path tokens (``"root/spine/neck"``), one per joint, in joint order.

    Names are sanitized with ``Tf.MakeValidIdentifier`` and made unique over the whole
    skeleton, so that every path is a valid, unique ``Sdf.Path``.
    """
    idents = _unique_identifiers(skeleton.names)
    paths = []
    for j, p in enumerate(skeleton.parents):
        paths.append(idents[j] if p < 0 else f"{paths[p]}/{idents[j]}")
    return paths


def _gf_matrices(M):
    """``(N, 4, 4)`` column-vector matrices -> ``Vt.Matrix4dArray`` of row-vector matrices."""
    _, _, _, _, _, _, Vt = _pxr()
    M = np.ascontiguousarray(np.swapaxes(np.asarray(M, dtype=np.float64), -1, -2))
    return Vt.Matrix4dArray.FromNumpy(M.reshape(-1, 4, 4))


def _gf_matrix(M):
    Gf = _pxr()[0]
    return Gf.Matrix4d(np.asarray(M, dtype=np.float64).T.tolist())


def _quatf_array(R):
    """``(N, 4)`` xyzw quaternions -> ``Vt.QuatfArray`` (GfQuatf stores x, y, z, w in memory)."""
    Vt = _pxr()[6]
    return Vt.QuatfArray.FromNumpy(np.ascontiguousarray(np.asarray(R).reshape(-1, 4), dtype=np.float32))


def _vec3f(A):
    Vt = _pxr()[6]
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(np.asarray(A).reshape(-1, 3), dtype=np.float32))


def _root_frames(skeleton):
    """The SkelRoot transform ``base`` (4, 4) and per-joint folds ``(J, 4, 4)`` for the roots.

    ``fold[j]`` pre-multiplies root ``j``'s local transform (identity for other joints and when
    every root shares one anchor, which then becomes ``base``).
    """
    J = skeleton.num_joints
    parent_worlds = skeleton.root_parent_worlds()  # (J, 4, 4), identity when no anchor
    roots = skeleton.roots
    fold = np.broadcast_to(np.eye(4), (J, 4, 4)).copy()
    if len(roots) == 0:
        return np.eye(4), fold
    anchors = {int(a) for a in skeleton.root_anchor[roots]}
    if len(anchors) == 1:
        return parent_worlds[roots[0]].copy(), fold
    logger.debug("usd: roots hang from %d different anchors; folding them into the roots", len(anchors))
    fold[roots] = parent_worlds[roots]
    return np.eye(4), fold


class _OutOfRange(InputError):
    """A value that USD would store as NaN or infinity (re-raised by :func:`write_usd` with the file)."""


def _finite(values, what: str, dtype=np.float32):
    """``values`` as ``dtype``, finite there (:func:`rigmix.geometry.check_float32`)."""
    try:
        return check_float32(values, what, dtype=dtype)
    except InputError as e:
        raise _OutOfRange(str(e)) from None


def _where(character):
    return character.label or "character"  # the file's name, never its folders


def _resolve_clip(character, clip):
    """A Clip from a Clip, a name or an index (InputError naming the clips when absent)."""
    if isinstance(clip, (int, np.integer)):
        if not -len(character.clips) <= int(clip) < len(character.clips):
            raise InputError(f"usd: {_where(character)} has no clip #{int(clip)}; it has {len(character.clips)}")
        return character.clips[int(clip)]
    if isinstance(clip, str):
        try:
            return character.clip(clip)
        except KeyError:
            names = [c.name for c in character.clips]
            raise InputError(f"usd: {_where(character)} has no clip {clip!r}; clips: {names}") from None
    return clip


def _check_suffix(path):
    if path.suffix.lower() not in USD_SUFFIXES:
        raise InputError(f"usd: cannot write {path.name}: the suffix must be one of {', '.join(USD_SUFFIXES)}")


def write_usd(character, path, *, clips=None, default_clip=None, fps=30.0):
    """Write a character as a UsdSkel asset (``.usda``, ``.usdc``, ``.usd`` or ``.usdz``).

    Parameters
    ----------
    character : rigmix.character.Character
        Its meshes become ``UsdGeom.Mesh`` prims bound to one Skeleton, its clips
        ``SkelAnimation`` prims, its materials ``UsdPreviewSurface`` networks, its props rigidly
        skinned (or static) meshes. A character without joints is written as plain meshes.
    path : str or Path
        Output file; the format follows the suffix. Textures go to ``textures/`` next to it
        (inside the package for ``.usdz``).
    clips : sequence of (Clip, str or int), optional
        The clips written (objects, names or indices); default: every clip of the character.
    default_clip : Clip, str or int, optional
        The ``animation`` variant selected in the file; default: the first written clip. A
        default clip missing from ``clips`` is written too (first).
    fps : float
        Sampling rate of the animations and the stage's ``timeCodesPerSecond``; each clip is
        sampled at :func:`rigmix.animation.clip_times` (``1/fps`` apart, end included).

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    InputError
        Unknown suffix or clip, a file that cannot be written (no partial file is left), a
        singular or non-finite joint matrix, or a value that is NaN or beyond float32 (float16
        for joint scales), naming the mesh, joint or clip.
    """
    path = Path(path)
    _check_suffix(path)
    if fps <= 0:
        raise InputError(f"usd: fps must be positive, got {fps}")
    chosen = list(character.clips) if clips is None else [_resolve_clip(character, c) for c in clips]
    if character.skeleton.num_joints == 0:
        chosen = []
    selected = None
    if chosen:
        selected = chosen[0] if default_clip is None else _resolve_clip(character, default_clip)
        if all(selected is not c for c in chosen):
            chosen.insert(0, selected)

    root_ident = _unique_identifiers([character.name or "Character"])[0]
    tex_names, tex_files = texture_files(character.materials, root_ident, _unique_identifiers)
    sk = character.skeleton
    if sk.num_joints:
        roots = sk.roots  # USD stores bind worlds and the roots' anchor frame inverted
        for what, M, names in (("inverse bind matrix", sk.inverse_binds, sk.names),
                               ("anchor matrix", sk.root_parent_worlds()[roots], [sk.names[r] for r in roots])):
            check_transforms(M, names, where=f"usd: {path.name}", what=what,
                             fix="fix the character's skeleton before writing it")
    try:
        stage = _build_stage(character, root_ident, chosen, selected, tex_names, fps)
    except _OutOfRange as e:
        raise InputError(f"usd: {path.name}: {e}") from None

    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        if path.suffix.lower() == ".usdz":
            _write_usdz(stage, tex_files, path)
        else:
            write_texture_files(tex_files, path.parent)
            _export_atomic(stage, path)
    except OSError as exc:
        raise InputError(f"usd: could not write {path}: {exc}") from exc
    logger.debug("usd: wrote %s (%d joints, %d meshes, %d clips, %d materials)", path,
                 character.skeleton.num_joints, len(character.meshes), len(chosen), len(character.materials))
    return path


def _export_atomic(stage, path):
    """Export the root layer to a temporary file beside ``path``, then rename it over ``path``."""
    with atomic_output(path, suffix=path.suffix) as tmp:  # USD picks the format by suffix
        if not stage.GetRootLayer().Export(str(tmp)):
            raise InputError(f"usd: could not write {path} (check the folder and the suffix)")


def _write_usdz(stage, tex_files, path):
    from pxr import Sdf, UsdUtils

    with tempfile.TemporaryDirectory(prefix=".rigmix-usdz-", dir=path.parent) as tmpdir:
        tmpdir = Path(tmpdir)
        layer = tmpdir / (path.stem + ".usdc")
        write_texture_files(tex_files, tmpdir)
        if not stage.GetRootLayer().Export(str(layer)):
            raise InputError(f"usd: could not write the layer of {path}")
        with atomic_output(path, suffix=".usdz") as tmp:
            if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(tmp)):
                raise InputError(f"usd: could not package {path} as usdz")


def _build_stage(character, root_ident, clips, selected, tex_names, fps):
    """The in-memory stage (see the module docstring for the layout)."""
    _, Sdf, _, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    sk = character.skeleton
    rigged = sk.num_joints > 0
    base, fold = _root_frames(sk) if rigged else (np.eye(4), None)
    base_inv = np.linalg.inv(base)

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.GetRootLayer().customLayerData = {"creator": "rigmix"}

    root_path = Sdf.Path("/" + root_ident)
    root = UsdSkel.Root.Define(stage, root_path) if rigged else UsdGeom.Xform.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())
    if not np.allclose(base, np.eye(4), atol=0):
        UsdGeom.Xformable(root).AddTransformOp().Set(_gf_matrix(base))
    if character.name:
        root.GetPrim().SetCustomDataByKey("rigmix:name", character.name)

    taken = {"Skeleton", "Animations", "Materials"}
    materials = []
    if character.materials:
        mat_idents = _unique_identifiers([m.name or "material" for m in character.materials])
        materials = define_materials(stage, root_path.AppendChild("Materials"), character.materials,
                                     mat_idents, tex_names)

    skel = None
    if rigged:
        skel = _define_skeleton(stage, root_path, sk, base_inv, fold)
        if clips:
            _define_animations(stage, root_path, skel, sk, clips, selected, fold, fps)
            root.GetPrim().SetCustomDataByKey("rigmix:clipNames", Vt.StringArray([c.name for c in clips]))

    meshes = list(character.meshes)
    names = [m.name or "mesh" for m in meshes] + [f"prop_{p.mesh.name or 'mesh'}" for p in character.props]
    idents = _unique_identifiers(names, taken)
    bind_worlds = np.linalg.inv(sk.inverse_binds) if rigged else None
    for mesh, ident in zip(meshes, idents):
        if mesh.skinned and not rigged:  # pragma: no cover - the reader never makes this
            raise InputError(f"usd: {_where(character)} mesh {mesh.name!r} is skinned but there is no skeleton")
        prim = _define_mesh(stage, root_path.AppendChild(ident), mesh, base_inv, materials, character)
        if mesh.skinned:
            _bind(prim, skel, mesh.joints, mesh.weights, constant=False)
    for prop, ident in zip(character.props, idents[len(meshes):]):
        if prop.joint >= 0 and rigged:
            to_skel = base_inv @ bind_worlds[prop.joint] @ prop.matrix
            prim = _define_mesh(stage, root_path.AppendChild(ident), prop.mesh, to_skel, materials, character)
            _bind(prim, skel, np.array([[prop.joint]]), np.ones((1, 1)), constant=True)
            prim.GetPrim().SetCustomDataByKey("rigmix:propJoint", sk.names[prop.joint])
        else:
            prim = _define_mesh(stage, root_path.AppendChild(ident), prop.mesh, np.eye(4), materials, character)
            UsdGeom.Xformable(prim).AddTransformOp().Set(_gf_matrix(base_inv @ prop.matrix))
    return stage


def _define_skeleton(stage, root_path, sk, base_inv, fold):
    """Skeleton prim: joint paths, bind transforms (skeleton space), rest transforms (local)."""
    _, _, _, _, _, UsdSkel, Vt = _pxr()
    skel = UsdSkel.Skeleton.Define(stage, root_path.AppendChild("Skeleton"))
    skel.CreateJointsAttr(Vt.TokenArray(joint_paths(sk)))
    skel.CreateJointNamesAttr(Vt.TokenArray(list(sk.names)))
    skel.GetPrim().SetCustomDataByKey("rigmix:jointNames", Vt.StringArray(list(sk.names)))
    skel.CreateBindTransformsAttr(_gf_matrices(_finite(base_inv @ np.linalg.inv(sk.inverse_binds),
                                                       "skeleton bindTransforms", np.float64)))
    rest = _finite(sk.rest_locals(), "skeleton restTransforms", np.float64)
    roots = sk.roots
    rest[roots] = fold[roots] @ rest[roots]
    skel.CreateRestTransformsAttr(_gf_matrices(rest))
    UsdSkel.BindingAPI.Apply(skel.GetPrim())
    return skel


def _define_animations(stage, root_path, skel, sk, clips, selected, fold, fps):
    """One SkelAnimation per clip under ``Animations``, and the ``animation`` variant set."""
    _, _, _, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    scope = UsdGeom.Scope.Define(stage, root_path.AppendChild("Animations"))
    joints = Vt.TokenArray(joint_paths(sk))
    idents = _unique_identifiers([c.name or "clip" for c in clips])
    roots = sk.roots
    folded = [r for r in roots if not np.array_equal(fold[r], np.eye(4))]
    starts, ends = [], []
    anim_paths = []
    for clip, ident in zip(clips, idents):
        anim = UsdSkel.Animation.Define(stage, scope.GetPath().AppendChild(ident))
        anim.CreateJointsAttr(joints)
        prim = anim.GetPrim()
        prim.SetCustomDataByKey("rigmix:clipName", clip.name)
        for tr in clip.tracks:  # a NaN key would be sampled silently as identity
            _finite(tr.times, f"clip {clip.name!r} {tr.path} track of joint {sk.names[tr.joint]!r} times")
            _finite(tr.values, f"clip {clip.name!r} {tr.path} track of joint {sk.names[tr.joint]!r} values")
        times = clip_times(clip, fps)
        prim.SetCustomDataByKey("rigmix:startTime", float(times[0]))
        prim.SetCustomDataByKey("rigmix:endTime", float(times[-1]))
        T, R, S = sample_clip(sk, clip, times)
        if folded:
            L = trs_to_matrix(T[:, folded], R[:, folded], S[:, folded])
            T[:, folded], R[:, folded], S[:, folded] = matrix_to_trs(fold[folded] @ L)
        _finite(T, f"clip {clip.name!r} translations")
        _finite(R, f"clip {clip.name!r} rotations")
        _finite(S, f"clip {clip.name!r} scales (half floats)", np.float16)
        t_attr = anim.CreateTranslationsAttr()
        r_attr = anim.CreateRotationsAttr()
        s_attr = anim.CreateScalesAttr()
        S16 = S.astype(np.float16)
        for f, t in enumerate(times):
            code = Usd.TimeCode(float(t * fps))
            t_attr.Set(_vec3f(T[f]), code)
            r_attr.Set(_quatf_array(R[f]), code)
            s_attr.Set(Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(S16[f])), code)
        starts.append(times[0])
        ends.append(times[-1])
        anim_paths.append(anim.GetPath())
    stage.SetStartTimeCode(float(min(starts) * fps))
    stage.SetEndTimeCode(float(max(ends) * fps))

    vset = skel.GetPrim().GetVariantSets().AddVariantSet("animation")
    for ident, anim_path in zip(idents, anim_paths):
        vset.AddVariant(ident)
        vset.SetVariantSelection(ident)
        with vset.GetVariantEditContext():
            UsdSkel.BindingAPI(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim_path])
    vset.SetVariantSelection(idents[[c is selected for c in clips].index(True)])


def _define_mesh(stage, path, mesh, to_skel, materials, character):
    """A Mesh prim with points and normals mapped by ``to_skel`` (4, 4), st, colours, material."""
    Gf, Sdf, _, _, UsdGeom, _, Vt = _pxr()
    from pxr import UsdShade

    prim = UsdGeom.Mesh.Define(stage, path)
    if mesh.name:
        prim.GetPrim().SetCustomDataByKey("rigmix:name", mesh.name)
    lin = to_skel[:3, :3]
    if not (np.isfinite(to_skel).all() and abs(np.linalg.det(lin)) > 0):
        raise _OutOfRange(f"mesh {mesh.name!r} has a singular or non-finite transform")
    P = _finite(mesh.positions @ lin.T + to_skel[:3, 3], f"mesh {mesh.name!r} points")
    prim.CreatePointsAttr(_vec3f(P))
    prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, dtype=np.int32)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.ravel(), dtype=np.int32)))
    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    prim.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)  # glTF: counter-clockwise front faces
    lo, hi = (P.min(axis=0), P.max(axis=0)) if len(P) else (np.zeros(3), np.zeros(3))
    prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    pv = UsdGeom.PrimvarsAPI(prim)
    if mesh.normals is not None:
        N = mesh.normals @ np.linalg.inv(lin)  # rows: (inverse transpose @ n) transposed
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
        _finite(N, f"mesh {mesh.name!r} normals")
        prim.CreateNormalsAttr(_vec3f(N))
        prim.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    for i, uv in enumerate(mesh.uvs):
        st = _finite(np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1), f"mesh {mesh.name!r} st{i or ''}")
        var = pv.CreatePrimvar("st" if i == 0 else f"st{i}", Sdf.ValueTypeNames.TexCoord2fArray,
                               UsdGeom.Tokens.vertex)
        var.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(st, dtype=np.float32)))
    material = character.materials[mesh.material] if 0 <= mesh.material < len(materials) else None
    if mesh.colors is not None:
        _finite(mesh.colors, f"mesh {mesh.name!r} displayColor")
        prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(_vec3f(mesh.colors[:, :3]))
        if np.any(mesh.colors[:, 3] < 1):
            prim.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex).Set(
                Vt.FloatArray.FromNumpy(np.ascontiguousarray(mesh.colors[:, 3], dtype=np.float32)))
    elif material is not None:  # a viewer without shading still shows the flat colour
        prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(_vec3f(material.base_color[:3]))
    if material is not None:
        prim.CreateDoubleSidedAttr(bool(material.double_sided))
        UsdShade.MaterialBindingAPI.Apply(prim.GetPrim()).Bind(materials[mesh.material])
    return prim


def _bind(prim, skel, joints, weights, *, constant):
    """UsdSkel binding: jointIndices/jointWeights (elementSize K), geomBindTransform identity."""
    Gf, _, _, _, _, UsdSkel, Vt = _pxr()
    _finite(weights, f"mesh {prim.GetPath().name!r} jointWeights")
    binding = UsdSkel.BindingAPI.Apply(prim.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    K = joints.shape[1]
    binding.CreateJointIndicesPrimvar(constant, K).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(joints.ravel(), dtype=np.int32)))
    binding.CreateJointWeightsPrimvar(constant, K).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(weights.ravel(), dtype=np.float32)))
    # points are already in skeleton space (module docstring): no extra bind transform
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
