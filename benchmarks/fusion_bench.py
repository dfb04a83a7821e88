"""Fusion benchmark: time per composition and voxel count (issue: mesh fusion).

Cases: the example configs (built-in characters, through the pipeline up to the mapping, then
the fusion stage), a centaur of two shared characters (Horse body, Knight rider) and limb
self-compositions of the shared characters, whose ground truth is the character itself
(Hausdorff distance relative to the bounding-box diagonal, share of faces preserved).

Writes ``benchmarks/results/fusion.json`` and ``fusion.md``. Run: ``python -m benchmarks.fusion_bench``.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from conftest import ASSETS, CHARACTERS  # noqa: E402

EXAMPLES = ["centaur", "self_arm", "beast_arms", "tailed_humanoid"]


def _self_cases():
    """Every limb of every shared character (the self-composition benchmark's list):
    ``[(file relative to ASSETS, [limb root joints])]``."""
    from benchmarks.self_composition import LIMBS

    return [(CHARACTERS[ch], list(limbs.values())) for ch, limbs in LIMBS.items()]


REAL_CENTAUR = f"""
name = "horse_knight_centaur"
[characters.body]
path = "{ASSETS / CHARACTERS['Horse']}"
[characters.rider]
path = "{ASSETS / CHARACTERS['Knight']}"
[[actions]]
op = "replace"
source = "rider"
source_joint = "Abdomen"
target = "body"
target_joint = "Neck1"
mode = "blend"
"""


def _row(name, rep, seconds, extra=None):
    m, f = rep["mesh"], rep["fields"]
    row = {
        "case": name,
        "fusion_s": round(seconds, 3),
        "voxels": f["voxels"],
        "voxel_size": f["voxel_size"],
        "junction_faces": m["junction_faces"],
        "junction_boundary_edges": m["junction_boundary_edges"],
        "new_non_manifold_edges": m["new_non_manifold_edges"],
        "junction_min_angle_p05": (
            None if m["junction_min_angle_p05"] is None else round(m["junction_min_angle_p05"], 2)
        ),
        "junction_self_intersections": m.get("junction_self_intersections"),
        "stages": rep["timings"],
    }
    row.update(extra or {})
    return row


def _compose_case(cfg):
    from rigmix.pipeline import compose, fusion_stage

    comp = compose(cfg, until="mapping")
    t0 = time.perf_counter()
    comp = fusion_stage(comp)
    return comp.surface.report, time.perf_counter() - t0


def _self_case(c, joint):
    """One limb replaced by itself, fused twice: with the junction rebuilt from the fields
    (``copy_coincident=False``, as between two different characters: the row's timing, grid
    and junction figures) and by default (the shared junction faces copied)."""
    import igl

    from rigmix.fusion import FusionAction, FusionParams, fuse_surfaces
    from rigmix.fusion.inputs import fusion_input
    from rigmix.fusion.presence import compute_presence
    from rigmix.geometry import bounding_box_diagonal

    sub = c.skeleton.subtree(c.skeleton.index(joint))
    a, b = fusion_input(c, ~sub), fusion_input(c, sub)
    diag = bounding_box_diagonal(a.V)

    def against_original(out):
        h_out = np.sqrt(igl.point_mesh_squared_distance(out.V, a.V, a.F)[0]).max() / diag
        h_in = np.sqrt(igl.point_mesh_squared_distance(a.V, out.V, out.F)[0]).max() / diag
        return round(100 * max(h_out, h_in), 3), round(float((out.face_origin_input >= 0).sum() / len(a.F)), 3)

    t0 = time.perf_counter()
    out = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)], params=FusionParams(copy_coincident=False))
    dt = time.perf_counter() - t0
    h, kept = against_original(out)
    t0 = time.perf_counter()
    copied = fuse_surfaces([a, b], [FusionAction("replace", 0, 1)])
    dt_c = time.perf_counter() - t0
    h_c, kept_c = against_original(copied)
    # what the paper's rule allows at most: faces of presence 1 before any seam clean-up
    bound = float(sum(np.count_nonzero(compute_presence(x.V, x.F, x.W, x.used).preserved) for x in (a, b)) / len(a.F))
    return out.report, dt, {"hausdorff_pct": h, "faces_preserved": kept, "presence_one": round(bound, 3),
                            "default_s": round(dt_c, 3), "default_hausdorff_pct": h_c,
                            "default_faces_preserved": kept_c,
                            "default_copied_faces": copied.report["mesh"]["copied_faces"]}


def main():
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in EXAMPLES:
        rep, dt = _compose_case(ROOT / "examples" / f"{name}.toml")
        rows.append(_row(f"example {name}", rep, dt))
    if (ASSETS / CHARACTERS["Horse"]).exists():
        with tempfile.TemporaryDirectory() as d:
            cfg = Path(d) / "centaur.toml"
            cfg.write_text(REAL_CENTAUR)
            rep, dt = _compose_case(cfg)
            rows.append(_row("Horse + Knight centaur", rep, dt))
        from rigmix.io import load_character

        for path, joints in _self_cases():
            character = load_character(ASSETS / path)
            for joint in joints:
                rep, dt, extra = _self_case(character, joint)
                rows.append(_row(f"self {Path(path).stem}:{joint}", rep, dt, extra))
    (RESULTS / "fusion.json").write_text(json.dumps({"cpu_count": os.cpu_count(), "cases": rows}, indent=2) + "\n")
    lines = [
        "Fusion time (s, fuse_surfaces only) and grid size per case. Self-compositions (a limb replaced by "
        "itself) are fused with the junction rebuilt from the fields (`copy_coincident=False`, as between two "
        "different characters: time, grid, junction, Hausdorff distance to the original in % of the bounding-box "
        "diagonal, share of faces preserved, share of faces whose presence is 1 by the paper's rule: the most "
        "that can be preserved) and by default (`default`: the junction faces both inputs share are copied).",
        "",
        "| case | fusion s | voxels | voxel | junction faces | gap edges | new non-manifold | min angle p05 "
        "| crossing pairs | Hausdorff % | preserved | presence 1 | default s | default Hausdorff % "
        "| default preserved |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['fusion_s']} | {r['voxels']} | {r['voxel_size']:.4g} | {r['junction_faces']} | "
            f"{r['junction_boundary_edges']} | {r['new_non_manifold_edges']} | {r['junction_min_angle_p05']} | "
            f"{r['junction_self_intersections']} | {r.get('hausdorff_pct', '')} | "
            f"{r.get('faces_preserved', '')} | {r.get('presence_one', '')} | "
            f"{r.get('default_s', '')} | {r.get('default_hausdorff_pct', '')} | "
            f"{r.get('default_faces_preserved', '')} |"
        )
    selfs = [r for r in rows if "default_hausdorff_pct" in r]
    if selfs:
        def count(key_h, key_p):
            return sum(r[key_h] <= 0.5 and r[key_p] >= 0.9 for r in selfs)

        by_default = count("default_hausdorff_pct", "default_faces_preserved")
        rebuilt = count("hausdorff_pct", "faces_preserved")
        lines += ["", "Self-compositions within 0.5% with at least 90% of the faces preserved: "
                  f"{by_default}/{len(selfs)} by default, {rebuilt}/{len(selfs)} with the junction rebuilt."]
    (RESULTS / "fusion.md").write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
