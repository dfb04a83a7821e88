"""The output character: fused surface + W_R + A_R + the inputs' materials and props.

:func:`assemble_character` turns the results of the stages into a :class:`Character`:

* preserved faces are grouped by (input, material) into one mesh each; their vertices carry
  the input mesh's own attributes (every UV set, normals, colours) copied bit-identically;
* junction faces form one mesh ``<name>.junction`` with a plain material and vertex colours
  interpolated from the closest input points (textures baked to vertex colours first, as in the
  paper), smooth normals from the fused surface;
* props on kept joints follow the output joint of that joint, at the same rest place (their
  matrix re-expressed in the output joint's unit-scale frame); static props are kept; props on
  dropped joints are dropped with a warning naming them;
* materials equal in everything but their name are written once, unused ones not at all;
* the skeleton is S_R (its anchors are the plan's), the clips those of the completion stage.
"""

from __future__ import annotations

import io
import logging
from dataclasses import replace
from functools import lru_cache

import numpy as np

from dfd.mesh import vertex_normals

from .character import Character, Material, Mesh, Prop
from .weights import closest_point_weights, to_influences

__all__ = ["assemble_character", "baked_colors", "deduplicate_materials", "input_mesh_ranges"]

log = logging.getLogger(__name__)


def input_mesh_ranges(character) -> dict:
    """``{mesh index: first split vertex}`` of the meshes :func:`rigmix.fusion.inputs.fusion_input` concatenates."""
    out, base = {}, 0
    for k, m in enumerate(character.meshes):
        if m.skinned and len(m.faces):
            out[k] = base
            base += len(m.positions)
    return out


@lru_cache(maxsize=16)
def _decode(data: bytes) -> np.ndarray:
    from PIL import Image

    img = Image.open(io.BytesIO(data)).convert("RGBA")
    return np.asarray(img, dtype=np.float64) / 255.0


def _srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def baked_colors(mesh: Mesh, material: Material | None) -> np.ndarray:
    """Linear RGBA per vertex: base colour factor x texture (nearest texel, sRGB decoded) x COLOR_0.

    Parameters
    ----------
    mesh : Mesh
    material : Material or None
        ``None`` for the default material (white).

    Returns
    -------
    (n, 4) float64 in [0, 1]
    """
    n = len(mesh.positions)
    c = np.ones((n, 4)) if mesh.colors is None else np.asarray(mesh.colors, np.float64).copy()
    if material is None:
        return c
    c *= material.base_color[None, :]
    tex = material.base_color_texture
    if tex is not None and len(mesh.uvs) > material.base_color_texcoord:
        try:
            img = _decode(tex.data)
        except Exception as e:  # an undecodable image: keep the factor (the texture stays on preserved faces)
            log.warning("assembly: texture %r of material %r could not be decoded (%s); junction colours "
                        "use the base colour only", tex.name, material.name, e)
            return np.clip(c, 0.0, 1.0)
        H, Wd = img.shape[:2]
        uv = np.asarray(mesh.uvs[material.base_color_texcoord], np.float64)
        x = np.clip((np.mod(uv[:, 0], 1.0) * Wd).astype(np.int64), 0, Wd - 1)
        y = np.clip((np.mod(uv[:, 1], 1.0) * H).astype(np.int64), 0, H - 1)
        t = img[y, x]
        c[:, :3] *= _srgb_to_linear(t[:, :3])
        c[:, 3] *= t[:, 3]
    return np.clip(c, 0.0, 1.0)


def _mesh_attributes(positioned, k, local):
    """Attributes of the split vertices ``local`` of mesh ``k`` of a positioned character."""
    m = positioned.meshes[k]
    return (tuple(np.asarray(u)[local] for u in m.uvs),
            None if m.normals is None else np.asarray(m.normals)[local],
            None if m.colors is None else np.asarray(m.colors)[local])


