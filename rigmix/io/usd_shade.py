"""USD materials: glTF metallic-roughness materials as ``UsdPreviewSurface`` networks.

Part of the USD exporter (:mod:`rigmix.io.usd`). Each :class:`rigmix.character.Material`
becomes one ``UsdShade.Material`` holding:

* ``PreviewSurface`` (``UsdPreviewSurface``): ``diffuseColor`` (base colour RGB), ``opacity``
  (base colour alpha, for ``MASK`` and ``BLEND``; ``opacityThreshold`` = alpha cutoff for
  ``MASK``), ``metallic``, ``roughness``, ``emissiveColor``;
* with a base colour texture: ``BaseColorTexture`` (``UsdUVTexture``, ``file`` =
  ``textures/<image>``, ``scale`` = the base colour factor, as glTF multiplies them, wrap modes
  from the glTF sampler, ``sourceColorSpace = sRGB``) whose ``rgb`` (and ``a``) drive the
  surface, and ``STReader`` (``UsdPrimvarReader_float2``) reading the mesh's ``st`` primvar
  (``st<n>`` for ``TEXCOORD_n``).

Texture images are written byte for byte (PNG or JPEG, never re-encoded) to a ``textures/``
folder next to the layer; identical images are written once.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from ..safety import atomic_write_bytes

__all__ = ["texture_files", "define_materials", "write_texture_files"]

#: glTF sampler wrap modes -> UsdUVTexture wrapS/wrapT tokens.
_WRAP = {33071: "clamp", 33648: "mirror", 10497: "repeat"}

_EXT = {"image/png": ".png", "image/jpeg": ".jpg"}


def texture_files(materials, prefix, make_identifiers):
    """Relative file names for the base colour textures of ``materials``.

    Parameters
    ----------
    materials : sequence of rigmix.character.Material
    prefix : str
        Prepended to every file name (the character's prim name), so that several exports into
        one folder do not overwrite each other's textures.
    make_identifiers : callable
        ``names -> valid unique identifiers`` (the exporter's sanitizer).

    Returns
    -------
    names : list of (str or None)
        Per material, ``"textures/<file>"`` or None when it has no texture.
    files : dict str -> bytes
        Relative file name -> encoded image, one entry per distinct image.
    """
    by_digest = {}
    names = []
    files = {}
    stems = []
    for m in materials:
        tex = m.base_color_texture
        if tex is None:
            names.append(None)
            continue
        digest = hashlib.sha256(tex.data).hexdigest()
        if digest not in by_digest:
            stem = make_identifiers([f"{prefix}_{tex.name or m.name or 'texture'}"], stems)[0]
            stems.append(stem)
            rel = f"textures/{stem}{_EXT.get(tex.mime_type, '.png')}"
            by_digest[digest] = rel
            files[rel] = tex.data
        names.append(by_digest[digest])
    return names, files


def write_texture_files(files, folder):
    """Write ``{relative name: bytes}`` under ``folder``, each atomically (temp file + rename)."""
    folder = Path(folder)
    for rel, data in files.items():
        target = folder / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(target, data)


def define_materials(stage, scope_path, materials, identifiers, texture_names):
    """Define one ``UsdShade.Material`` per material under ``scope_path``.

    Parameters
    ----------
    stage : Usd.Stage
    scope_path : Sdf.Path
        A ``Scope`` prim (defined here) holding the materials.
    materials : sequence of rigmix.character.Material
    identifiers : list of str
        Valid, unique prim names, one per material.
    texture_names : list of (str or None)
        From :func:`texture_files`.

    Returns
    -------
    list of UsdShade.Material
        In the order of ``materials``.
    """
    from pxr import Gf, Sdf, UsdGeom, UsdShade

    UsdGeom.Scope.Define(stage, scope_path)
    out = []
    for m, ident, tex_name in zip(materials, identifiers, texture_names):
        mat = UsdShade.Material.Define(stage, scope_path.AppendChild(ident))
        if m.name:
            mat.GetPrim().SetCustomDataByKey("rigmix:name", m.name)
        surf = UsdShade.Shader.Define(stage, mat.GetPath().AppendChild("PreviewSurface"))
        surf.CreateIdAttr("UsdPreviewSurface")
        rgba = [float(c) for c in m.base_color]
        surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(m.metallic))
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(m.roughness))
        surf.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, m.emissive)))
        diffuse = surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
        opacity = surf.CreateInput("opacity", Sdf.ValueTypeNames.Float)
        transparent = m.alpha_mode in ("MASK", "BLEND")
        if m.alpha_mode == "MASK":
            surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(float(m.alpha_cutoff))
        if tex_name is None:
            diffuse.Set(Gf.Vec3f(*rgba[:3]))
            opacity.Set(rgba[3] if transparent else 1.0)
        else:
            reader = UsdShade.Shader.Define(stage, mat.GetPath().AppendChild("STReader"))
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            varname = "st" if m.base_color_texcoord == 0 else f"st{m.base_color_texcoord}"
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set(varname)
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
            tex = UsdShade.Shader.Define(stage, mat.GetPath().AppendChild("BaseColorTexture"))
            tex.CreateIdAttr("UsdUVTexture")
            tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath("./" + tex_name))
            tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
                reader.ConnectableAPI(), "result")
            tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*rgba))
            sampler = m.base_color_texture.sampler or {}
            tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(_WRAP.get(sampler.get("wrapS", 10497), "repeat"))
            tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(_WRAP.get(sampler.get("wrapT", 10497), "repeat"))
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
            diffuse.ConnectToSource(tex.ConnectableAPI(), "rgb")
            if transparent:
                tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
                opacity.ConnectToSource(tex.ConnectableAPI(), "a")
            else:
                opacity.Set(1.0)
        surf.CreateOutput("surface", Sdf.ValueTypeNames.Token)
        mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
        out.append(mat)
    return out
