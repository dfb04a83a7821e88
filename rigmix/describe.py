r"""Summaries for people: a character (``rigmix inspect``) and a composition (``rigmix compose``).

:func:`describe` gives a character's summary as plain values (the ``--json`` output of
``rigmix inspect``), :func:`format_description` the text report made from them, and
:func:`format_composition` the line ``rigmix compose`` prints once its files are written. The
command line and the demo print these; they read objects in memory only, never a file.

:func:`describe`'s keys
-----------------------
``file``, ``name``, ``skinned`` (bool: a skeleton and at least one skinned mesh),
``counts`` (``joints``, ``roots``, ``anchors``, ``meshes``, ``props``, ``vertices`` and
``faces`` over meshes and props, ``clips``, ``materials``, ``textures``, ``warnings``),
``joints`` (list of ``index``, ``name``, ``parent`` (name or null), ``parent_index``, ``depth``, ``anchor`` (name
of the anchor a root hangs from, or null), ``translation``, ``rotation`` (xyzw), ``scale``),
``anchors`` (``name``, ``parent``, ``translation``), ``meshes`` (``name``, ``vertices``,
``faces``, ``material`` (index), ``material_name``, ``skinned``, ``influences`` (largest number
of non-zero weights on one vertex, 0 if unskinned), ``slots`` (joint slots per vertex),
``normals``, ``uv_sets``, ``colors``), ``props`` (``name``, ``joint`` (name or null),
``vertices``, ``faces``, ``material``), ``materials`` (``index``, ``name``, ``base_color``,
``metallic``, ``roughness``, ``texture``: null or ``name``, ``mime_type``, ``bytes``),
``clips`` (``name``, ``start``, ``end``, ``duration`` in seconds, ``channels``, ``paths``
(path -> channel count), ``interpolations`` (sorted)), ``limbs`` (:func:`rigmix.limbs.limbs_summary`:
``kind`` (arm, leg, head, tail, wing or other), ``side``, ``root``, ``joints``, ``chain``,
``partner``, ``detached``, ``confidence``; empty without a skin), ``warnings`` (the defects
repaired on load, one string each).

Every string taken from a file (names, paths, MIME types, warnings) goes through
:func:`printable`: control characters and bidirectional overrides are shown escaped (``\x1b``,
``\u202e``), in the text and in the JSON alike, so that a name cannot move the cursor, colour
the terminal or forge lines. Each joint also has ``parent_index`` (index or null), so the tree
never depends on names that escaping could make equal.
"""

from __future__ import annotations

import logging
import re

import numpy as np

__all__ = ["describe", "format_description", "format_composition", "printable"]

logger = logging.getLogger(__name__)

#: C0 controls, DEL, C1 controls, the bidirectional embeddings, overrides and isolates (U+202A-E,
#: U+2066-9), the bidirectional marks (U+061C, U+200E, U+200F) and the line and paragraph
#: separators (U+2028, U+2029): what a terminal or an editor acts on instead of showing.
_UNPRINTABLE = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def _escape(m) -> str:
    c = ord(m.group())
    return f"\\x{c:02x}" if c < 0x100 else f"\\u{c:04x}"


def printable(text) -> str:
    r"""``str(text)`` with control and bidirectional-override characters escaped.

    ``"\x1b[31m"`` becomes the 7 characters ``\x1b[31m``, a newline ``\x0a``, U+202E
    ``\u202e``; every other character (accents, CJK, emoji, joiners) is kept.
    """
    text = str(text)
    return _UNPRINTABLE.sub(_escape, text) if _UNPRINTABLE.search(text) else text


def _p(text):
    return None if text is None else printable(text)


def _floats(a, digits=6):
    return [round(float(x), digits) for x in np.asarray(a).ravel()]


