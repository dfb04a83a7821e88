"""End-to-end composition benchmark (issue 8): per-stage times and fusion scaling.

1. Per-stage times of :func:`rigmix.compose` for every composition config (``tests/configs``
   on the shared characters and ``examples`` on the built-in ones), with the fused mesh size and
   voxel count. The SkinMixer paper reports 12 s on average per composition.
2. Scaling of fusion time with mesh resolution: CesiumMan midpoint-subdivided 1, 2 and 4 times
   (18,688 / 74,752 / 1,196,032 faces: the 10k, 100k and 1M orders of magnitude), its left arm
   replaced by itself. Each case runs in a child process (its peak memory is reported) with a
   time limit, so a case that runs away is recorded rather than stopping the benchmark.
3. The reference operation of issue 26 (:func:`benchmarks.common.reference_operation`: libigl's
   fast winding number of 1M points against the Horse subdivided to 78,552 faces), timed before
   the configs and again after the scaling cases; every timing is also given as a multiple of
   the median of both (``x ref``), so runs on idle and loaded machines compare. The per-stage
   medians over the configs are given in seconds and in multiples.
4. Issue 26's timed corpus case (:data:`ACCEPTANCE`), after the configs and outside their medians.

Writes ``benchmarks/results/compose_bench.json`` and ``compose_bench.md``.
Usage: ``python -m benchmarks.compose_bench``.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.common import git_commit, ratio, reference_operation

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
CONFIGS = sorted((ROOT / "tests" / "configs").glob("*.toml")) + sorted((ROOT / "examples").glob("*.toml"))
SUBDIVISIONS = (1, 2, 4)
STAGES = ("load", "operations", "mapping", "fusion", "weights", "completion", "assembly", "quality", "total")
CASE_TIMEOUT = 900.0  # seconds per scaling case
#: Issue 26's timed case on the corpus (``benchmarks.corpus_matrix``): a humanoid upper body
#: replacing the Wasp's head (six legs; its neck joint also carries the wings and the abdomen,
#: which stay). Timed after the configs, not in their medians; skipped without the corpus.
ACCEPTANCE = ("torso__Wasp__PlatformerCharacter",)


def subdivide_mesh(mesh, num_joints):
    """One midpoint subdivision (each triangle into 4) of a :class:`rigmix.Mesh`.

    Edge midpoints average every vertex attribute (normals renormalized, weights re-cut to the 4
    largest), so the subdivided character deforms like the original.
    """
    from rigmix.weights import sparsify

    F = mesh.faces
    n = len(mesh.positions)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + n  # (m, 3) midpoint index of edges (01, 12, 20)

    def mid(a):
        return None if a is None else np.concatenate([a, 0.5 * (a[uniq[:, 0]] + a[uniq[:, 1]])])

    a, b, c = F.T
    ab, bc, ca = inv.T
    faces = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    normals = mid(mesh.normals)
    if normals is not None:
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    joints = weights = None
    if mesh.skinned:
        W = sparsify(mid(mesh.dense_weights(num_joints)), 4)
        order = np.argsort(-W, axis=1, kind="stable")[:, :4]
        joints = order
        weights = np.take_along_axis(W, order, axis=1)
    return replace(mesh, positions=mid(mesh.positions), faces=faces, normals=normals,
                   uvs=tuple(mid(u) for u in mesh.uvs), colors=mid(mesh.colors), joints=joints, weights=weights)


def subdivided_character(character, levels):
    """``character`` with every mesh subdivided ``levels`` times."""
    meshes = character.meshes
    for _ in range(levels):
        meshes = tuple(subdivide_mesh(m, character.skeleton.num_joints) for m in meshes)
    return replace(character, meshes=meshes)


def _compose_report(config_path):
    from rigmix.pipeline import compose

    t0 = time.perf_counter()
    comp = compose(config_path)
    wall = time.perf_counter() - t0
    r = comp.report
    in_root = str(config_path).startswith(str(ROOT))
    return {"config": str(Path(config_path).relative_to(ROOT)) if in_root else str(config_path),
            "wall_s": round(wall, 3), "timings": r.get("timings", {}),
            "vertices": r.get("mesh", {}).get("vertices"), "faces": r.get("mesh", {}).get("faces"),
            "junction_faces": r.get("mesh", {}).get("junction_faces"),
            "voxels": r.get("fields", {}).get("voxels"),
            "junction_min_angle_p05": r.get("mesh", {}).get("junction_min_angle_p05"),
            "junction_self_intersections": r.get("mesh", {}).get("junction_self_intersections"),
            "junction_stretch_ratio": r.get("quality", {}).get("junction_stretch_ratio"),
            "junction_weight_roughness_max": r.get("quality", {}).get("junction_weight_roughness_max"),
            "source_weight_roughness_max": r.get("quality", {}).get("source_weight_roughness_max")}


def run_acceptance(folder):
    """Rows as for the configs, for the :data:`ACCEPTANCE` cases (``config``: the case name)."""
    from benchmarks.corpus_matrix import generate_matrix, load_subjects, write_configs

    rows = []
    try:
        matrix = [c for c in generate_matrix(load_subjects()) if c.name in ACCEPTANCE]
    except Exception as exc:  # no corpus beside the checkout
        return [{"config": name, "error": f"{type(exc).__name__}: {exc}"} for name in ACCEPTANCE]
    for name, path in write_configs(matrix, Path(folder)).items():
        try:
            rows.append({**_compose_report(path), "config": name})
        except Exception as exc:
            rows.append({"config": name, "error": f"{type(exc).__name__}: {exc}"})
    return rows


def _scaling_case(levels, queue):
    """Child process: subdivide CesiumMan, self-compose its left arm (junction rebuilt from the
    fields), report times and memory."""
    try:
        sys.path.insert(0, str(ROOT / "tests"))
        from conftest import ASSETS, CHARACTERS

        from rigmix.config import Config
        from rigmix.io.gltf import read_gltf, write_gltf

        character = subdivided_character(read_gltf(ASSETS / CHARACTERS["CesiumMan"]), levels)
        faces = int(sum(len(m.faces) for m in character.meshes))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "CesiumMan_sub.glb"
            write_gltf(character, path)
            joint = "Skeleton_arm_joint_L__4_"
            config = Config.model_validate({
                "name": f"cesiumman_sub{levels}",
                "characters": {"body": {"path": str(path)}, "donor": {"path": str(path)}},
                "actions": [{"op": "replace", "source": "donor", "source_joint": joint,
                             "target": "body", "target_joint": joint}],
                # the junction rebuilt from the fields: copied (the default here) it costs nothing
                "fusion": {"copy_coincident": False},
            })
            row = _compose_report(config)
        row.update(config=f"CesiumMan x{4 ** levels} (arm self-composition, junction rebuilt)",
                   input_faces=faces,
                   subdivisions=levels,
                   peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1))
        queue.put(row)
    except Exception as exc:  # reported in the table, the other cases still run
        queue.put({"subdivisions": levels, "error": f"{type(exc).__name__}: {exc}"})


def run_scaling():
    rows = []
    ctx = mp.get_context("spawn")
    for levels in SUBDIVISIONS:
        q = ctx.Queue()
        p = ctx.Process(target=_scaling_case, args=(levels, q))
        t0 = time.perf_counter()
        p.start()
        p.join(CASE_TIMEOUT)
        if p.is_alive():
            p.kill()
            p.join()
            rows.append({"subdivisions": levels, "error": f"timed out after {CASE_TIMEOUT:.0f} s"})
            continue
        try:
            rows.append(q.get(timeout=5))
        except Exception:
            rows.append({"subdivisions": levels, "error": f"child exited with code {p.exitcode} "
                                                        f"after {time.perf_counter() - t0:.1f} s"})
    return rows


def combine_references(first: dict, last: dict) -> dict:
    """One reference from the timings before and after the benchmark: ``seconds`` the median of
    every call, ``before`` and ``after`` each time's median and load average."""
    runs = first["runs"] + last["runs"]
    return {**first, "seconds": round(float(np.median(runs)), 4), "runs": runs,
            "before": {"seconds": first["seconds"], "load_average": first["load_average"], "date": first["date"]},
            "after": {"seconds": last["seconds"], "load_average": last["load_average"], "date": last["date"]}}


