"""dfd speed (issue 5): renders, distillation, binding and deformation on the CPU.

- render: 24 views at 224 px of a ~50k-face mesh (target: about a second);
- distill: a 50k-face mesh with the default (filter bank) encoder and default settings, split
  into decimation, rendering, encoding and training (target: under 60 s on 2 cores); the mesh is
  CesiumMan subdivided twice (74,752 faces), so the 50k face budget decimates it first;
- bind: weights of 100 handles for 1M vertices from their features (target: under 1 s), plus
  the time to evaluate the field at 1M points (done once per mesh, not per binding);
- deform: one deformation of a 1M-vertex mesh by 100 handles (target: under 50 ms).

Timings are medians of several runs, with the load average of the machine at the time (the
development machine is shared, so wall times there are pessimistic). Writes
``benchmarks/results/dfd_bench.json`` and ``dfd_bench.md``.

Usage: ``python -m benchmarks.dfd_bench``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from conftest import ASSETS, CHARACTERS  # noqa: E402

from dfd.deform import deform, translations  # noqa: E402
from dfd.distill import DEFAULT_BATCH_SIZE, DEFAULT_STEPS, decimate, distill, training_samples  # noqa: E402
from dfd.encoders import encode_views, get_encoder  # noqa: E402
from dfd.field import FeatureField  # noqa: E402
from dfd.io import read_mesh  # noqa: E402
from dfd.render import render_views  # noqa: E402
from dfd.shapes import grid  # noqa: E402
from dfd.weights import handle_weights  # noqa: E402


def _timed(fn, repeats=1):
    """(median seconds, last result) of ``repeats`` calls."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
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
    t_dec, (Vd, Fd, _, UVd) = _timed(lambda: decimate(V, F, 50_000, uvs=UV))
    out["decimate_s"] = t_dec
    out["decimated_faces"] = int(len(Fd))
    t_render, views = _timed(lambda: render_views(Vd, Fd, uvs=UVd, texture=tex), repeats=3)
    out["render_24x224_s"] = t_render
    out["covered_pixels"] = int(views.mask.sum())
    enc = get_encoder("filterbank")
    t_enc, feats = _timed(lambda: encode_views(enc, views))
    out["encode_s"] = t_enc
    points, targets = training_samples(Vd, Fd, views, feats)
    # training alone, the same loop as distill, at the default steps and batch size
    X = torch.from_numpy(points.astype(np.float32))
    Y = torch.from_numpy(targets)
    field = FeatureField(Y.shape[1])
    opt = torch.optim.Adam(field.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(0)

    def train():
        for _ in range(DEFAULT_STEPS):
            idx = torch.randint(len(X), (DEFAULT_BATCH_SIZE,), generator=g)
            loss = (field(X[idx]) - Y[idx]).square().sum(dim=1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()

    out["train_s"] = _timed(train)[0]
    out["steps"] = DEFAULT_STEPS
    out["batch_size"] = DEFAULT_BATCH_SIZE
    cpu0 = time.process_time()
    out["distill_total_s"] = _timed(lambda: distill(V, F, uvs=UV, texture=tex))[0]
    out["distill_total_cpu_s"] = time.process_time() - cpu0
    return out


def bench_bind_and_deform(n_side=1000, n_handles=100):
    V, F = grid(n_side)  # 1,000,000 vertices
    rng = np.random.default_rng(0)
    field = FeatureField(get_encoder("filterbank").feature_dim)
    out = {"vertices": int(len(V)), "handles": n_handles}
    t_eval, feats = _timed(lambda: field.evaluate(V))
    out["field_evaluate_1M_s"] = t_eval
    handles = rng.choice(len(V), n_handles, replace=False)
    H = feats[handles]
    out["bind_s"], W = _timed(lambda: handle_weights(feats, H), repeats=5)
    out["bind_cosine_s"] = _timed(lambda: handle_weights(feats, H, form="cosine"), repeats=5)[0]
    T = translations(rng.normal(size=(n_handles, 3)))
    out["deform_s"] = _timed(lambda: deform(V, W, T), repeats=7)[0]
    out["weights_dtype"] = str(W.dtype)
    return out


def main():
    RESULTS.mkdir(parents=True, exist_ok=True)
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
    (RESULTS / "dfd_bench.json").write_text(json.dumps(result, indent=2) + "\n")
    r, b = result["render_distill"], result["bind_deform"]
    load = ", ".join(f"{x:.1f}" for x in result["machine"]["load_average_start"])
    lines = [
        f"Machine: {result['machine']['cpus']} CPUs, torch {result['machine']['torch']} with "
        f"{result['machine']['torch_threads']} threads, load average at start {load}.",
        "",
        "| measure | seconds | target |",
        "|---|---:|---:|",
        f"| render 24 views x 224 px ({r['decimated_faces']} faces) | {r['render_24x224_s']:.3f} | ~1 |",
        f"| distill ({r['mesh']}), total | {r['distill_total_s']:.1f} | < 60 |",
        f"| - decimate to 50k | {r['decimate_s']:.2f} | |",
        f"| - encode (filter bank) | {r['encode_s']:.2f} | |",
        f"| - train ({r['steps']} steps x {r['batch_size']} px) | {r['train_s']:.1f} | |",
        f"| bind {b['handles']} handles, {b['vertices']} vertices (distance form) | {b['bind_s']:.3f} | < 1 |",
        f"| bind, cosine form | {b['bind_cosine_s']:.3f} | |",
        f"| field evaluation at {b['vertices']} points (once per mesh) | {b['field_evaluate_1M_s']:.1f} | |",
        f"| deform {b['vertices']} vertices, {b['handles']} handles | {b['deform_s']:.3f} | < 0.05 |",
    ]
    (RESULTS / "dfd_bench.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result


if __name__ == "__main__":
    main()
