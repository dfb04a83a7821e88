"""dfd speed (issue 5): renders, distillation, binding and deformation on the CPU.

- render: 24 views at 224 px of a ~50k-face mesh (target: about a second);
- distill: a 50k-face mesh with the default (filter bank) encoder and default settings, split
  into decimation, rendering, encoding and training (target: under 60 s on 2 cores); the mesh is
  CesiumMan subdivided twice (74,752 faces), so the 50k face budget decimates it first;
- bind: weights of 100 handles for 1M vertices from their features (target: under 1 s), plus
  the time to evaluate the field at 1M points (done once per mesh, not per binding);
- deform: one deformation of a 1M-vertex mesh by 100 handles (target: under 50 ms).

Timings are medians of several runs, with the load average of the machine at the time. Torch
runs with ONE thread (``--threads`` to change): on a shared, overloaded machine two threads spin
waiting for each other and both their wall and CPU times mean little, while the CPU seconds of a
single thread measure the work itself; on 2 free cores the wall time is at most that. Writes
``benchmarks/results/dfd_bench.json`` and ``dfd_bench.md``.

Usage: ``python -m benchmarks.dfd_bench``.
"""

from __future__ import annotations

import os

# one BLAS thread as well, for the same reason (effective when this module is the first to load numpy)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from conftest import ASSETS, CHARACTERS  # noqa: E402

from dfd.deform import deform, translations  # noqa: E402
from dfd.distill import DEFAULT_BATCH_SIZE, DEFAULT_STEPS, decimate, distill  # noqa: E402
from dfd.encoders import encode_views, get_encoder  # noqa: E402
from dfd.field import FeatureField  # noqa: E402
from dfd.io import read_mesh  # noqa: E402
from dfd.render import render_views  # noqa: E402
from dfd.shapes import grid  # noqa: E402
from dfd.weights import handle_weights  # noqa: E402

#: CPU seconds (all threads of this process) of each measure, by name, next to the wall times.
CPU = {}


def _timed(fn, repeats=1, name=None):
    """(median wall seconds, last result) of ``repeats`` calls; records median CPU seconds."""
    times, cpu, out = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    if name:
        CPU[name] = float(np.median(cpu))
    return float(np.median(times)), out


def _character_50k():
    import igl

    m = read_mesh(ASSETS / CHARACTERS["CesiumMan"])
    V, F = m.V, m.F
    UV = m.uvs
    for _ in range(2):  # upsample positions and UVs together (same vertex order, same faces)
        VU, F = igl.upsample(np.hstack([V, UV]), F)
        V, UV = VU[:, :3], VU[:, 3:]
    return V, np.asarray(F, dtype=np.int64), UV, m.texture


def bench_render_and_distill():
    V, F, UV, tex = _character_50k()
    out = {"mesh": f"CesiumMan subdivided twice: {len(V)} vertices, {len(F)} faces"}
    t_dec, (Vd, Fd, _, UVd) = _timed(lambda: decimate(V, F, 50_000, uvs=UV), name="decimate")
    out["decimate_s"] = t_dec
    out["decimated_faces"] = int(len(Fd))
    t_render, views = _timed(lambda: render_views(Vd, Fd, uvs=UVd, texture=tex), repeats=3, name="render")
    out["render_24x224_s"] = t_render
    out["covered_pixels"] = int(views.mask.sum())
    enc = get_encoder("filterbank")
    t_enc, feats = _timed(lambda: encode_views(enc, views), name="encode")
    out["encode_s"] = t_enc
    out["steps"] = DEFAULT_STEPS
    out["batch_size"] = DEFAULT_BATCH_SIZE
    out["distill_total_s"] = _timed(lambda: distill(V, F, uvs=UV, texture=tex), name="distill")[0]
    # training is what remains of the total once decimation, rendering and encoding are counted
    out["train_s"] = out["distill_total_s"] - t_dec - t_render - t_enc
    CPU["train"] = CPU["distill"] - CPU["decimate"] - CPU["render"] - CPU["encode"]
    return out


