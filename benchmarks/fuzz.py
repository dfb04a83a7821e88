"""`make fuzz`: run the whole hostile-input corpus (``tests/hostile.py``) and write a table.

Every file case is run as ``rigmix inspect FILE``; those that read (exit 0) are also converted to
GLB, and a round-robin subset of them (``--compose-max``, across categories) composed with
themselves (a self-composition config that uses the file as body and donor). Every bad config is
run as ``rigmix compose``. Each run is a subprocess with a 120 s timeout, an address-space limit
and an audit hook on ``open`` (``tests/hostile.py``).

Results: ``benchmarks/results/fuzz.md`` (one row per category, counts of cases) and ``fuzz.json``
(the table and every run that failed the acceptance, with its reasons).

Usage: ``python -m benchmarks.fuzz [--quick] [--category NAME ...] [--compose-max N] [--keep]``.
Exit status 0 when every run passes the acceptance, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE.parent / "tests"))

import hostile  # noqa: E402

#: Table columns: (key, header). Counts are of cases: a case counts once if any of its runs shows it.
COLUMNS = [
    ("cases", "cases"), ("runs", "runs"), ("clean_error", "clean errors"), ("accepted", "exit 0"),
    ("internal_error", "internal errors"), ("traceback", "tracebacks"), ("hang", "hangs"), ("crash", "crashes"),
    ("silently_accepted", "silently accepted"), ("partial_files", "partial files"),
    ("inputs_modified", "inputs modified"), ("outside_opens", "outside opens"), ("leaked", "sentinel leaks"),
    ("raw_controls", "raw controls"), ("invalid_output", "invalid outputs"), ("unexpected", "unexpected"),
    ("peak_rss_mb", "peak RSS MB"),
]


def summarize(outcomes: list, cases: list) -> dict:
    """category -> counts (and a TOTAL row)."""
    by_case: dict[str, list] = {}
    for o in outcomes:
        by_case.setdefault(o.case, []).append(o)
    cat = {c.id: c.category for c in cases}
    rows: dict[str, dict] = {}
    for cid, runs in by_case.items():
        for name in (cat[cid], "TOTAL"):
            row = rows.setdefault(name, {k: 0 for k, _ in COLUMNS})
            row["cases"] += 1
            row["runs"] += len(runs)
            first = runs[0]  # inspect for a file, compose for a config
            row["clean_error"] += first.clean_error
            row["accepted"] += first.rc == 0
            for key in ("internal_error", "traceback", "hang", "crash", "silently_accepted", "leaked",
                        "raw_controls", "invalid_output", "unexpected"):
                row[key] += any(getattr(r, key) for r in runs)
            for key in ("partial_files", "inputs_modified", "outside_opens"):
                row[key] += any(bool(getattr(r, key)) for r in runs)
            row["peak_rss_mb"] = max(row["peak_rss_mb"], max(r.peak_rss_mb for r in runs))
    order = sorted(k for k in rows if k != "TOTAL") + ["TOTAL"]
    return {k: rows[k] for k in order if k in rows}


def markdown(table: dict, meta: dict) -> str:
    lines = ["# Hostile-input corpus (`make fuzz`)", "",
             f"{meta['cases']} cases ({meta['file_cases']} files, {meta['config_cases']} configs), "
             f"{meta['runs']} runs (inspect {meta['commands'].get('inspect', 0)}, convert "
             f"{meta['commands'].get('convert', 0)}, compose {meta['commands'].get('compose', 0)}) in "
             f"{meta['seconds']:.0f} s; timeout {meta['timeout']:.0f} s per run; commit {meta['commit']}"
             + (" (PARTIAL: interrupted)" if meta.get("partial") else "") + ".", "",
             "Counts are of cases (a case counts once if any of its runs shows it). *clean errors*: the "
             "first run (inspect, or compose for a config) exits 2 with one `rigmix: error:` line. "
             "*silently accepted*: exit 0 with no warning where the Khronos validator reports errors "
             "(configs: exit 0 where a refusal is expected). *unexpected*: the outcome differs from the "
             "case's expectation (refuse / refuse-or-repair). *outside opens*: audit-hook `open` events "
             "outside the case's folder (symlinks resolved; the file named on the command line is "
             "trusted, wherever a link leads); *sentinel leaks*: bytes of the sentinel files "
             "(or their folder's path) in any output, stdout or stderr.", "",
             "| category | " + " | ".join(h for _, h in COLUMNS) + " |",
             "|---|" + "---:|" * len(COLUMNS)]
    for name, row in table.items():
        cells = [f"{row[k]:.0f}" if k == "peak_rss_mb" else str(row[k]) for k, _ in COLUMNS]
        label = f"**{name}**" if name == "TOTAL" else name
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE.parent, capture_output=True,
                              text=True, timeout=10).stdout.strip() or "?"
    except OSError:
        return "?"


def _pick_compose(eligible: list, limit: int) -> list:
    """Round-robin across categories, in corpus order, up to ``limit`` cases."""
    by_cat: dict[str, list] = {}
    for c in eligible:
        by_cat.setdefault(c.category, []).append(c)
    picked = []
    while len(picked) < limit and any(by_cat.values()):
        for cat in list(by_cat):
            if by_cat[cat] and len(picked) < limit:
                picked.append(by_cat[cat].pop(0))
    order = {c.id: i for i, c in enumerate(eligible)}
    return sorted(picked, key=lambda c: order[c.id])


def _meta(outcomes, cases, args, seconds, partial=False) -> dict:
    commands: dict[str, int] = {}
    for o in outcomes:
        commands[o.command] = commands.get(o.command, 0) + 1
    done = {o.case for o in outcomes}
    return {"cases": len(done), "file_cases": sum(c.kind == "file" for c in cases if c.id in done),
            "config_cases": sum(c.kind == "config" for c in cases if c.id in done), "runs": len(outcomes),
            "commands": commands, "seconds": seconds, "timeout": args.timeout, "commit": _commit(),
            "quick": args.quick, "categories": args.category, "partial": partial}


def write(outcomes, cases, args, seconds, partial=False) -> list:
    """Write fuzz.json and fuzz.md; returns the failing runs."""
    meta = _meta(outcomes, cases, args, seconds, partial)
    table = summarize(outcomes, cases)
    expect = {c.id: (c.expect, c.finding, c.note) for c in cases}
    failures = [dict(asdict(o), failures=o.failures(), expect=expect[o.case][0], finding=expect[o.case][1],
                     note=expect[o.case][2]) for o in outcomes if o.failures()]
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "fuzz.json").write_text(json.dumps({"meta": meta, "table": table, "failures": failures},
                                                       indent=1, default=str) + "\n")
    (args.results / "fuzz.md").write_text(markdown(table, meta))
    return failures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.fuzz", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the fast slice of tests/test_hostile.py")
    parser.add_argument("--category", nargs="*", help="only these categories")
    parser.add_argument("--compose-max", type=int, default=40, help="file cases also composed (default 40)")
    parser.add_argument("--timeout", type=float, default=hostile.TIMEOUT)
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder (its path is printed)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args([] if argv is None else argv)

    cases = hostile.slice_cases() if args.quick else hostile.all_cases()
    if args.category:
        cases = [c for c in cases if c.category in args.category]
    work = Path(tempfile.mkdtemp(prefix="rigmix-fuzz-"))
    ws = hostile.Workspace(work)
    print(f"fuzz: {len(cases)} cases in {work}", flush=True)
    t0 = time.perf_counter()
    outcomes, readable = [], []

    def record(o):
        outcomes.append(o)
        if len(outcomes) % 50 == 0:  # a checkpoint: an interrupted run still leaves its table
            write(outcomes, cases, args, time.perf_counter() - t0, partial=True)
        fails = o.failures()
        mark = "ok  " if not fails else "FAIL"
        print(f"{mark} {o.case} [{o.command}] rc={o.rc} {o.seconds:.1f}s {o.peak_rss_mb:.0f}MB"
              + (f": {'; '.join(fails)}" if fails else ""), flush=True)
        return o

    for case in cases:
        if case.kind == "config":
            record(hostile.execute(case, ws, "compose", timeout=args.timeout))
            continue
        o = record(hostile.execute(case, ws, "inspect", timeout=args.timeout))
        if o.rc == 0:
            record(hostile.execute(case, ws, "convert", timeout=args.timeout))
            if not case.special:
                readable.append(case)
    for case in _pick_compose(readable, args.compose_max):
        record(hostile.execute(case, ws, "compose", timeout=args.timeout))
    failures = write(outcomes, cases, args, time.perf_counter() - t0)
    print(markdown(summarize(outcomes, cases), _meta(outcomes, cases, args, time.perf_counter() - t0)))
    print(f"wrote {args.results / 'fuzz.md'} and fuzz.json; {len(failures)} failing runs")
    if args.keep:
        print(f"kept {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if not failures else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