def describe(character, path=None) -> dict:
    """A JSON-ready summary of a character (see the module docstring for the keys).

    Parameters
    ----------
    character : rigmix.character.Character
    path : str or Path, optional
        The file it came from (default ``character.source``).

    Returns
    -------
    dict
        Plain Python values only (str, int, float, bool, list, dict, None).
    """
    sk = character.skeleton
    J = sk.num_joints
    depth = np.zeros(J, dtype=int)
    for j in range(J):  # topological order
        depth[j] = 0 if sk.parents[j] < 0 else depth[sk.parents[j]] + 1
    anchors = [
        {
            "name": printable(a.name),
            "parent": printable(sk.anchors[a.parent].name) if a.parent >= 0 else None,
            "translation": _floats(a.matrix[:3, 3]),
        }
        for a in sk.anchors
    ]
    joints = [
        {
            "index": j,
            "name": printable(sk.names[j]),
            "parent": printable(sk.names[sk.parents[j]]) if sk.parents[j] >= 0 else None,
            "parent_index": int(sk.parents[j]) if sk.parents[j] >= 0 else None,
            "depth": int(depth[j]),
            "anchor": printable(sk.anchors[sk.root_anchor[j]].name) if sk.root_anchor[j] >= 0 else None,
            "translation": _floats(sk.translations[j]),
            "rotation": _floats(sk.rotations[j]),
            "scale": _floats(sk.scales[j]),
        }
        for j in range(J)
    ]

    def material_name(i):
        return _p(character.materials[i].name) if 0 <= i < len(character.materials) else None

    meshes = []
    for m in character.meshes:
        influences = int((m.weights > 0).sum(axis=1).max()) if m.skinned and len(m.weights) else 0
        meshes.append({
            "name": printable(m.name),
            "vertices": len(m.positions),
            "faces": len(m.faces),
            "material": int(m.material),
            "material_name": material_name(m.material),
            "skinned": m.skinned,
            "influences": influences,
            "slots": int(m.joints.shape[1]) if m.skinned else 0,
            "normals": m.normals is not None,
            "uv_sets": len(m.uvs),
            "colors": m.colors is not None,
        })
    props = [
        {
            "name": printable(p.mesh.name),
            "joint": printable(sk.names[p.joint]) if 0 <= p.joint < J else None,
            "vertices": len(p.mesh.positions),
            "faces": len(p.mesh.faces),
            "material": int(p.mesh.material),
        }
        for p in character.props
    ]
    materials = []
    for i, mat in enumerate(character.materials):
        tex = mat.base_color_texture
        materials.append({
            "index": i,
            "name": _p(mat.name),
            "base_color": _floats(mat.base_color, 4),
            "metallic": round(float(mat.metallic), 4),
            "roughness": round(float(mat.roughness), 4),
            "texture": None if tex is None else
            {"name": _p(tex.name), "mime_type": _p(tex.mime_type), "bytes": len(tex.data)},
        })
    clips = []
    for c in character.clips:
        paths: dict[str, int] = {}
        for t in c.tracks:
            paths[printable(t.path)] = paths.get(printable(t.path), 0) + 1
        clips.append({
            "name": printable(c.name),
            "start": round(c.start, 6),
            "end": round(c.end, 6),
            "duration": round(c.duration, 6),
            "channels": len(c.tracks),
            "paths": paths,
            "interpolations": sorted({printable(t.interpolation) for t in c.tracks}),
        })
    all_meshes = list(character.meshes) + [p.mesh for p in character.props]
    counts = {
        "joints": J,
        "roots": int(len(sk.roots)),
        "anchors": len(sk.anchors),
        "meshes": len(character.meshes),
        "props": len(character.props),
        "vertices": int(sum(len(m.positions) for m in all_meshes)),
        "faces": int(sum(len(m.faces) for m in all_meshes)),
        "clips": len(character.clips),
        "materials": len(character.materials),
        "textures": sum(m.base_color_texture is not None for m in character.materials),
        "warnings": len(character.warnings),
    }
    return {
        "file": printable(path if path is not None else character.source),
        "name": printable(character.name),
        "skinned": bool(character.skinned),
        "counts": counts,
        "joints": joints,
        "anchors": anchors,
        "meshes": meshes,
        "props": props,
        "materials": materials,
        "clips": clips,
        "limbs": _limbs(character),
        "warnings": [printable(w) for w in character.warnings],
    }


def _limbs(character) -> list:
    """The limbs :mod:`rigmix.limbs` finds on a skinned character, names escaped (none without a skin)."""
    if not character.skinned:
        return []
    from .limbs import limbs_summary  # scipy and the mirror plane: loaded only when a skin is described

    rest = character.skeleton.rest_worlds()[:, :3, 3]
    with np.errstate(all="ignore"):
        extent = float(np.abs(rest).max()) if len(rest) else 0.0
    if not np.isfinite(extent) or extent > 1e6:  # a skeleton out of range has no meaningful limbs
        return []
    try:
        rows = limbs_summary(character)
    except (ValueError, IndexError, ArithmeticError, np.linalg.LinAlgError) as e:
        # the summary is an aid: a rig it cannot read is still described (and composes or not)
        logger.warning("%s: limbs not classified (%s)", printable(character.name), printable(e))
        return []

    def clean(v):
        if isinstance(v, str):
            return printable(v)
        return [clean(x) for x in v] if isinstance(v, list) else v

    return [{k: clean(v) for k, v in row.items()} for row in rows]


def _vec(v):
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _depth_first(joints: list) -> list:
    """The joint entries in depth-first order (children under their parent), roots in order."""
    children: dict = {}
    for j in joints:  # by index: names may repeat once escaped
        children.setdefault(j["parent_index"], []).append(j)
    out, stack = [], list(reversed(children.get(None, [])))
    while stack:
        j = stack.pop()
        out.append(j)
        stack.extend(reversed(children.get(j["index"], [])))
    return out


