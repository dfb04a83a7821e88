"""Animation completion speed: 20 clips of 300 frames completed against 20 clips of 300 frames.

Also: scaling with the clip length (20 clips per side of 75 ... 600 frames), the share of the
score matrix alone, and the smoothness figure of the acceptance test (angular acceleration of
the completed joints over that of the source clips) on the real Horse + Knight centaur and
the built-in examples.

Characters: the shared Horse (50 joints) and Knight (31 joints) skeletons when available
(the built-in examples otherwise), with synthetic clips (every joint swinging smoothly with
random frequencies, amplitudes and phases) so that the clip count and length are exact.
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

from rigmix.character import Clip, Track  # noqa: E402
from rigmix.completion import CompletionOptions, complete_clips  # noqa: E402
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
    """(base, donor, graft arguments, label): Horse + Knight if present, else the examples."""
    import test_completion as tc

    try:
        from conftest import ASSETS, CHARACTERS
        from rigmix.io import load_character

        horse = load_character(ASSETS / CHARACTERS["Horse"])
        knight = load_character(ASSETS / CHARACTERS["Knight"])
        extra = [("knight", "Body", "Body", 0.5), ("knight", "Hips", "Torso", 0.6),
                 ("knight", "Abdomen", "Torso2", 0.7), ("horse", "Neck1", "knight.Neck", 0.6),
                 ("horse", "Head", "knight.Head", 0.7)]
        skel, prov, maps = tc.graft(horse, "horse", "Torso3", knight, "knight", "Torso",
                                    drop="Neck1", extra=extra)
        return {"horse": horse, "knight": knight}, skel, prov, maps, "Horse + Knight (shared assets)"
    except Exception:  # assets missing: the built-in examples
        from rigmix import examples

        quad, human = examples.quadruped(), examples.humanoid()
        extra = [("human", "Hips", "Hips", 0.5), ("human", "Spine", "Spine", 0.6),
                 ("quad", "Head", "human.Head", 0.7)]
        skel, prov, maps = tc.graft(quad, "quad", "Neck", human, "human", "Chest", extra=extra)
        return {"quad": quad, "human": human}, skel, prov, maps, "examples quadruped + humanoid"


def time_completion(inputs, skel, prov, maps, n_clips, n_frames, repeats=3):
    """Seconds to complete the first input's clips against the second's (best of repeats)."""
    ids = list(inputs)
    synth = {cid: dataclasses.replace(ch, clips=synthetic_clips(ch.skeleton, n_clips, n_frames, i))
             for i, (cid, ch) in enumerate(inputs.items())}
    opts = CompletionOptions(clips={ids[0]: [c.name for c in synth[ids[0]].clips]})
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = complete_clips(skel, synth, maps, options=opts, provenance=prov)
        best = min(best, time.perf_counter() - t0)
    assert len(out) == n_clips
    return best


def time_scores(inputs, skel, n_frames_total, repeats=3):
    """Seconds for the score matrix alone, (F, F), with every joint of S_R weighted."""
    from rigmix.completion import keyframe_scores

    rng = np.random.default_rng(0)
    J = skel.num_joints
    G = rng.normal(size=(n_frames_total, J, 4))
    G /= np.linalg.norm(G, axis=-1, keepdims=True)
    P = rng.normal(size=(n_frames_total, J, 3))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        keyframe_scores(G, P, G, P, np.ones(J))
        best = min(best, time.perf_counter() - t0)
    return best


def smoothness_figures():
    """Acceleration ratios of the acceptance test on real and built-in characters."""
    import test_completion as tc
    from rigmix import examples

    out = {}
    quad, human = examples.quadruped(), examples.humanoid()
    extra = [("human", "Hips", "Hips", 0.5), ("human", "Spine", "Spine", 0.6), ("quad", "Head", "human.Head", 0.7)]
    skel, prov, maps = tc.graft(quad, "quad", "Neck", human, "human", "Chest", extra=extra)
    inputs = {"quad": quad, "human": human}
    clips = complete_clips(skel, inputs, maps, provenance=prov)
    keys = [(cid, c.name) for cid, ch in inputs.items() for c in ch.clips]
    out["examples centaur"] = tc.acceleration_figures(skel, inputs, maps, prov, clips, keys)
    try:
        inputs, skel, prov, maps, label = characters()
        if "horse" in inputs:
            for name, opts in (("default (Viterbi, jump_penalty 0.05)", CompletionOptions()),
                               ("paper rule (best frame per output frame)", CompletionOptions(jump_penalty=0.0))):
                clips = complete_clips(skel, inputs, maps, options=opts, provenance=prov)
                keys = [(cid, c.name) for cid, ch in inputs.items() for c in ch.clips]
                out[f"Horse + Knight centaur, {name}"] = tc.acceleration_figures(skel, inputs, maps, prov, clips, keys)
    except Exception as exc:  # noqa: BLE001 - report, do not fail the benchmark
        out["Horse + Knight centaur"] = f"skipped: {exc}"
    return out


def main():
    RESULTS.mkdir(parents=True, exist_ok=True)
    inputs, skel, prov, maps, label = characters()
    main_s = time_completion(inputs, skel, prov, maps, 20, 300)
    scaling = []
    for n in (75, 150, 300, 600):
        s = main_s if n == 300 else time_completion(inputs, skel, prov, maps, 20, n, repeats=1)
        scaling.append({"frames_per_clip": n, "clips_per_side": 20, "seconds": round(s, 3)})
    score_s = time_scores(inputs, skel, 20 * 300)
    smooth = smoothness_figures()
    result = {
        "benchmark": "completion",
        "characters": label,
        "output_joints": skel.num_joints,
        "target_seconds": 2.0,
        "seconds_20x300_vs_20x300": round(main_s, 3),
        "passes": bool(main_s < 2.0),
        "score_matrix_6000x6000_seconds": round(score_s, 3),
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
        f"**{main_s:.2f} s** (target < 2 s: {'met' if main_s < 2.0 else 'NOT met'}); "
        f"the 6000 x 6000 score matrix alone (all joints weighted): {score_s:.2f} s.",
        "",
        "| frames per clip | clips per side | seconds |",
        "|---:|---:|---:|",
    ]
    lines += [f"| {r['frames_per_clip']} | {r['clips_per_side']} | {r['seconds']:.3f} |" for r in scaling]
    lines += ["", "Angular acceleration of the completed joints over that of the source clips (mean, p95, max):", "",
              "| case | completed clips of | mean | p95 | max |", "|---|---|---:|---:|---:|"]
    for case, figs in smooth.items():
        if isinstance(figs, str):
            lines.append(f"| {case} | {figs} | | | |")
            continue
        for x, f in figs.items():
            lines.append(f"| {case} | {x} | {f['mean_ratio']:.2f} | {f['p95_ratio']:.2f} | {f['max_ratio']:.2f} |")
    (RESULTS / "completion.md").write_text("\n".join(lines) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