def stage_medians(configs) -> dict:
    """Stage -> median seconds over the configs that composed."""
    ok = [r["timings"] for r in configs if "error" not in r]
    return {s: round(float(np.median([t[s] for t in ok if s in t])), 4) for s in STAGES if any(s in t for t in ok)}


def _markdown(configs, scaling, reference, acceptance=()):
    stages = list(STAGES)
    ref = reference["seconds"]
    medians = stage_medians(configs)
    lines = [f"Reference operation (issue 26): {reference['operation']}: **{ref:.2f} s** (median of "
             f"{len(reference['runs'])} calls, {reference['before']['seconds']:.2f} s before the configs at load "
             f"average {reference['before']['load_average'][0]:g}, {reference['after']['seconds']:.2f} s after the "
             f"scaling cases at {reference['after']['load_average'][0]:g}); commit {reference['commit']}, "
             f"{reference['machine']}, {reference['cpus']} CPUs, {reference['date']}. `x ref`: a time divided by "
             "it, comparable between idle and loaded machines.", "",
             "Median per stage over the configs (seconds, and x ref):", "",
             "| | " + " | ".join(medians) + " |", "|---|" + "---:|" * len(medians),
             "| median s | " + " | ".join(f"{v:.2f}" for v in medians.values()) + " |",
             "| median x ref | " + " | ".join(f"{ratio(v, ref):.3f}" for v in medians.values()) + " |", "",
             "Per-stage times of `rigmix.compose` (seconds; the SkinMixer paper reports 12 s on average "
             "per composition), then the total as x ref.", "",
             "| config | " + " | ".join(stages) + " | total x ref | faces | voxels | min angle p05 | crossing pairs "
             "| stretch ratio | weight roughness max, junction / sources |",
             "|---|" + "---:|" * (len(stages) + 7)]
    for r in list(configs) + [{**a, "config": f"{a['config']} (corpus, not in the medians)"} for a in acceptance]:
        if "error" in r:
            lines.append(f"| {r['config']} | error: {r['error']} |")
            continue
        t = r["timings"]
        cells = [f"{t[s]:.2f}" if s in t else "" for s in stages]
        ang = r["junction_min_angle_p05"]
        sr = r["junction_stretch_ratio"]
        rough = " / ".join("-" if r.get(k) is None else f"{r[k]:.2f}"
                           for k in ("junction_weight_roughness_max", "source_weight_roughness_max"))
        tr = ratio(t.get("total"), ref)
        lines.append(f"| {r['config']} | " + " | ".join(cells) + f" | {'' if tr is None else f'{tr:.3f}'}" +
                     f" | {r['faces']} | {r['voxels']} | {'' if ang is None else f'{ang:.1f}'} | "
                     f"{r.get('junction_self_intersections', '')} | {'' if sr is None else f'{sr:.2f}'} | {rough} |")
    lines += ["", "Fusion time against mesh resolution (CesiumMan subdivided, left arm replaced by itself, "
              "junction rebuilt from the fields):", "",
              "| input faces | fusion s | fusion x ref | total s | total x ref | output faces | voxels | peak RSS MB |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in scaling:
        if "error" in r:
            lines.append(f"| x{4 ** r['subdivisions']} | error: {r['error']} | | | | | | |")
            continue
        fusion, total = r["timings"].get("fusion"), r["timings"].get("total")
        lines.append(f"| {r['input_faces']} | {fusion:.2f} | {ratio(fusion, ref):.3f} | {total:.2f} | "
                     f"{ratio(total, ref):.3f} | {r['faces']} | {r['voxels']} | {r['peak_rss_mb']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    os.environ.setdefault("CI", "false")
    first = reference_operation()
    print(json.dumps({"reference_before": first}), flush=True)
    configs = []
    for path in CONFIGS:
        try:
            configs.append(_compose_report(path))
        except Exception as exc:
            configs.append({"config": str(path.relative_to(ROOT)), "error": f"{type(exc).__name__}: {exc}"})
        print(json.dumps(configs[-1]), flush=True)
    with tempfile.TemporaryDirectory() as folder:
        acceptance = run_acceptance(folder)
    for row in acceptance:
        print(json.dumps(row), flush=True)
    scaling = run_scaling()
    for row in scaling:
        print(json.dumps(row), flush=True)
    reference = combine_references(first, reference_operation())
    for row in configs + acceptance + scaling:
        if "timings" in row:
            row["timings_x_ref"] = {k: ratio(v, reference["seconds"]) for k, v in row["timings"].items()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d %H:%M"),
            "commit": git_commit(), "load_average_after": [round(x, 2) for x in os.getloadavg()]}
    medians = stage_medians(configs)
    (RESULTS / "compose_bench.json").write_text(json.dumps(
        {"meta": meta, "reference": reference, "stage_medians_s": medians,
         "stage_medians_x_ref": {k: ratio(v, reference["seconds"]) for k, v in medians.items()},
         "configs": configs, "acceptance": acceptance, "scaling": scaling}, indent=2) + "\n")
    (RESULTS / "compose_bench.md").write_text(_markdown(configs, scaling, reference, acceptance))
    return 0


if __name__ == "__main__":
    sys.exit(main())