def bench_bind_and_deform(n_side=1000, n_handles=100):
    V, F = grid(n_side)  # 1,000,000 vertices
    rng = np.random.default_rng(0)
    C = get_encoder("filterbank").feature_dim
    field = FeatureField(C)
    out = {"vertices": int(len(V)), "handles": n_handles}
    # the field is evaluated once per mesh, not per binding: timed on 100k points, scaled to 1M
    t_eval, _ = _timed(lambda: field.evaluate(V[:100_000]), name="evaluate")
    out["field_evaluate_1M_s"] = 10.0 * t_eval
    CPU["evaluate"] *= 10.0
    # binding cost does not depend on the feature values: random unit features
    feats = rng.normal(size=(len(V), C)).astype(np.float32)
    feats /= np.linalg.norm(feats, axis=1, keepdims=True)
    handles = rng.choice(len(V), n_handles, replace=False)
    H = feats[handles]
    out["bind_s"], W = _timed(lambda: handle_weights(feats, H), repeats=5, name="bind")
    out["bind_cosine_s"] = _timed(lambda: handle_weights(feats, H, form="cosine"), repeats=5, name="bind_cosine")[0]
    T = translations(rng.normal(size=(n_handles, 3)))
    out["deform_s"] = _timed(lambda: deform(V, W, T), repeats=7, name="deform")[0]
    out["weights_dtype"] = str(W.dtype)
    # for scale: one single-threaded read of the dense weights (deform splits its read over the cores)
    out["read_weights_once_s"] = _timed(lambda: W.sum(axis=1), repeats=7, name="read_weights")[0]
    return out


def main(threads=1):
    RESULTS.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(threads)
    result = {
        "machine": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
            "cpus": os.cpu_count(),
            "load_average_start": os.getloadavg(),
        },
        "targets": {"render_s": 1.0, "distill_s": 60.0, "bind_s": 1.0, "deform_s": 0.05},
    }
    result["bind_deform"] = bench_bind_and_deform()
    result["render_distill"] = bench_render_and_distill()
    result["machine"]["load_average_end"] = os.getloadavg()
    result["cpu_seconds"] = CPU
    (RESULTS / "dfd_bench.json").write_text(json.dumps(result, indent=2) + "\n")
    r, b = result["render_distill"], result["bind_deform"]
    load = ", ".join(f"{x:.1f}" for x in result["machine"]["load_average_start"])
    lines = [
        f"Machine: {result['machine']['cpus']} CPUs, torch {result['machine']['torch']} with "
        f"{result['machine']['torch_threads']} threads, load average at start {load}.",
        "",
        "Wall seconds, and CPU seconds of the process: on a loaded machine the CPU figure is the one",
        "to compare with the targets (with one torch thread, wall ~ CPU when a core is free), but",
        "for deform, which splits its rows over every core: its CPU figure is the sum of the threads'.",
        "",
        "| measure | wall s | CPU s | target s |",
        "|---|---:|---:|---:|",
        f"| render 24 views x 224 px ({r['decimated_faces']} faces) | {r['render_24x224_s']:.3f} "
        f"| {CPU['render']:.3f} | ~1 |",
        f"| distill ({r['mesh']}), total | {r['distill_total_s']:.1f} | {CPU['distill']:.1f} | < 60 |",
        f"| - decimate to 50k | {r['decimate_s']:.2f} | {CPU['decimate']:.2f} | |",
        f"| - encode (filter bank) | {r['encode_s']:.2f} | {CPU['encode']:.2f} | |",
        f"| - train ({r['steps']} steps x {r['batch_size']} px; total minus the above) | {r['train_s']:.1f} "
        f"| {CPU['train']:.1f} | |",
        f"| bind {b['handles']} handles, {b['vertices']} vertices (distance form) | {b['bind_s']:.3f} "
        f"| {CPU['bind']:.3f} | < 1 |",
        f"| bind, cosine form | {b['bind_cosine_s']:.3f} | {CPU['bind_cosine']:.3f} | |",
        f"| field evaluation at {b['vertices']} points (once per mesh; 100k timed, x10) "
        f"| {b['field_evaluate_1M_s']:.1f} | {CPU['evaluate']:.1f} | |",
        f"| deform {b['vertices']} vertices, {b['handles']} handles (translations) | {b['deform_s']:.3f} "
        f"| {CPU['deform']:.3f} | < 0.05 |",
        f"| - for scale: one single-threaded read of the {b['vertices']} x {b['handles']} float32 weights (W.sum) "
        f"| {b['read_weights_once_s']:.3f} | {CPU['read_weights']:.3f} | |",
    ]
    (RESULTS / "dfd_bench.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    main(parser.parse_args().threads)