def assemble_character(composition) -> Character:
    """The composed character.

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        After the fusion, weight and completion stages (``surface``,
        ``weights``, ``fusion_inputs``, ``fusion_ids``,
        optionally ``clips``).

    Returns
    -------
    Character
        Skinned meshes in the bind space of S_R (world space at rest), materials of every input
        (in input order) plus one junction material, props re-targeted, clips A_R.
    """
    plan = composition.plan
    surface = composition.surface
    skin = composition.weights
    ids = list(composition.fusion_ids)
    inputs = composition.fusion_inputs
    clips = tuple(composition.clips)
    V, F = np.asarray(surface.V), np.asarray(surface.F)
    joints_all, weights_all = to_influences(skin.W, 4)

    materials, mat_base = [], {}
    for cid in ids:
        mat_base[cid] = len(materials)
        materials.extend(plan.positioned[cid].materials)

    meshes = []
    fo_in = np.asarray(surface.face_origin_input)
    # faces from inputs (preserved, and any kept by a face-selection fallback), by (input, material)
    for i, cid in enumerate(ids):
        ch = plan.positioned[cid]
        starts = input_mesh_ranges(ch)
        fi = np.flatnonzero(fo_in == i)
        if not len(fi):
            continue
        kof = np.asarray(surface.mesh_of_vertex)[F[fi, 0]]
        mat_of_face = np.array([ch.meshes[k].material for k in kof], np.int64)
        for mat in np.unique(mat_of_face):
            faces = fi[mat_of_face == mat]
            verts, Fl = np.unique(F[faces].ravel(), return_inverse=True)
            Fl = Fl.reshape(-1, 3)
            kv = np.asarray(surface.mesh_of_vertex)[verts]
            ov = np.asarray(surface.origin_vertex)[verts]
            # attributes from the input meshes themselves (every UV set), bit-identical
            ks = np.unique(kv)
            uv_sets = min(len(ch.meshes[k].uvs) for k in ks)
            has_n = all(ch.meshes[k].normals is not None for k in ks)
            has_c = any(ch.meshes[k].colors is not None for k in ks)
            uvs = [np.zeros((len(verts), 2)) for _ in range(uv_sets)]
            nrm = np.zeros((len(verts), 3)) if has_n else None
            col = np.ones((len(verts), 4)) if has_c else None
            for k in ks:
                sel = kv == k
                local = ov[sel] - starts[int(k)]
                u, n, c = _mesh_attributes(ch, int(k), local)
                for s in range(uv_sets):
                    uvs[s][sel] = u[s]
                if has_n:
                    nrm[sel] = n
                if has_c and c is not None:
                    col[sel] = c
            named = 0 <= mat < len(ch.materials) and ch.materials[mat].name
            mname = ch.materials[mat].name if named else f"material{mat}"
            meshes.append(Mesh(name=f"{cid}.{mname}", positions=V[verts], faces=Fl, normals=nrm, uvs=tuple(uvs),
                               colors=col, joints=joints_all[verts], weights=weights_all[verts],
                               material=mat_base[cid] + int(mat) if mat >= 0 else -1))

    jf = np.flatnonzero(fo_in < 0)
    if len(jf):
        verts, Fl = np.unique(F[jf].ravel(), return_inverse=True)
        Fl = Fl.reshape(-1, 3)
        colors = _junction_colors(surface, inputs, ids, plan, verts)
        normals = vertex_normals(V, F)[verts]
        normals[~normals.any(axis=1)] = (0.0, 1.0, 0.0)  # glTF requires unit normals
        rough = [m.roughness for m in materials] or [1.0]
        materials.append(Material(name=f"{composition.config.name}.junction", base_color=np.ones(4),
                                  metallic=0.0, roughness=float(np.median(rough))))
        meshes.append(Mesh(name=f"{composition.config.name}.junction", positions=V[verts], faces=Fl,
                           normals=normals, colors=colors, joints=joints_all[verts], weights=weights_all[verts],
                           material=len(materials) - 1))

    props, dropped = [], []
    out_worlds = composition.skeleton.rest_worlds()
    for cid in ids:
        ch = plan.positioned[cid]
        in_worlds = ch.skeleton.rest_worlds()
        for p in ch.props:
            mat = p.mesh.material
            mesh = Mesh(name=f"{cid}.{p.mesh.name}", positions=p.mesh.positions, faces=p.mesh.faces,
                        normals=p.mesh.normals, uvs=p.mesh.uvs, colors=p.mesh.colors,
                        material=mat_base[cid] + mat if mat >= 0 else -1)
            if p.joint < 0:
                props.append(Prop(mesh, -1, p.matrix))
                continue
            o = int(plan.image[cid][p.joint])
            if o < 0:
                dropped.append(f"assembly: prop '{p.mesh.name}' of {cid!r} is parented to joint "
                               f"'{ch.skeleton.names[p.joint]}', which the composition removes: dropped")
                log.warning(dropped[-1])
                continue
            # relative to the output joint's frame, which is rigid where the input's was scaled
            props.append(Prop(mesh, o, np.linalg.inv(out_worlds[o]) @ in_worlds[p.joint] @ p.matrix))
    warnings = tuple(w for cid in ids for w in composition.inputs[cid].warnings) + tuple(dropped)
    meshes, props, materials = deduplicate_materials(meshes, props, materials)
    return Character(name=composition.config.name, skeleton=composition.skeleton, meshes=tuple(meshes),
                     clips=clips, materials=tuple(materials), props=tuple(props), source="",
                     warnings=warnings)


