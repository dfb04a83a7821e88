"""USD export and offscreen rendering: speed and agreement figures on every shared character.

For each character in ``../shared/data/characters`` (or ``$RIGMIX_ASSETS``):

* ``write_usd`` (``.usdc``, every clip) and ``read_usd`` times (median of 3);
* UsdValidation errors on the written stage (all registered validators);
* the largest difference between UsdSkel's own skinned points and rigmix's, at 10 times of
  every clip (switching the ``animation`` variant), relative to the bounding-box diagonal
  (issue 7, acceptance 3: at most 1e-5);
* the round trip (write then read) difference over every frame of every clip, same measure;
* render speed (frames per second at 240x240) of the OpenGL (EGL, Mesa llvmpipe) and Pillow
  rasterizers on the first clip.

Writes ``benchmarks/results/usd_render.json`` and ``usd_render.md``.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from conftest import ASSETS, CHARACTERS  # noqa: E402
from pxr import Usd, UsdSkel  # noqa: E402
from test_usd import (  # noqa: E402
    ours_world,
    posed_error,
    relative_error,
    select_clip,
    ten_times,
    usd_skinned_world,
    validation_errors,
)

from benchmarks.common import median_seconds  # noqa: E402
from rigmix.animation import clip_times  # noqa: E402
from rigmix.io.gltf import read_gltf  # noqa: E402
from rigmix.io.usd import write_usd  # noqa: E402
from rigmix.io.usd_read import read_usd  # noqa: E402
from rigmix.preview.render import pose_scene, render_frames  # noqa: E402


def main():
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, rel in sorted(CHARACTERS.items()):
            path = ASSETS / rel
            if not path.exists():
                continue
            ch = read_gltf(path)
            out = Path(tmp) / f"{name}.usdc"
            write_ms = 1e3 * median_seconds(lambda: write_usd(ch, out))
            read_ms = 1e3 * median_seconds(lambda: read_usd(out))
            stage = Usd.Stage.Open(str(out))
            anims = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
            usdskel = 0.0
            for anim, clip in zip(anims, ch.clips):
                select_clip(stage, anim.GetName())
                t = ten_times(clip)
                usdskel = max(usdskel, relative_error(usd_skinned_world(stage, t), ours_world(ch, clip, t)))
            scene = pose_scene(ch, ch.clips[0] if ch.clips else None)
            fps = {}
            for backend in ("gl", "pil"):
                t0 = time.perf_counter()
                render_frames(scene, width=240, height=240, backend=backend)
                fps[backend] = len(scene.times) / (time.perf_counter() - t0)
            rows.append({
                "name": name,
                "clips": len(ch.clips),
                "usdc_bytes": out.stat().st_size,
                "write_ms": write_ms,
                "read_ms": read_ms,
                "validation_errors": len(validation_errors(out)),
                "usdskel_vs_rigmix": usdskel,
                "round_trip": posed_error(ch, read_usd(out), clip_times),
                "render_fps_gl": fps["gl"],
                "render_fps_pil": fps["pil"],
            })
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "machine": platform.machine(), "processor": platform.processor()}
    (RESULTS / "usd_render.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = ["| character | clips | write ms | read ms | validation errors | UsdSkel vs rigmix (x diag) "
             "| round trip (x diag) | render fps gl / pil (240 px) |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['name']} | {r['clips']} | {r['write_ms']:.1f} | {r['read_ms']:.1f} | "
                     f"{r['validation_errors']} | {r['usdskel_vs_rigmix']:.2e} | {r['round_trip']:.2e} | "
                     f"{r['render_fps_gl']:.0f} / {r['render_fps_pil']:.0f} |")
    (RESULTS / "usd_render.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