def format_description(d: dict) -> str:
    """The text report of ``rigmix inspect`` from :func:`describe`'s dict."""
    c = d["counts"]
    lines = [f"{d['file'] or d['name']}: character '{d['name']}'"]
    if d["skinned"]:
        lines.append(f"skin: yes ({c['joints']} joints, {sum(m['skinned'] for m in d['meshes'])} skinned mesh(es))")
    else:
        lines.append("skin: none (no skin: a static model; it can be viewed but not composed)")
    lines.append("counts: " + ", ".join(f"{k} {v}" for k, v in c.items()))

    lines.append(f"anchors ({len(d['anchors'])}):" if d["anchors"] else "anchors: none")
    for a in d["anchors"]:
        under = f" under '{a['parent']}'" if a["parent"] else ""
        lines.append(f"  {a['name']}{under}  t={_vec(a['translation'])}")

    lines.append(f"joints ({len(d['joints'])}):" if d["joints"] else "joints: none")
    for j in _depth_first(d["joints"]):
        extra = ""
        if j["parent"] is None:
            extra = f"  [root, under anchor '{j['anchor']}']" if j["anchor"] else "  [root]"
        # indentation capped: a chain 100k joints deep would otherwise print ~10 GB of spaces
        indent = "  " * j["depth"] if j["depth"] <= 40 else f"{'  ' * 40}[{j['depth']}] "
        lines.append(f"  {indent}{j['name']}  t={_vec(j['translation'])}{extra}")

    lines.append(f"meshes ({len(d['meshes'])}):" if d["meshes"] else "meshes: none (no skinned mesh)")
    for m in d["meshes"]:
        mat = ("default material" if m["material"] < 0 else
               f"material {m['material']}" + (f" '{m['material_name']}'" if m["material_name"] else ""))
        skin = f"skinned, {m['influences']} influences max" if m["skinned"] else "not skinned"
        attrs = [a for a, on in (("normals", m["normals"]), ("colors", m["colors"])) if on]
        if m["uv_sets"]:
            attrs.append(f"{m['uv_sets']} uv set(s)")
        lines.append(f"  {m['name']}: {m['vertices']} vertices, {m['faces']} faces, {mat}, {skin}"
                     + (f"; {', '.join(attrs)}" if attrs else ""))

    lines.append(f"props ({len(d['props'])}):" if d["props"] else "props: none")
    for p in d["props"]:
        where = f"on joint '{p['joint']}'" if p["joint"] else "static (world)"
        lines.append(f"  {p['name']}: {p['vertices']} vertices, {p['faces']} faces, material {p['material']}, {where}")

    lines.append(f"materials ({len(d['materials'])}):" if d["materials"] else "materials: none")
    for m in d["materials"]:
        tex = m["texture"]
        tex_s = f", texture '{tex['name']}' {tex['mime_type']} {tex['bytes']} bytes" if tex else ""
        lines.append(f"  {m['index']} '{m['name']}': base colour {_vec(m['base_color'])}{tex_s}")

    lines.append(f"clips ({len(d['clips'])}):" if d["clips"] else "clips: none")
    for cl in d["clips"]:
        paths = ", ".join(f"{k} {v}" for k, v in cl["paths"].items())
        lines.append(f"  '{cl['name']}': {cl['duration']:.4g} s, {cl['channels']} channels ({paths}), "
                     f"{'/'.join(cl['interpolations'])}")

    limbs = d.get("limbs", [])
    lines.append(f"limbs ({len(limbs)}):" if limbs else "limbs: none")
    for lb in limbs:
        side = f" {lb['side']}" if lb["side"] else ""
        partner = f", mirror of '{lb['partner']}'" if lb["partner"] else ""
        lines.append(f"  {lb['kind']}{side}: '{lb['root']}' ({lb['joints']} joints{partner})")

    lines.append(f"repaired defects ({len(d['warnings'])}):" if d["warnings"] else "repaired defects: none")
    lines += [f"  {w}" for w in d["warnings"]]
    return "\n".join(lines)


def format_composition(composition, output, gates=None) -> str:
    """The one-line summary of a composition written to ``output``.

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        A full composition (its ``character`` is set).
    output : str or Path
        The character file written.
    gates : sequence of dict, optional
        Its hard gates (:func:`rigmix.gates.evaluate_gates`), summarized when given.

    Returns
    -------
    str
        Joints, vertices, faces and clips of the result, the junction weight method, the
        junction stretch ratio, the total time in seconds and ``gates: N/M passed`` (with the
        failed gates' names).
    """
    from .gates import gate_summary

    report = composition.report
    w, m, q = report.get("weights", {}), report.get("mesh", {}), report.get("quality", {})
    text = (f"{printable(output)}: {composition.skeleton.num_joints} joints, {m.get('vertices')} vertices, "
            f"{m.get('faces')} faces, {len(composition.character.clips)} clips; weights {w.get('method')}; "
            f"junction stretch ratio {q.get('junction_stretch_ratio')}; {report['timings']['total']:.1f} s")
    return text + (f"; {gate_summary(list(gates))}" if gates else "")
