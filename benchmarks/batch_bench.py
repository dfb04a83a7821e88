"""Batch throughput: ``rigmix.batch.run_batch`` with 1 and 2 worker processes.

Eight configs built from the shipped built-in example compositions (``examples/*.toml``: tail
graft, arm self-composition, centaur, beast arms), each also with the prototype's mapping score,
all with the ``nearest`` junction weights so that the batch machinery and the surface fusion
dominate rather than the weight solver. The built-in characters are built once per batch
(:func:`rigmix.batch.share_builtins`; included in the wall time, reported separately as the largest
load stage of a job).

Writes ``benchmarks/results/batch_bench.json`` and ``batch_bench.md``: wall time, compositions
per minute, mean and median compose time per job, the speed-up of 2 workers over 1, and the
machine's load average (the timings are only comparable on an otherwise idle machine). CPU
seconds say what the load does not change: the jobs' own (``timings.cpu`` of the manifest, summed),
and all the worker processes' (start-up, imports, built-in characters and the validator's
subprocesses included); from the speed-up S, the serial fraction by Amdahl's law, 2 / S - 1.
"""

from __future__ import annotations

import json
import os
import platform
import re
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT))

from rigmix.batch import run_batch  # noqa: E402

EXAMPLES = ["tailed_humanoid", "self_arm", "centaur", "beast_arms"]
WORKERS = (1, 2)


def make_configs(folder: Path) -> list[Path]:
    """Two variants of each built-in example: as shipped, and with the prototype's mapping score."""
    paths = []
    for name in EXAMPLES:
        text = (ROOT / "examples" / f"{name}.toml").read_text()
        text = re.sub(r"(?m)^\[weights\][^\[]*", "", text) + '\n[weights]\nmethod = "nearest"\n'
        for k, extra in enumerate(("", '\n[mapping]\nscore = "prototype"\n')):
            p = folder / f"{name}_{k}.toml"
            p.write_text(text + extra)
            paths.append(p)
    return paths


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)  # the workers, once the pool has joined them
    return r.ru_utime + r.ru_stime


def run(workers: int, configs: list[Path], out: Path) -> dict:
    c0 = _children_cpu()
    t0 = time.perf_counter()
    entries = run_batch(configs, out, workers=workers)
    wall = time.perf_counter() - t0
    workers_cpu = _children_cpu() - c0
    ok = [e for e in entries if e["status"] == "ok"]
    compose = [e["timings"]["compose"] for e in ok]
    load = [e["timings"].get("stages", {}).get("load", 0.0) for e in ok]
    return {
        "workers": workers,
        "jobs": len(entries),
        "ok": len(ok),
        "failed": [f"{e['stem']}: {e['error']}" for e in entries if e["status"] != "ok"],
        "wall_s": round(wall, 2),
        "per_minute": round(60.0 * len(ok) / wall, 2) if wall > 0 else None,
        "compose_mean_s": round(statistics.mean(compose), 3) if compose else None,
        "compose_median_s": round(statistics.median(compose), 3) if compose else None,
        "load_max_s": round(max(load), 3) if load else None,
        "jobs_cpu_s": round(sum(e["timings"].get("cpu", 0.0) for e in ok), 2),
        "workers_cpu_s": round(workers_cpu, 2),
    }


def main():
    RESULTS.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(prefix="rigmix-batch-bench-") as tmp:
        tmp = Path(tmp)
        (tmp / "configs").mkdir()
        configs = make_configs(tmp / "configs")
        for w in WORKERS:
            rows.append(run(w, configs, tmp / f"out{w}"))
    speedup = rows[0]["wall_s"] / rows[1]["wall_s"] if rows[1]["wall_s"] else None
    serial = 2.0 / speedup - 1.0 if speedup else None
    result = {
        "benchmark": "batch_bench",
        "configs": [p.name for p in configs],
        "runs": rows,
        "speedup_2_over_1": round(speedup, 2) if speedup else None,
        "serial_fraction": round(serial, 3) if serial is not None else None,
        "cpu_count": os.cpu_count(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    (RESULTS / "batch_bench.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        f"Batch of {len(configs)} built-in compositions (nearest junction weights), "
        f"{os.cpu_count()} CPUs, load average {result['load_average_before'][0]} before the run.",
        "",
        "| workers | jobs ok | wall (s) | compositions / min | compose mean (s) | compose median (s) | "
        "built-in load, max (s) | jobs' CPU (s) | worker processes' CPU (s) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['workers']} | {r['ok']}/{r['jobs']} | {r['wall_s']} | {r['per_minute']} | "
                     f"{r['compose_mean_s']} | {r['compose_median_s']} | {r['load_max_s']} | {r['jobs_cpu_s']} | "
                     f"{r['workers_cpu_s']} |")
    lines += ["", f"Speed-up of 2 workers over 1: {result['speedup_2_over_1']}x (serial fraction by Amdahl's law, "
              f"2 / S - 1: {result['serial_fraction']}); load average {result['load_average_after'][0]} after."]
    failed = [f for r in rows for f in r["failed"]]
    if failed:
        lines += ["", "Failed jobs: " + "; ".join(sorted(set(failed)))]
    (RESULTS / "batch_bench.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result


if __name__ == "__main__":
    main()