def _material_key(m: Material) -> tuple:
    """Everything a material renders with, its name aside."""
    tex = m.base_color_texture
    tex_key = None if tex is None else (tex.data, tex.mime_type, repr(sorted(tex.sampler.items())))
    return (m.base_color.tobytes(), float(m.metallic), float(m.roughness), tex_key, int(m.base_color_texcoord),
            bool(m.double_sided), m.alpha_mode, float(m.alpha_cutoff), m.emissive.tobytes(),
            repr(sorted(m.extra.items())))


def deduplicate_materials(meshes, props, materials):
    """Materials merged by content and pruned to those used.

    Two inputs made in one tool often carry equal materials (``Black`` in both): the output keeps
    one, under the first one's name, and drops the materials no mesh or prop uses (those of
    removed parts).

    Parameters
    ----------
    meshes : sequence of Mesh
    props : sequence of Prop
    materials : sequence of Material
        ``Mesh.material`` indexes it (``-1``: the default material).

    Returns
    -------
    (list of Mesh, list of Prop, list of Material)
        The same meshes and props, their ``material`` re-indexed into the returned materials
        (first-use order of the original indices kept).
    """
    used = sorted({m.material for m in meshes if m.material >= 0} | {p.mesh.material for p in props
                                                                      if p.mesh.material >= 0})
    new_index, kept, by_key = {}, [], {}
    for k in used:
        key = _material_key(materials[k])
        if key not in by_key:
            by_key[key] = len(kept)
            kept.append(materials[k])
        new_index[k] = by_key[key]

    def remap(mesh):
        return mesh if mesh.material < 0 else replace(mesh, material=new_index[mesh.material])

    return ([remap(m) for m in meshes], [replace(p, mesh=remap(p.mesh)) for p in props], kept)


def _junction_colors(surface, inputs, ids, plan, verts):
    """Linear RGBA of the junction mesh's vertices: input vertices keep their baked colour,
    new vertices interpolate the closest input points (presence over distance)."""
    baked = []
    for i, cid in enumerate(ids):
        ch = plan.positioned[cid]
        parts = []
        for k in input_mesh_ranges(ch):
            m = ch.meshes[k]
            mat = ch.materials[m.material] if 0 <= m.material < len(ch.materials) else None
            parts.append(baked_colors(m, mat))
        baked.append(np.concatenate(parts) if parts else np.ones((len(inputs[i].V), 4)))
    out = np.ones((len(verts), 4))
    oi = np.asarray(surface.origin_input)[verts]
    ov = np.asarray(surface.origin_vertex)[verts]
    for i in range(len(ids)):
        sel = oi == i
        out[sel] = baked[i][ov[sel]]
    new = oi < 0
    if new.any() and len(surface.junction_sources):
        rows = np.searchsorted(np.flatnonzero(surface.junction_vertices), verts[new])
        srcs = [{k: np.asarray(v)[rows] for k, v in s.items()} for s in surface.junction_sources]
        diag = float(np.linalg.norm(np.ptp(surface.V, axis=0)))
        c, _ = closest_point_weights(srcs, baked, [x.F for x in inputs], tolerance=0.05 * diag)
        out[new] = np.clip(c, 0.0, 1.0)
    return out
