"""`make bench`: run every benchmark module in this folder and write a Markdown summary.

Each benchmark is a module ``benchmarks/<name>.py`` with a ``main()`` that writes
``benchmarks/results/<name>.json`` and ``<name>.md``. This runner calls them in turn (one
failing does not stop the others), then concatenates their Markdown tables into
``benchmarks/results/SUMMARY.md``.

Usage: ``python -m benchmarks.run [NAME ...]`` (default: all). Naming some re-runs those and
keeps the others' last status in ``run.json`` and their last results in the summary.
"""

from __future__ import annotations

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


#: Modules that are not timing or quality benchmarks: the hostile-input corpus (``make fuzz``) and the
#: composition matrix (``make corpus``) have their own targets, each longer than the whole ``make bench``.
NOT_BENCHMARKS = {"__init__", "run", "common", "calibrate", "fuzz", "corpus", "corpus_matrix"}


def discover() -> list[str]:
    """Names of the benchmark modules, sorted."""
    return sorted(p.stem for p in HERE.glob("*.py") if p.stem not in NOT_BENCHMARKS)


def main(argv=None) -> int:
    names = list(argv if argv is not None else sys.argv[1:]) or discover()
    RESULTS.mkdir(parents=True, exist_ok=True)
    status = {}
    for name in names:
        t0 = time.perf_counter()
        print(f"== benchmark {name}", flush=True)
        try:
            importlib.import_module(f"benchmarks.{name}").main()
            status[name] = {"status": "ok", "seconds": round(time.perf_counter() - t0, 2)}
        except Exception as exc:  # a failing benchmark is reported, the others still run
            traceback.print_exc()
            status[name] = {"status": "failed", "error": f"{type(exc).__name__}: {exc}",
                            "seconds": round(time.perf_counter() - t0, 2)}
    # a partial run (names given) updates its entries; the summary always covers every benchmark
    previous = RESULTS / "run.json"
    merged = json.loads(previous.read_text()) if previous.exists() else {}
    merged.update(status)
    known = set(discover())
    merged = {n: merged[n] for n in sorted(merged) if n in known}
    lines = ["# rigmix benchmarks", "",
             "| benchmark | status | seconds |", "|---|---|---:|"]
    lines += [f"| {n} | {s['status']} | {s['seconds']} |" for n, s in merged.items()]
    for name in merged:
        md = RESULTS / f"{name}.md"
        if md.exists():
            lines += ["", f"## {name}", "", md.read_text().strip()]
    (RESULTS / "SUMMARY.md").write_text("\n".join(lines) + "\n")
    (RESULTS / "run.json").write_text(json.dumps(merged, indent=2) + "\n")
    print(f"wrote {RESULTS / 'SUMMARY.md'}")
    return 0 if all(s["status"] == "ok" for s in status.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
