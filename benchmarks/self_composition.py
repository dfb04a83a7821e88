"""Self-composition benchmark (issue 6): replace a limb by itself and measure W_R against the truth.

For each shared character and each limb subtree (arms, legs, tail, head where present), the
character is composed with itself (two config ids, one file): the subtree at the limb's root
joint of the donor replaces the same subtree of the body. The fusion runs once per case; each
junction weight method (``nearest``, ``inpaint``, ``dfd``) then fills W_R, and we report:

* junction weight error: L1 over output joints between W_R and the original weights at the
  closest original point cut to their 4 largest (what a 4-influence output can hold; the
  figures against the full interpolation are in the JSON as ``full_truth``), mean and max over
  junction vertices;
* skinned-vertex error: over every frame (30 fps) of every clip of the character, the distance
  between the vertex skinned with W_R and with the true weights, relative to the bounding-box
  diagonal (max and mean);
* junction stretch ratio (:func:`rigmix.quality.junction_stretch_ratio`; the completed clips of a
  self-composition are the character's own).

Writes ``benchmarks/results/self_composition.json`` and ``self_composition.md``.
Usage: ``python -m benchmarks.self_composition [CHARACTER ...]``.
"""

from __future__ import annotations

import json
import logging
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from rigmix.config import Config  # noqa: E402
from rigmix.pipeline import assembly_stage, compose, quality_stage  # noqa: E402
from rigmix.quality import self_composition_errors  # noqa: E402
from rigmix.skin_weights import WEIGHT_METHODS, blend_weights  # noqa: E402

#: Limb roots per shared character (SimpleSkin has no limb; the Wasp's body is 13 parts).
LIMBS = {
    "CesiumMan": {"arm.L": "Skeleton_arm_joint_L__4_", "arm.R": "Skeleton_arm_joint_R",
                  "leg.L": "leg_joint_L_1", "leg.R": "leg_joint_R_1", "head": "Skeleton_neck_joint_1"},
    "RiggedFigure": {"arm.L": "arm_joint_L_1", "arm.R": "arm_joint_R_1", "leg.L": "leg_joint_L_1",
                     "leg.R": "leg_joint_R_1", "head": "neck_joint_1"},
    "Knight": {"arm.L": "UpperArm.L", "arm.R": "UpperArm.R", "leg.L": "UpperLeg.L", "leg.R": "UpperLeg.R",
               "head": "Neck"},
    "Fox": {"arm.L": "b_LeftUpperArm_09", "arm.R": "b_RightUpperArm_06", "leg.L": "b_LeftLeg01_015",
            "leg.R": "b_RightLeg01_019", "tail": "b_Tail01_012", "head": "b_Neck_04"},
    "Horse": {"leg.FL": "FrontUpperLeg.L", "leg.FR": "FrontUpperLeg.R", "leg.BL": "BackUpperLeg.L",
              "leg.BR": "BackUpperLeg.R", "tail": "Tail1", "head": "Neck1"},
    "Velociraptor": {"arm.L": "FrontUpLeg.L", "arm.R": "FrontUpLeg.R", "leg.L": "BackUpLeg.L",
                     "leg.R": "BackUpLeg.R", "tail": "Tail1", "head": "Neck"},
    "Wasp": {"leg.L": "MidLeg1.L", "leg.R": "MidLeg1.R", "head": "Head", "tail": "Abdomen"},
}


def self_config(path: Path, joint: str) -> Config:
    """The config replacing ``joint``'s subtree of a character with the same subtree of itself."""
    return Config.model_validate({
        "name": f"self_{path.stem}_{joint}",
        "characters": {"body": {"path": str(path)}, "donor": {"path": str(path)}},
        "actions": [{"op": "replace", "source": "donor", "source_joint": joint, "target": "body",
                     "target_joint": joint, "mode": "blend"}],
    })


def run_case(path: Path, joint: str, *, methods=WEIGHT_METHODS, max_frames=None) -> dict:
    """Fuse once, fill W_R with every method, measure. Returns ``{method: figures}`` + fusion info."""
    t0 = time.perf_counter()
    comp = compose(self_config(path, joint), until="completion")
    t_fuse = time.perf_counter() - t0
    ids = comp.stages["fusion_ids"]
    out = {"fusion_s": round(t_fuse, 2), "junction_vertices": int((comp.stages["surface"].origin_input < 0).sum()),
           "mesh": {k: comp.report["mesh"].get(k) for k in ("vertices", "junction_faces", "junction_boundary_edges",
                                                            "junction_min_angle_p05")},
           "methods": {}}
    for method in methods:
        t1 = time.perf_counter()
        skin = blend_weights(comp.stages["surface"], comp.stages["fusion_inputs"], [comp.maps[c] for c in ids],
                             comp.skeleton.num_joints, method=method)
        t_w = time.perf_counter() - t1
        figures = self_composition_errors(comp, skin, max_frames=max_frames)
        full = self_composition_errors(comp, skin, max_frames=max_frames, truth_influences=None)
        figures["full_truth"] = {k: full[k] for k in ("junction_weight_error_mean", "junction_weight_error_max",
                                                      "skinned_error_max")}
        c2 = replace(comp, stages={**comp.stages, "weights": skin})
        c2 = quality_stage(assembly_stage(c2))
        figures["junction_stretch_ratio"] = c2.report["quality"]["junction_stretch_ratio"]
        figures["weights_s"] = round(t_w, 3)
        figures["max_influences"] = skin.report["max_influences"]
        out["methods"][method] = figures
    return out


