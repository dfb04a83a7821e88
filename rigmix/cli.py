"""The ``rigmix`` command line; the only place that configures logging.

Usage::

    rigmix [-v] [--debug] <command> ...
    rigmix inspect FILE [--json]
    rigmix convert IN OUT
    rigmix render FILE [--clip NAME] [--gif OUT.gif] [--mp4 OUT.mp4] [--sheet OUT.png]
    rigmix preview FILE.glb [--out DIR] [--port N] [--no-serve]
    rigmix map CONFIG [--json]
    rigmix schema

Adding a command
----------------
Write ``_add_<name>(parser)`` (declares the arguments of its ``argparse`` sub-parser) and
``_run_<name>(args) -> int`` (does the work, returns the exit status), then append one
:class:`Command` to :data:`COMMANDS`. Heavy imports go inside ``_run_<name>``, so that
``rigmix --help`` stays fast.

Errors
------
A :class:`rigmix.errors.RigmixError` (or an ``OSError`` such as a missing file) is printed as
one line ``rigmix: error: <message>`` on stderr, exit status 2, no traceback; any other
exception is reported the same way as an internal error, exit status 1. ``--debug`` re-raises
instead (full traceback). Library code never prints: it logs through
``logging.getLogger(__name__)``; warnings go to stderr, ``-v`` adds info, ``-vv`` debug.

``rigmix inspect --json`` keys
------------------------------
``file``, ``name``, ``skinned`` (bool: a skeleton and at least one skinned mesh),
``counts`` (``joints``, ``roots``, ``anchors``, ``meshes``, ``props``, ``vertices`` and
``faces`` over meshes and props, ``clips``, ``materials``, ``textures``, ``warnings``),
``joints`` (list of ``index``, ``name``, ``parent`` (name or null), ``depth``, ``anchor`` (name
of the anchor a root hangs from, or null), ``translation``, ``rotation`` (xyzw), ``scale``),
``anchors`` (``name``, ``parent``, ``translation``), ``meshes`` (``name``, ``vertices``,
``faces``, ``material`` (index), ``material_name``, ``skinned``, ``influences`` (largest number
of non-zero weights on one vertex, 0 if unskinned), ``slots`` (joint slots per vertex),
``normals``, ``uv_sets``, ``colors``), ``props`` (``name``, ``joint`` (name or null),
``vertices``, ``faces``, ``material``), ``materials`` (``index``, ``name``, ``base_color``,
``metallic``, ``roughness``, ``texture``: null or ``name``, ``mime_type``, ``bytes``),
``clips`` (``name``, ``start``, ``end``, ``duration`` in seconds, ``channels``, ``paths``
(path -> channel count), ``interpolations`` (sorted)), ``warnings`` (the defects repaired on
load, one string each).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import __version__
from .errors import RigmixError

__all__ = ["main", "build_parser", "describe", "format_description", "Command", "COMMANDS"]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# describe: Character -> plain dict (shared by the text and JSON printers)
# --------------------------------------------------------------------------------------------


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
            "name": a.name,
            "parent": sk.anchors[a.parent].name if a.parent >= 0 else None,
            "translation": _floats(a.matrix[:3, 3]),
        }
        for a in sk.anchors
    ]
    joints = [
        {
            "index": j,
            "name": sk.names[j],
            "parent": sk.names[sk.parents[j]] if sk.parents[j] >= 0 else None,
            "depth": int(depth[j]),
            "anchor": sk.anchors[sk.root_anchor[j]].name if sk.root_anchor[j] >= 0 else None,
            "translation": _floats(sk.translations[j]),
            "rotation": _floats(sk.rotations[j]),
            "scale": _floats(sk.scales[j]),
        }
        for j in range(J)
    ]

    def material_name(i):
        return character.materials[i].name if 0 <= i < len(character.materials) else None

    meshes = []
    for m in character.meshes:
        influences = int((m.weights > 0).sum(axis=1).max()) if m.skinned and len(m.weights) else 0
        meshes.append({
            "name": m.name,
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
            "name": p.mesh.name,
            "joint": sk.names[p.joint] if 0 <= p.joint < J else None,
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
            "name": mat.name,
            "base_color": _floats(mat.base_color, 4),
            "metallic": round(float(mat.metallic), 4),
            "roughness": round(float(mat.roughness), 4),
            "texture": None if tex is None else
            {"name": tex.name, "mime_type": tex.mime_type, "bytes": len(tex.data)},
        })
    clips = []
    for c in character.clips:
        paths: dict[str, int] = {}
        for t in c.tracks:
            paths[t.path] = paths.get(t.path, 0) + 1
        clips.append({
            "name": c.name,
            "start": round(c.start, 6),
            "end": round(c.end, 6),
            "duration": round(c.duration, 6),
            "channels": len(c.tracks),
            "paths": paths,
            "interpolations": sorted({t.interpolation for t in c.tracks}),
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
        "file": str(path if path is not None else character.source),
        "name": character.name,
        "skinned": bool(character.skinned),
        "counts": counts,
        "joints": joints,
        "anchors": anchors,
        "meshes": meshes,
        "props": props,
        "materials": materials,
        "clips": clips,
        "warnings": list(character.warnings),
    }


def _vec(v):
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _depth_first(joints: list) -> list:
    """The joint entries in depth-first order (children under their parent), roots in order."""
    children: dict = {}
    for j in joints:
        children.setdefault(j["parent"], []).append(j)
    out, stack = [], list(reversed(children.get(None, [])))
    while stack:
        j = stack.pop()
        out.append(j)
        stack.extend(reversed(children.get(j["name"], [])))
    return out


def format_description(d: dict) -> str:
    """The text report of ``rigmix inspect`` from :func:`describe`'s dict."""
    c = d["counts"]
    lines = [f"{d['file'] or d['name']}: character {d['name']!r}"]
    if d["skinned"]:
        lines.append(f"skin: yes ({c['joints']} joints, {sum(m['skinned'] for m in d['meshes'])} skinned mesh(es))")
    else:
        lines.append("skin: none (no skin: a static model; it can be viewed but not composed)")
    lines.append("counts: " + ", ".join(f"{k} {v}" for k, v in c.items()))

    lines.append(f"anchors ({len(d['anchors'])}):" if d["anchors"] else "anchors: none")
    for a in d["anchors"]:
        under = f" under {a['parent']!r}" if a["parent"] else ""
        lines.append(f"  {a['name']}{under}  t={_vec(a['translation'])}")

    lines.append(f"joints ({len(d['joints'])}):" if d["joints"] else "joints: none")
    for j in _depth_first(d["joints"]):
        extra = ""
        if j["parent"] is None:
            extra = f"  [root, under anchor {j['anchor']!r}]" if j["anchor"] else "  [root]"
        # indentation capped: a chain 100k joints deep would otherwise print ~10 GB of spaces
        indent = "  " * j["depth"] if j["depth"] <= 40 else f"{'  ' * 40}[{j['depth']}] "
        lines.append(f"  {indent}{j['name']}  t={_vec(j['translation'])}{extra}")

    lines.append(f"meshes ({len(d['meshes'])}):" if d["meshes"] else "meshes: none (no skinned mesh)")
    for m in d["meshes"]:
        mat = ("default material" if m["material"] < 0 else
               f"material {m['material']}" + (f" {m['material_name']!r}" if m["material_name"] else ""))
        skin = f"skinned, {m['influences']} influences max" if m["skinned"] else "not skinned"
        attrs = [a for a, on in (("normals", m["normals"]), ("colors", m["colors"])) if on]
        if m["uv_sets"]:
            attrs.append(f"{m['uv_sets']} uv set(s)")
        lines.append(f"  {m['name']}: {m['vertices']} vertices, {m['faces']} faces, {mat}, {skin}"
                     + (f"; {', '.join(attrs)}" if attrs else ""))

    lines.append(f"props ({len(d['props'])}):" if d["props"] else "props: none")
    for p in d["props"]:
        where = f"on joint {p['joint']!r}" if p["joint"] else "static (world)"
        lines.append(f"  {p['name']}: {p['vertices']} vertices, {p['faces']} faces, material {p['material']}, {where}")

    lines.append(f"materials ({len(d['materials'])}):" if d["materials"] else "materials: none")
    for m in d["materials"]:
        tex = m["texture"]
        tex_s = f", texture {tex['name']!r} {tex['mime_type']} {tex['bytes']} bytes" if tex else ""
        lines.append(f"  {m['index']} {m['name']!r}: base colour {_vec(m['base_color'])}{tex_s}")

    lines.append(f"clips ({len(d['clips'])}):" if d["clips"] else "clips: none")
    for cl in d["clips"]:
        paths = ", ".join(f"{k} {v}" for k, v in cl["paths"].items())
        lines.append(f"  {cl['name']!r}: {cl['duration']:.4g} s, {cl['channels']} channels ({paths}), "
                     f"{'/'.join(cl['interpolations'])}")

    lines.append(f"repaired defects ({len(d['warnings'])}):" if d["warnings"] else "repaired defects: none")
    lines += [f"  {w}" for w in d["warnings"]]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """One sub-command: its name, one-line help, argument declaration and runner."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _add_inspect(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("--json", action="store_true", help="print a JSON object instead of text")


def _run_inspect(args) -> int:
    from .io import load_character

    path = args.file
    try:
        character = load_character(path)
    except RigmixError as exc:
        if path.name not in str(exc):  # every message must name the file
            raise type(exc)(f"inspect: {path}: {exc}") from exc
        raise
    d = describe(character, path)
    print(json.dumps(d, indent=2) if args.json else format_description(d))
    return 0


def _add_map(parser):
    parser.add_argument("config", type=Path, help="a composition config (.toml)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON object: output_joints, mapping rows (character, input_joint, "
                             "output_joint, confidence) and the operations report (scales, fused pairs)")


def _run_map(args) -> int:
    from .pipeline import compose, mapping_table

    comp = compose(args.config, until="mapping")
    rows = mapping_table(comp)
    if args.json:
        print(json.dumps({"config": str(args.config), "output_joints": list(comp.skeleton.names),
                          "mapping": rows, "operations": comp.report["operations"]}, indent=2))
        return 0
    heads = ("character", "input joint", "output joint", "confidence")
    cells = [(r["character"], r["input_joint"], r["output_joint"] or "-", f"{r['confidence']:.3f}") for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(heads, widths)).rstrip()]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells]
    for cid, info in comp.report["operations"]["characters"].items():
        lines.append(f"# {cid}: scale {info['scale']:.6g} ({info['scale_method']})")
    print("\n".join(lines))
    return 0


def _add_schema(parser):
    pass


def _run_schema(args) -> int:
    from .config import config_schema

    print(json.dumps(config_schema(), indent=2))
    return 0


def _add_convert(parser):
    parser.add_argument("input", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("output", type=Path,
                        help="the file to write: .usda, .usdc, .usd (crate), .usdz, .glb or .gltf; USD keeps "
                             "every clip (an 'animation' variant set), materials and textures (textures/ beside it)")


def _run_convert(args) -> int:
    from .io.convert import convert

    character = convert(args.input, args.output)
    print(f"{args.output}: {character.skeleton.num_joints} joints, {len(character.meshes)} meshes, "
          f"{len(character.props)} props, {len(character.clips)} clips, {len(character.materials)} materials")
    return 0


def _add_render(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("--clip", help="the clip to render (default: the first; the rest pose if there is none)")
    parser.add_argument("--gif", type=Path, help="write an animated GIF")
    parser.add_argument("--mp4", type=Path, help="write an MP4 video (needs imageio-ffmpeg)")
    parser.add_argument("--sheet", type=Path, help="write a contact sheet PNG of frames over the clip")
    parser.add_argument("--size", type=int, nargs=2, default=(480, 480), metavar=("W", "H"), help="pixels")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    parser.add_argument("--azimuth", type=float, default=30.0, help="camera degrees around +Y from the front")
    parser.add_argument("--elevation", type=float, default=15.0, help="camera degrees above the horizon")
    parser.add_argument("--backend", choices=("auto", "gl", "pil"), default="auto",
                        help="gl: OpenGL on EGL (Mesa, CPU); pil: Pillow fallback; auto: gl if it works")
    parser.add_argument("--bones", action="store_true", help="draw the skeleton over the character")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_render(args) -> int:
    from tqdm import tqdm

    from .errors import InputError
    from .io import load_character
    from .preview.render import render_clip

    outputs = [p for p in (args.gif, args.mp4, args.sheet) if p is not None]
    if not outputs:
        raise InputError("render: nothing to write; give --gif OUT.gif, --mp4 OUT.mp4 or --sheet OUT.png")
    character = load_character(args.file)
    with tqdm(desc="render", unit="frame", disable=args.no_progress, file=sys.stderr, leave=False) as bar:
        def progress(done, total):
            bar.total = total
            bar.update(done - bar.n)

        frames = render_clip(character, args.clip, gif=args.gif, mp4=args.mp4, sheet=args.sheet, fps=args.fps,
                             width=args.size[0], height=args.size[1], azimuth=args.azimuth,
                             elevation=args.elevation, backend=args.backend, bones=args.bones,
                             progress=progress)
    print(f"{', '.join(map(str, outputs))}: {len(frames)} frames of {args.size[0]}x{args.size[1]}")
    return 0


def _add_preview(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, or a .gltf with embedded buffers)")
    parser.add_argument("--out", type=Path, help="the viewer folder (default: <name>_preview beside the file)")
    parser.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: a free one)")
    parser.add_argument("--no-serve", action="store_true", help="only write the viewer folder")


def _run_preview(args) -> int:
    import threading

    from .preview.viewer import serve, write_viewer

    out = args.out or args.file.with_name(args.file.stem + "_preview")
    index = write_viewer(args.file, out)
    if args.no_serve:
        print(f"{index}: open it through a web server (ES modules do not load from file://)")
        return 0
    server, url = serve(out, port=args.port)
    print(f"rigmix preview: {url} (serving {out}; Ctrl+C to stop)", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
    return 0


#: The sub-commands, in the order ``rigmix --help`` lists them. Append here.
def _add_compose(parser):
    parser.add_argument("config", type=Path, help="a composition config (.toml)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the composed character (.glb or .gltf)")
    parser.add_argument("--report", type=Path, help="write the JSON report (timings, mesh, fields, weights, "
                                                    "quality, animation, scales, warnings)")
    parser.add_argument("--usd", type=Path, help="also write the character as USD (.usda, .usdc, .usd, .usdz)")
    parser.add_argument("--dump-fields", type=Path, metavar="DIR",
                        help="write the blended signed distance fields (.vdb with OpenVDB, else .npz) to DIR")
    parser.add_argument("--weights", choices=("nearest", "inpaint", "dfd"),
                        help="junction weight method (default: the config's [weights] method, else dfd)")
    parser.add_argument("--no-feature-field", action="store_true",
                        help="dfd without the distilled DFD feature field of the fused surface (saves a few "
                             "seconds; same as [weights] feature_field = false)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_compose(args) -> int:
    import tempfile

    from tqdm import tqdm

    from .config import load_config
    from .errors import InputError
    from .io.gltf import write_gltf
    from .pipeline import STAGE_NAMES, compose
    from .safety import atomic_output, atomic_write_text

    if args.output.suffix.lower() not in (".glb", ".gltf"):
        raise InputError(f"compose: output {args.output} must end in .glb or .gltf")
    if args.usd is not None and args.usd.suffix.lower() not in (".usda", ".usdc", ".usd", ".usdz"):
        raise InputError(f"compose: --usd {args.usd} must end in .usda, .usdc, .usd or .usdz")
    for p in (args.output, args.report, args.usd):
        if p is not None and not p.parent.is_dir():
            raise InputError(f"compose: the folder of {p} does not exist")
    config = load_config(args.config)
    weights, fusion = {}, {}
    if args.weights:
        weights["method"] = args.weights
    if args.no_feature_field:
        weights["feature_field"] = False
    if args.dump_fields:
        fusion["keep_fields"] = True
    config = config.with_options(weights=weights, fusion=fusion)
    with tqdm(total=len(STAGE_NAMES), desc="compose", unit="stage", disable=args.no_progress, file=sys.stderr,
              leave=False) as bar:
        def progress(stage, done, total):
            if isinstance(done, int) and stage in STAGE_NAMES:
                bar.total = total
                bar.set_postfix_str(stage)
                bar.update(done - bar.n)

        comp = compose(config, progress=progress)
    # every output is written to a temporary file first; nothing is renamed until all succeeded
    with tempfile.TemporaryDirectory(dir=args.output.parent, prefix=".rigmix-compose-") as tmp:
        tmp = Path(tmp)
        staged = tmp / ("character" + args.output.suffix.lower())
        write_gltf(comp.character, staged)
        usd_dir = None
        if args.usd is not None:
            from .io.usd import write_usd

            usd_dir = tmp / "usd"
            usd_dir.mkdir()
            write_usd(comp.character, usd_dir / args.usd.name)
        fields_written = []
        if args.dump_fields:
            from .fusion import dump_fields

            fdir = tmp / "fields"
            fdir.mkdir()
            fields_written = dump_fields(fdir, comp.surface.fields) or []
            if not fields_written:
                print(f"rigmix compose: --dump-fields {args.dump_fields}: no junction field was computed (every "
                      "junction was copied from faces the inputs share); nothing written", file=sys.stderr)
        report = dict(comp.report)
        report["output"] = str(args.output)
        text = json.dumps(report, indent=2, default=_json_default)
        # commit: the character, then the USD (and its textures), the fields, the report
        with atomic_output(args.output) as out:
            out.write_bytes(staged.read_bytes())
        if usd_dir is not None:
            for f in sorted(usd_dir.rglob("*")):
                if f.is_file():
                    dest = args.usd.parent / f.relative_to(usd_dir)
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    with atomic_output(dest, suffix=dest.suffix) as out:
                        out.write_bytes(f.read_bytes())
        if args.dump_fields:
            args.dump_fields.mkdir(parents=True, exist_ok=True)
            for f in sorted((tmp / "fields").iterdir()):
                with atomic_output(args.dump_fields / f.name, suffix=f.suffix) as out:
                    out.write_bytes(f.read_bytes())
        if args.report is not None:
            atomic_write_text(args.report, text + "\n")
    w, m, q = comp.report.get("weights", {}), comp.report.get("mesh", {}), comp.report.get("quality", {})
    print(f"{args.output}: {comp.skeleton.num_joints} joints, {m.get('vertices')} vertices, {m.get('faces')} faces, "
          f"{len(comp.character.clips)} clips; weights {w.get('method')}; junction stretch ratio "
          f"{q.get('junction_stretch_ratio')}; {comp.report['timings']['total']:.1f} s")
    return 0


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def _add_batch(parser):
    parser.add_argument("configs", type=Path, nargs="+", metavar="CONFIG", help="composition configs (.toml)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder: <config name>.glb, <config name>.report.json, manifest.jsonl")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes (default: the CPU count; 0: in this process; with "
                             "--scheduler local-dask: Dask workers, default 2)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on a Dask cluster: a scheduler address (tcp://host:8786) or 'local-dask' "
                             "(needs rigmix[dask]; the output folder must be shared with the workers)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_batch(args) -> int:
    from tqdm import tqdm

    from .batch import run_batch

    if args.workers is not None and args.workers < 0:
        from .errors import InputError

        raise InputError(f"batch: --workers must be 0 or more, got {args.workers}")
    with tqdm(total=len(args.configs), desc="batch", unit="config", disable=args.no_progress,
              file=sys.stderr) as bar:
        def progress(done, total, entry):
            bar.set_postfix_str(f"{entry['stem']} {'skipped' if entry.get('skipped') else entry['status']}")
            bar.update(done - bar.n)

        entries = run_batch(args.configs, args.out, workers=args.workers, scheduler=args.scheduler,
                            progress=progress)
    failed = [e for e in entries if e["status"] != "ok"]
    skipped = sum(bool(e.get("skipped")) for e in entries)
    for e in failed:
        _error(f"{Path(e['config']).name}: {e['error']}")
    print(f"{args.out}: {len(entries) - len(failed) - skipped} composed, {skipped} skipped (done before), "
          f"{len(failed)} failed; manifest {args.out / 'manifest.jsonl'}")
    return 1 if failed else 0


COMMANDS: list[Command] = [
    Command("inspect", "print a character's joints, meshes, clips, counts and repaired defects",
            _add_inspect, _run_inspect),
    Command("convert", "convert a character file: glTF/GLB <-> USD (.usda, .usdc, .usd, .usdz)",
            _add_convert, _run_convert),
    Command("render", "render a clip offscreen on the CPU to a GIF, an MP4 or a contact sheet PNG",
            _add_render, _run_render),
    Command("preview", "write a web viewer for a .glb (clips, timeline, skeleton) and serve it on 127.0.0.1",
            _add_preview, _run_preview),
    Command("map", "print the bone-to-bone mapping of a composition config (input joint -> output "
                   "joint, confidence)", _add_map, _run_map),
    Command("schema", "print the JSON schema of composition configs", _add_schema, _run_schema),
    Command("compose", "compose a new character from a config: GLB (and USD), JSON report", _add_compose,
            _run_compose),
    Command("batch", "compose many configs in parallel (process pool or Dask), resumable, with a JSONL manifest",
            _add_batch, _run_batch),
]


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The ``rigmix`` parser with one sub-parser per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="rigmix",
        description="Compose new rigged, skinned and animated characters from pieces of existing ones.",
    )
    parser.add_argument("--version", action="version", version=f"rigmix {__version__}")
    # the common options are accepted before or after the command name; in the sub-parsers
    # they default to SUPPRESS so that they never overwrite a value given before the command
    _add_common_options(parser, default=True)
    parser.set_defaults(command=None)
    common = argparse.ArgumentParser(add_help=False)
    _add_common_options(common, default=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for cmd in COMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help, parents=[common])
        cmd.add_arguments(p)
        p.set_defaults(run=cmd.run)
    return parser


def _add_common_options(parser, *, default: bool) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=0 if default else argparse.SUPPRESS,
                        help="log info (-v) or debug (-vv) messages on stderr")
    parser.add_argument("--debug", action="store_true", default=False if default else argparse.SUPPRESS,
                        help="show the full traceback of an error")


class _OneLine(logging.Formatter):
    def format(self, record):
        return " ".join(super().format(record).split("\n"))


def _configure_logging(verbosity: int) -> None:
    """Warnings (or info/debug with -v/-vv) of rigmix and dfd on stderr, one line each."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLine("rigmix: %(levelname)s: %(message)s"))
    handler._rigmix_cli = True
    for name in ("rigmix", "dfd"):
        log = logging.getLogger(name)
        for h in [h for h in log.handlers if getattr(h, "_rigmix_cli", False)]:
            log.removeHandler(h)  # calling main() twice in one process must not double lines
        log.addHandler(handler)
        log.setLevel(level)
        log.propagate = False
    logging.captureWarnings(True)


def _error(message: str) -> None:
    print("rigmix: error: " + " ".join(str(message).split()), file=sys.stderr)


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 user error, 1 internal error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    _configure_logging(args.verbose)
    try:
        return int(args.run(args) or 0)
    except RigmixError as exc:
        if args.debug:
            raise
        _error(str(exc))
        return 2
    except BrokenPipeError:  # e.g. `rigmix inspect X | head`: stop quietly
        sys.stdout = open(os.devnull, "w")
        return 0
    except OSError as exc:
        if args.debug:
            raise
        _error(f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc))
        return 2
    except KeyboardInterrupt:
        _error("interrupted")
        return 130
    except Exception as exc:  # a bug: still one line, the traceback with --debug
        if args.debug:
            raise
        _error(f"internal error ({type(exc).__name__}: {exc}); run again with --debug for the traceback")
        return 1


if __name__ == "__main__":
    sys.exit(main())
