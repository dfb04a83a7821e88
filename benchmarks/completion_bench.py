"""Animation completion speed: 20 clips of 300 frames completed against 20 clips of 300 frames.

Also: scaling with the clip length (20 clips per side of 75 ... 600 frames), the share of the
score matrix alone, and the smoothness figure of the acceptance test (angular acceleration of
the completed joints over that of the source clips) on the real Horse + Knight centaur and
the built-in examples.

Characters: the pipeline's Horse + Knight centaur (tests/configs/centaur.toml: operations and
mapping stages) when the shared assets are present (the built-in centaur otherwise), with
synthetic clips (every joint swinging smoothly with random frequencies, amplitudes and
phases) so that the clip count and length are exact. The smoothness figures use the real
clips of every test config, for three frame-choice rules.
Writes ``benchmarks/results/completion.json`` and ``completion.md``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from rigmix.animation.completion import CompletionOptions, complete_clips, completion_provenance  # noqa: E402
from rigmix.character import Clip, Track  # noqa: E402
from rigmix.transforms import quat_multiply  # noqa: E402

FPS = 30.0


def synthetic_clips(skeleton, n_clips, n_frames, seed):
    """``n_clips`` LINEAR clips of ``n_frames`` keys at 30 fps on every joint of ``skeleton``."""
    rng = np.random.default_rng(seed)
    J = skeleton.num_joints
    t = np.arange(n_frames) / FPS
    clips = []
    for c in range(n_clips):
        axis = rng.normal(size=(J, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        amp = rng.uniform(0.05, 0.6, J)
        freq = rng.uniform(0.3, 2.0, J)
        phase = rng.uniform(0, 2 * np.pi, J)
        angle = amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None] + phase[None])  # (F, J)
        delta = np.concatenate([np.sin(angle / 2)[..., None] * axis[None], np.cos(angle / 2)[..., None]], -1)
        R = quat_multiply(skeleton.rotations[None], delta)
        T = np.broadcast_to(skeleton.translations, (n_frames, J, 3)).copy()
        T[:, 0, 1] += 0.05 * np.sin(2 * np.pi * freq[0] * t)
        tracks = [Track(j, "rotation", t, R[:, j]) for j in range(J)] + [Track(0, "translation", t, T[:, 0])]
        clips.append(Clip(f"clip{c:02d}", tuple(tracks)))
    return tuple(clips)


def characters():
    """(inputs, S_R, provenance, maps, label): the pipeline's Horse + Knight centaur
    (tests/configs/centaur.toml) when the shared assets are present, else examples/centaur.toml."""
    from conftest import ASSETS, CHARACTERS

    import rigmix

    if all((ASSETS / CHARACTERS[n]).exists() for n in ("Horse", "Knight")):
        config = ROOT / "tests" / "configs" / "centaur.toml"
        label = "Horse + Knight centaur (tests/configs/centaur.toml)"
    else:
        config, label = ROOT / "examples" / "centaur.toml", "built-in centaur (examples/centaur.toml)"
    comp = rigmix.compose(config, until="mapping")
    return comp.inputs, comp.plan.skeleton, comp.plan.provenance, comp.maps, label


def time_completion(inputs, skel, prov, maps, n_clips, n_frames, repeats=3):
    """(wall, cpu) seconds to complete the first input's clips against the second's (best of
    ``repeats``; CPU time counts this process's threads, a guide when the machine is shared)."""
    ids = list(inputs)
    synth = {cid: dataclasses.replace(ch, clips=synthetic_clips(ch.skeleton, n_clips, n_frames, i))
             for i, (cid, ch) in enumerate(inputs.items())}
    opts = CompletionOptions(clips={ids[0]: [c.name for c in synth[ids[0]].clips]})
    wall = cpu = np.inf
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = complete_clips(skel, synth, maps, options=opts, provenance=prov)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    assert len(out) == n_clips
    return wall, cpu


def time_scores(inputs, skel, n_frames_total, repeats=3):
    """(wall, CPU) seconds for the score matrix alone, (F, F) float32, every joint weighted."""
    from rigmix.animation.completion import keyframe_scores

    rng = np.random.default_rng(0)
    J = skel.num_joints
    G = rng.normal(size=(n_frames_total, J, 4))
    G /= np.linalg.norm(G, axis=-1, keepdims=True)
    P = rng.normal(size=(n_frames_total, J, 3))
    wall = cpu = np.inf
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        keyframe_scores(G, P, G, P, np.ones(J), dtype=np.float32)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu


#: (config, assets it needs) for the smoothness figures.
CONFIGS = [("examples/centaur.toml", ()),
           ("tests/configs/centaur.toml", ("Horse", "Knight")),
           ("tests/configs/tail_graft.toml", ("CesiumMan", "Velociraptor")),
           ("tests/configs/three_characters.toml", ("Knight", "Fox", "CesiumMan")),
           ("tests/configs/fox_arm.toml", ("CesiumMan", "Fox")),
           ("tests/configs/limb_swap.toml", ("CesiumMan", "RiggedFigure"))]

#: Frame-choice rules compared: (label, options).
RULES = [("paper: best frame per output frame", CompletionOptions(jump_penalty=0.0)),
         ("Viterbi, jump penalty 0.05", CompletionOptions(jump_penalty=0.05)),
         ("default: Viterbi, jump penalty 0.2", CompletionOptions())]


def smoothness_figures():
    """Acceleration ratios (completed joints over their source clips) through the pipeline."""
    import test_completion as tc
    from conftest import ASSETS, CHARACTERS

    import rigmix

    out = {}
    for config, assets in CONFIGS:
        if not all((ASSETS / CHARACTERS[n]).exists() for n in assets):
            out[config] = "skipped: shared assets missing"
            continue
        comp = rigmix.compose(ROOT / config, until="mapping")
        plan = comp.plan
        keys = [(cid, c.name) for cid, ch in comp.inputs.items() for c in ch.clips]
        prov = completion_provenance(plan)  # what the pipeline's completion stage uses
        out[config] = {}
        for label, opts in RULES:
            clips = complete_clips(plan.skeleton, comp.inputs, comp.maps, options=opts, provenance=prov)
            out[config][label] = tc.acceleration_figures(plan.skeleton, comp.inputs, comp.maps, prov, clips, keys)
    return out


def main():
    RESULTS.mkdir(parents=True, exist_ok=True)
    inputs, skel, prov, maps, label = characters()
    main_s, main_cpu = time_completion(inputs, skel, prov, maps, 20, 300)
    scaling = []
    for n in (75, 150, 300, 600):
        w, c = (main_s, main_cpu) if n == 300 else time_completion(inputs, skel, prov, maps, 20, n, repeats=1)
        scaling.append({"frames_per_clip": n, "clips_per_side": 20, "seconds": round(w, 3), "cpu_seconds": round(c, 3)})
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    score_s, score_cpu = time_scores(inputs, skel, 20 * 300)
    smooth = smoothness_figures()
    result = {
        "benchmark": "completion",
        "characters": label,
        "output_joints": skel.num_joints,
        "target_seconds": 2.0,
        "seconds_20x300_vs_20x300": round(main_s, 3),
        "cpu_seconds_20x300_vs_20x300": round(main_cpu, 3),
        "load_average_1min": load,
        "passes": bool(main_s < 2.0),
        "score_matrix_6000x6000_seconds": round(score_s, 3),
        "score_matrix_6000x6000_cpu_seconds": round(score_cpu, 3),
        "scaling": scaling,
        "acceleration_ratio_completed_over_source": smooth,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "numpy": np.__version__},
    }
    (RESULTS / "completion.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        f"Animation completion on {label} (S_R: {skel.num_joints} joints), {os.cpu_count()} CPUs.",
        "",
        f"- 20 clips x 300 frames completed against 20 clips x 300 frames: "
        f"**{main_s:.2f} s** wall, {main_cpu:.2f} s CPU (target < 2 s: {'met' if main_s < 2.0 else 'NOT met'}; "
        f"load average {load:.1f} on {os.cpu_count()} CPUs while measuring); "
        f"the 6000 x 6000 float32 score matrix alone (all {skel.num_joints} joints weighted): "
        f"{score_s:.2f} s wall, {score_cpu:.2f} s CPU.",
        "",
        "| frames per clip | clips per side | seconds (wall) | CPU seconds |",
        "|---:|---:|---:|---:|",
    ]
    lines += [f"| {r['frames_per_clip']} | {r['clips_per_side']} | {r['seconds']:.3f} | {r['cpu_seconds']:.3f} |"
              for r in scaling]
    lines += ["", "Mean angular acceleration of the completed joints over that of the same joints in "
              "their source clips (acceptance: <= 2; '-' where the source barely moves them):", "",
              "| config | rule | " + "completed clips of: ratio (mean, p95, max) |", "|---|---|---|"]

    def fmt(f):
        if f["mean_ratio"] is None:
            return "-"
        return f"{f['mean_ratio']:.2f} ({f['p95_ratio']:.2f}, {f['max_ratio']:.2f})"

    for config, rules in smooth.items():
        if isinstance(rules, str):
            lines.append(f"| {config} | {rules} | |")
            continue
        for rule, figs in rules.items():
            cells = "; ".join(f"{x}: {fmt(f)}" for x, f in figs.items())
            lines.append(f"| {config} | {rule} | {cells} |")
    (RESULTS / "completion.md").write_text("\n".join(lines) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