#: Address-space cap of the child process of one case (a runaway native allocation fails the case).
MEMORY_CAP = 10 * 2**30


def _cap_memory():
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


def run_isolated(path: Path, joint: str) -> dict:
    """:func:`run_case` in a child process: a native abort fails this case only."""
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=1, initializer=_cap_memory) as pool:
        return pool.submit(run_case, path, joint).result()


def _fmt(x, spec):
    return "-" if x is None else format(x, spec)


def main(argv=None) -> int:
    """Run every case (or the characters named on the command line) and write the results."""
    from conftest import ASSETS, CHARACTERS

    logging.basicConfig(level=logging.ERROR)
    names = list(argv if argv is not None else sys.argv[1:]) or list(LIMBS)
    rows, t_all = [], time.perf_counter()
    for name in names:
        path = ASSETS / CHARACTERS[name]
        if not path.exists():
            print(f"self_composition: missing {path}; skipped", file=sys.stderr)
            continue
        for limb, joint in LIMBS[name].items():
            try:
                res = run_isolated(path, joint)
            except Exception as e:  # a benchmark reports a failing case and goes on
                rows.append({"character": name, "limb": limb, "joint": joint, "error": f"{type(e).__name__}: {e}"})
                print(f"{name} {limb}: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
                continue
            rows.append({"character": name, "limb": limb, "joint": joint, **res})
            m = res["methods"]
            print(f"{name} {limb}: " + "  ".join(
                f"{k} {v['junction_weight_error_mean']:.3f}/{v['skinned_error_max'] * 100:.3f}%" for k, v in m.items()),
                flush=True)
    ok = [r for r in rows if "methods" in r]
    summary = {}
    for method in WEIGHT_METHODS:
        vals = [r["methods"][method] for r in ok if method in r["methods"]]
        if vals:
            ratios = [v["junction_stretch_ratio"] for v in vals if v["junction_stretch_ratio"] is not None]
            summary[method] = {
                "junction_weight_error_mean": float(np.mean([v["junction_weight_error_mean"] for v in vals])),
                "junction_weight_error_max": float(np.max([v["junction_weight_error_max"] for v in vals])),
                "skinned_error_max": float(np.max([v["skinned_error_max"] for v in vals])),
                "junction_stretch_ratio_median": float(np.median(ratios)) if ratios else None,
            }
    dfd_wins = sum(1 for r in ok if r["methods"]["dfd"]["junction_weight_error_mean"]
                   < r["methods"]["nearest"]["junction_weight_error_mean"])
    dfd_not_worse = sum(1 for r in ok if r["methods"]["dfd"]["junction_weight_error_mean"]
                        <= r["methods"]["inpaint"]["junction_weight_error_mean"] + 1e-9)
    under = sum(1 for r in ok if r["methods"]["dfd"]["skinned_error_max"] < 0.005)
    result = {"cases": rows, "summary": summary,
              "acceptance": {"cases": len(ok), "dfd_lower_than_nearest": dfd_wins,
                             "dfd_not_worse_than_inpaint": dfd_not_worse, "dfd_skinned_under_0.5%": under},
              "seconds": round(time.perf_counter() - t_all, 1), "machine": platform.platform(),
              "python": platform.python_version()}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "self_composition.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = ["# Self-composition: junction weights against the original (issue 6)", "",
             "Weight error: L1 over output joints at junction vertices (mean / max) against the original weights at the "
             "closest original point cut to 4 influences (JSON `full_truth`: uncut). Skinned error: max over all "
             "vertices, frames (30 fps) and clips, % of the bounding-box diagonal. Stretch: junction stretch ratio.", "",
             "| character | limb | junction verts | " + " | ".join(
                 f"{m} err mean / max | {m} skinned max % | {m} stretch" for m in WEIGHT_METHODS) + " |",
             "|---|---|---:|" + "---:|---:|---:|" * len(WEIGHT_METHODS)]
    for r in rows:
        if "methods" not in r:
            lines.append(f"| {r['character']} | {r['limb']} | failed: {r['error'][:80]} |")
            continue
        cells = []
        for m in WEIGHT_METHODS:
            v = r["methods"][m]
            cells += [f"{v['junction_weight_error_mean']:.3f} / {v['junction_weight_error_max']:.3f}",
                      f"{v['skinned_error_max'] * 100:.3f}", _fmt(v["junction_stretch_ratio"], ".2f")]
        lines.append(f"| {r['character']} | {r['limb']} | {r['junction_vertices']} | " + " | ".join(cells) + " |")
    lines += ["", f"dfd mean error lower than nearest in {dfd_wins}/{len(ok)} cases, not worse than inpaint in "
              f"{dfd_not_worse}/{len(ok)}; dfd skinned error under 0.5% of the diagonal in {under}/{len(ok)}.",
              "", "Summary: " + json.dumps(summary), "", f"{result['seconds']} s on {result['machine']}."]
    (RESULTS / "self_composition.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
