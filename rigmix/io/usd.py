"""USD export with UsdSkel (minimal: skeleton, skinned meshes, one clip).

This module and :mod:`rigmix.io.gltf` are the only places where conventions change. USD's
differences from rigmix's conventions (:mod:`rigmix.character`), and what we do:

* **Matrices.** USD matrices act on row vectors (``p' = p @ M``, translation in the last row);
  ours act on column vectors. Every matrix is transposed on the way out (:func:`_gf_matrices`).
* **Quaternions.** ``GfQuatf`` is constructed as ``(w, x, y, z)``; ours are ``(x, y, z, w)``.
  Rotations are converted explicitly with ``Gf.Quatf(w, Gf.Vec3f(x, y, z))``.
* **Texture coordinates.** USD's ``st`` has ``t`` up; glTF's ``v`` goes down: ``t = 1 - v``.
* **Scale precision.** ``SkelAnimation.scales`` is ``half3[]`` in the schema (about three
  significant digits); unit and power-of-two scales are exact, others are rounded.
* **Anchors.** A UsdSkel skeleton has one implicit root space (the Skeleton prim's world), while
  our roots each hang from an anchor (e.g. CesiumMan's ``Z_UP`` matrix). When all root joints
  share one anchor world ``A`` (every shared character), ``A`` becomes the ``SkelRoot``'s
  transform and the skeleton, bind transforms and mesh points are written in that skeleton
  space: points ``A^-1 p``, bind transforms ``A^-1 inverse(inverse_bind)``; rest and
  animated locals are unchanged. Otherwise the ``SkelRoot`` is identity and each root's anchor
  world is folded into that root's rest and animated local transforms. Either way
  ``SkelRoot world @ UsdSkel skinned points`` equals :func:`rigmix.skinning.linear_blend_skinning`
  of the same pose (checked in ``tests/test_usd.py`` against ``UsdSkel``'s own skinning).

Stage metadata: ``upAxis = Y``, ``metersPerUnit = 1``, ``timeCodesPerSecond = fps`` (30 by
default; time code = seconds x fps), the ``SkelRoot`` is the default prim. Joint paths are
built from sanitized, unique joint names (``Tf.MakeValidIdentifier``); the original names are in
the Skeleton prim's ``customData["rigmix:jointNames"]``.

Not written yet (the full exporter comes later): materials and textures, props, more than one
clip, blend shapes.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..animation import clip_times, sample_clip
from ..errors import InputError
from ..transforms import matrix_to_trs, trs_to_matrix

__all__ = ["write_usd"]

logger = logging.getLogger(__name__)


def _pxr():
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise InputError("usd: the `pxr` module is missing; install usd-core (pip install usd-core)") from exc
    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt


def _unique_identifiers(names, taken=()):
    """Valid, unique USD prim names for ``names`` (``Tf.MakeValidIdentifier`` + ``_2``, ``_3``...)."""
    _, _, Tf, _, _, _, _ = _pxr()
    used = set(taken)
    out = []
    for name in names:
        base = Tf.MakeValidIdentifier(str(name) or "unnamed")
        ident, k = base, 2
        while ident in used:
            ident, k = f"{base}_{k}", k + 1
        used.add(ident)
        out.append(ident)
    return out


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
    """``(N, 4)`` xyzw quaternions -> ``Vt.QuatfArray`` (``GfQuatf(w, (x, y, z))``)."""
    Gf, _, _, _, _, _, Vt = _pxr()
    R = np.asarray(R, dtype=np.float64).reshape(-1, 4)
    return Vt.QuatfArray([Gf.Quatf(float(w), Gf.Vec3f(float(x), float(y), float(z))) for x, y, z, w in R])


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


def _resolve_clip(character, clip):
    if clip is None:
        return character.clips[0] if character.clips else None
    if isinstance(clip, (int, np.integer)):
        return character.clips[int(clip)]
    if isinstance(clip, str):
        try:
            return character.clip(clip)
        except KeyError:
            names = [c.name for c in character.clips]
            raise InputError(f"usd: {character.source or character.name} has no clip {clip!r}; clips: {names}") from None
    return clip


def write_usd(character, path, *, clip=None, fps=30.0):
    """Write a character as a UsdSkel asset (``.usda``, ``.usdc`` or ``.usd``).

    Parameters
    ----------
    character : rigmix.character.Character
        Skinned character; its meshes become ``UsdGeom.Mesh`` prims bound to one Skeleton.
    path : str or Path
        Output file; the format follows the extension.
    clip : Clip, str, int or None
        The clip written as the skeleton's ``SkelAnimation`` (by object, name or index);
        ``None``: the first clip, if any.
    fps : float
        Sampling rate of the animation and the stage's ``timeCodesPerSecond``.

    Returns
    -------
    pathlib.Path
        The written file.

    Notes
    -----
    Layout: ``/<Character> (SkelRoot)`` holding ``Skeleton``, ``Animation`` (``SkelAnimation``)
    and one ``Mesh`` per mesh. See the module docstring for the conventions converted.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt = _pxr()
    path = Path(path)
    sk = character.skeleton
    if sk.num_joints == 0:
        raise InputError(f"usd: {character.source or character.name} has no skeleton to write as UsdSkel")
    clip = _resolve_clip(character, clip)
    base, fold = _root_frames(sk)
    base_inv = np.linalg.inv(base)
    roots = sk.roots

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)

    root_name = _unique_identifiers([character.name or "Character"])[0]
    root = UsdSkel.Root.Define(stage, Sdf.Path("/" + root_name))
    stage.SetDefaultPrim(root.GetPrim())
    if not np.allclose(base, np.eye(4), atol=0):
        UsdGeom.Xformable(root).AddTransformOp().Set(_gf_matrix(base))

    # skeleton: joint paths, bind transforms (skel space), rest transforms (local)
    taken = {"Skeleton", "Animation"}
    skel = UsdSkel.Skeleton.Define(stage, root.GetPath().AppendChild("Skeleton"))
    joints = Vt.TokenArray(joint_paths(sk))
    skel.CreateJointsAttr(joints)
    skel.GetPrim().SetCustomDataByKey("rigmix:jointNames", Vt.StringArray(list(sk.names)))
    skel.CreateBindTransformsAttr(_gf_matrices(base_inv @ np.linalg.inv(sk.inverse_binds)))
    rest = sk.rest_locals()
    rest[roots] = fold[roots] @ rest[roots]
    skel.CreateRestTransformsAttr(_gf_matrices(rest))

    # animation: sampled on the clip's fps grid, end included
    if clip is not None:
        anim = UsdSkel.Animation.Define(stage, root.GetPath().AppendChild("Animation"))
        anim.CreateJointsAttr(joints)
        anim.GetPrim().SetCustomDataByKey("rigmix:clipName", clip.name)
        times = clip_times(clip, fps)
        T, R, S = sample_clip(sk, clip, times)
        folded = [r for r in roots if not np.array_equal(fold[r], np.eye(4))]
        if folded:
            L = trs_to_matrix(T[:, folded], R[:, folded], S[:, folded])
            T[:, folded], R[:, folded], S[:, folded] = matrix_to_trs(fold[folded] @ L)
        t_attr = anim.CreateTranslationsAttr()
        r_attr = anim.CreateRotationsAttr()
        s_attr = anim.CreateScalesAttr()
        for f, t in enumerate(times):
            code = Usd.TimeCode(float(t * fps))
            t_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(T[f], dtype=np.float32)), code)
            r_attr.Set(_quatf_array(R[f]), code)
            s_attr.Set(Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(S[f], dtype=np.float16)), code)
        stage.SetStartTimeCode(float(times[0] * fps))
        stage.SetEndTimeCode(float(times[-1] * fps))
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    # meshes, in skeleton space
    mesh_names = _unique_identifiers([m.name or "mesh" for m in character.meshes], taken)
    lin_inv = base_inv[:3, :3]
    normal_matrix = np.linalg.inv(lin_inv).T  # normals transform by the inverse transpose
    for mesh, name in zip(character.meshes, mesh_names):
        prim = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild(name))
        P = mesh.positions @ lin_inv.T + base_inv[:3, 3]
        prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(P, dtype=np.float32)))
        prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, dtype=np.int32)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.ravel(), dtype=np.int32)))
        prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        lo, hi = (P.min(axis=0), P.max(axis=0)) if len(P) else (np.zeros(3), np.zeros(3))
        prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        pv = UsdGeom.PrimvarsAPI(prim)
        if mesh.normals is not None:
            N = mesh.normals @ normal_matrix.T
            N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
            prim.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(N, dtype=np.float32)))
            prim.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        for i, uv in enumerate(mesh.uvs):
            st = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # glTF v down -> USD t up
            var = pv.CreatePrimvar("st" if i == 0 else f"st{i}", Sdf.ValueTypeNames.TexCoord2fArray,
                                   UsdGeom.Tokens.vertex)
            var.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(st, dtype=np.float32)))
        if mesh.colors is not None:
            prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
                Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.colors[:, :3], dtype=np.float32)))
        if not mesh.skinned:
            continue
        binding = UsdSkel.BindingAPI.Apply(prim.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        K = mesh.joints.shape[1]
        binding.CreateJointIndicesPrimvar(False, K).Set(
            Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.joints.ravel(), dtype=np.int32)))
        binding.CreateJointWeightsPrimvar(False, K).Set(
            Vt.FloatArray.FromNumpy(np.ascontiguousarray(mesh.weights.ravel(), dtype=np.float32)))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))

    path.parent.mkdir(parents=True, exist_ok=True)
    if not stage.GetRootLayer().Export(str(path)):
        raise InputError(f"usd: could not write {path} (check the folder and the extension: .usda, .usdc, .usd)")
    logger.debug("usd: wrote %s (%d joints, %d meshes)", path, sk.num_joints, len(character.meshes))
    return path
