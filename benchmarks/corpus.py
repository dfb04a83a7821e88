"""`make corpus`: every composition of the matrix over the 27 characters, through the gates.

The matrix (:mod:`benchmarks.corpus_matrix`: :func:`generate_matrix`, :func:`ci_slice`) is
generated from the limb classifier; its configs are written to ``out/corpus/configs/``. Each case
runs as ``rigmix compose CONFIG -o out/corpus/glb/NAME.glb --report out/corpus/reports/NAME.json
--no-progress`` in a subprocess (its own process group, killed at ``--timeout``, default 120 s),
one at a time unless ``--jobs N``.

A row per case records the exit status, the last line of stderr, the wall time, the report's
per-stage ``timings``, its ``mesh``, ``quality`` and ``weights`` figures, and the gates, each
``{name, value, op, bound, pass}`` (and ``note``), as :mod:`rigmix.gates` writes them:

* ``exit_status`` (0) and ``process_seconds`` (the whole command, at most :data:`TIME_BOUND`, 60 s),
  measured here;
* ``blender_roundtrip_error`` (issue 25): the output imported into Blender and evaluated at rest
  and at :data:`BLENDER_FRAMES` frames of every clip (:func:`rigmix.io.blender_check.blender_roundtrip`),
  its largest vertex distance from rigmix's own skinning of the file over the diagonal, at most
  :data:`BLENDER_BOUND`; a machine without Blender fails it (``make`` installs Debian's), and
  ``--no-blender`` leaves it out. The row's ``blender_s`` is the round trip's seconds, outside the
  time gate (it is not the composition's);
* the report's ``gates`` (:mod:`rigmix.gates`) when it has them; otherwise (FALLBACK, marked
  ``gates_source = "fallback"`` in the row and the table) the same gates derived here from the
  report, the Khronos validator run on the output and the input clip counts
  (:func:`fallback_gates`); the identity gates then stay unmeasured (``pass`` null). A report gate
  named like a runner gate is left out (the runner's is kept).

A case passes when every gate passes. Results: ``benchmarks/results/corpus.json`` (every row, one
a line, each gate packed as a list of :data:`GATE_FIELDS`; :func:`load_rows` reads it back) and
``corpus.md`` (the pass rate by kind, the median time per stage, the failures with their failing
gates and message, one row per case with each gate and the time per stage), both rewritten after
every case.

The reference operation (issue 26, :func:`benchmarks.common.reference_operation`: libigl's fast
winding number of 1M points against the Horse subdivided to 78,552 faces) is timed once before a
run's first case; ``corpus.json`` keeps it (``reference``) and each row run then its seconds
(``reference_s``), and ``corpus.md`` gives every median also as a multiple of it, so runs on idle
and loaded machines compare. A row from a run that did not time it is divided by the stored
``reference`` (the table says so). ``--tables`` rewrites both files from the stored rows with the
reference timed now, composing nothing.

Resuming: a row whose config text is unchanged (SHA-256) is kept and its case skipped (unless it
lacks the Blender gate and the run measures it);
``--fresh`` runs everything again, ``--rerun-failed`` the cases that did not pass. Slices:
``--only PATTERN`` (shell pattern on the case name, or a substring), ``--kind KIND``,
``--limit N`` (the first N of the selection left to run), ``--ci`` (the CI slice).

Usage: ``python -m benchmarks.corpus [--fresh] [--rerun-failed] [--only PATTERN] [--kind KIND]
[--limit N] [--ci] [--jobs N] [--timeout S] [--no-blender] [--out DIR] [--results DIR] [--list]
[--tables]``.
Exit status 0 when every row passes, 1 otherwise, 2 when the characters are missing.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import logging
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from benchmarks.common import git_commit, ratio, reference_operation
from benchmarks.corpus_matrix import (
    ASSETS,
    CORPUS,
    KINDS,
    Case,
    character_files,
    ci_slice,
    generate_matrix,
    load_subjects,
    write_configs,
)

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
SCRATCH = ROOT / "out" / "corpus"

__all__ = ["Case", "KINDS", "generate_matrix", "ci_slice", "run_case", "report_gates", "fallback_gates", "select",
           "main"]

#: seconds a composition may take, interpreter start-up included (the ``process_seconds`` gate)
TIME_BOUND = 60.0
#: seconds before a composition is killed
DEFAULT_TIMEOUT = 120.0
#: the report's figures a row keeps
REPORT_FIGURES = ("timings", "mesh", "quality", "weights")
#: the stages of the time table, in pipeline order (then any other the rows have)
STAGES = ("load", "operations", "mapping", "fusion", "weights", "completion", "assembly", "quality", "total",
          "write", "gates")
#: a weight row sums to 1 within this (float32 in the file)
SUM_TOLERANCE = 1e-3
#: Blender's deformed output may depart from rigmix's skinning by this much of the diagonal (issue 25)
BLENDER_BOUND = 1e-3
#: frames of each clip the Blender round trip compares (evenly spaced, :func:`rigmix.io.blender_check.sample_times`)
BLENDER_FRAMES = 8
#: the gate the Blender round trip writes
BLENDER_GATE = "blender_roundtrip_error"


# --------------------------------------------------------------------------- gates


def gate(name: str, value, op: str, bound, ok, note: str | None = None) -> dict:
    """One gate as the report writes it: ``{name, value, op, bound, pass}`` (and ``note``); ``pass``
    null: not measured."""
    out = {"name": name, "value": value, "op": op, "bound": bound, "pass": ok}
    if note:
        out["note"] = note
    return out


def measured(name: str, value, op: str, bound, note: str | None = None) -> dict:
    """The gate ``value op bound`` (``op`` ``"<="`` or ``">="``); null value: not measured."""
    ok = None if value is None else (value <= bound if op == "<=" else value >= bound)
    return gate(name, value, op, bound, ok, note)


def runner_gates(rc, wall: float) -> list[dict]:
    """The gates measured around the subprocess: exit status 0, and the whole command (interpreter
    start-up included) within :data:`TIME_BOUND` seconds."""
    return [gate("exit_status", rc, "==", 0, rc == 0),
            measured("process_seconds", round(wall, 2), "<=", TIME_BOUND)]


def fallback_gates(report: dict, glb: Path, input_clips: int, identity: bool) -> list[dict]:
    """FALLBACK while the report carries no ``gates`` (:mod:`rigmix.gates`): the issue's gates as far
    as the report, the Khronos validator on ``glb`` and the count of distinct input clips tell them.

    Parameters
    ----------
    report : dict
        ``rigmix compose --report`` JSON.
    glb : Path
        The composed file.
    input_clips : int
        Distinct clips of the input files (a file listed under two ids counts once).
    identity : bool
        Whether the case is an identity composition; its gates need the composition, not the
        report: listed, not measured (``pass`` null).

    Returns
    -------
    list of dict
        Named as :mod:`rigmix.gates` names them, except ``weights_sum_error`` (the report's
        largest distance of a weight sum from 1, in place of the count of unnormalized vertices;
        negative weights are not seen here); ``clips_missing`` compares counts of clips only.
    """
    mesh, quality, weights = report.get("mesh", {}), report.get("quality", {}), report.get("weights", {})
    out = []
    try:
        from rigmix.io.validator import validate_gltf

        issues = validate_gltf(glb)["issues"]
        codes = list(dict.fromkeys(m.get("code") for m in issues.get("messages", []) if m.get("severity") == 0))
        out.append(measured("validator_errors", int(issues["numErrors"]), "<=", 0, ", ".join(codes[:3])))
    except Exception as exc:  # no validator on this machine, or it failed on the file: not measured
        out.append(gate("validator_errors", None, "<=", 0, None, str(exc)))
    for key in ("junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges",
                "junction_self_intersections"):
        out.append(measured(key, mesh.get(key), "<=", 0))
    angle = mesh.get("junction_min_angle_p05")
    out.append(measured("junction_min_angle_p05", angle, ">=", 20.0) if angle is not None
               else gate("junction_min_angle_p05", None, ">=", 20.0, True, "no junction triangle generated"))
    stretch = quality.get("junction_stretch_ratio")  # null passes only where no input has a clip
    out.append(measured("junction_stretch_ratio", stretch, "<=", 1.5) if stretch is not None
               else gate("junction_stretch_ratio", None, "<=", 1.5, input_clips == 0, "not measured"))
    if "min_sum" in weights:
        dev = max(abs(weights["min_sum"] - 1.0), abs(weights["max_sum"] - 1.0))
        out.append(measured("weights_sum_error", dev, "<=", SUM_TOLERANCE))
    out.append(measured("weights_max_influences", weights.get("max_influences"), "<=", 4))
    clips = len(report.get("animation", {}).get("clips", []))
    out.append(measured("clips_missing", max(0, input_clips - clips), "<=", 0))
    if identity:
        out += [gate(n, None, "<=", 0.005, None, "fallback: not measured")
                for n in ("identity_surface_error", "identity_skinned_error")]
    return out


def blender_gate(glb: Path, *, timeout: float) -> tuple[dict, float]:
    """The ``blender_roundtrip_error`` gate of the composed file ``glb`` (module docstring) and the
    round trip's seconds; a failing import or a missing Blender fails it, with the reason as note."""
    from rigmix.errors import RigmixError
    from rigmix.io.blender_check import blender_roundtrip

    t0 = time.perf_counter()
    try:
        rt = blender_roundtrip(glb, frames=BLENDER_FRAMES, timeout=timeout)
    except RigmixError as exc:  # no Blender, or it failed on the file
        return gate(BLENDER_GATE, None, "<=", BLENDER_BOUND, False, _last_line(str(exc))), time.perf_counter() - t0
    worst = max(rt.clip_errors, key=rt.clip_errors.get) if rt.clip_errors else None
    note = f"rest {rt.rest_error:.2g}" + (f", worst clip {worst!r}" if worst is not None else "")
    return (measured(BLENDER_GATE, float(f"{rt.error:.4g}"), "<=", BLENDER_BOUND, note),
            time.perf_counter() - t0)


def report_gates(report: dict, glb: Path, case: Case) -> tuple[str, list[dict]]:
    """``("report", report["gates"])`` when the report has them, else ``("fallback",``
    :func:`fallback_gates` ``)``."""
    if isinstance(report.get("gates"), list):
        return "report", list(report["gates"])
    return "fallback", fallback_gates(report, glb, _input_clips(case), case.kind == "identity")


def failed_gates(gates: list[dict]) -> list[dict]:
    return [g for g in gates if g["pass"] is False]


# --------------------------------------------------------------------------- one case


def _last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1].strip() if lines else ""


def _env(threads: int | None = None) -> dict:
    """The compositions' environment: the asset folders, and with ``threads`` the numerical
    libraries' thread count (``--jobs N`` compositions at once share the cores out, as the
    batch's workers do: :data:`rigmix.batch.THREAD_VARIABLES`)."""
    from rigmix.batch import THREAD_VARIABLES

    env = dict(os.environ)
    env.setdefault("RIGMIX_ASSETS", str(ASSETS))
    env.setdefault("RIGMIX_CORPUS", str(CORPUS))
    if threads is not None:
        env.update({name: str(max(1, int(threads))) for name in THREAD_VARIABLES})
    return env


def _input_clips(case: Case) -> int:
    """Distinct clips of the case's input files (each file once)."""
    from rigmix.io import load_character

    files = character_files()
    return sum(len(load_character(files[n][1]).clips) for n in case.characters)


def run_case(case: Case, config: Path, scratch: Path, *, timeout: float = DEFAULT_TIMEOUT,
             blender: bool = True, threads: int | None = None) -> dict:
    """Compose one case in a subprocess and return its row (see the module docstring); with
    ``blender``, a composed file also goes through the Blender round trip (:func:`blender_gate`,
    killed after ``timeout`` seconds too); ``threads``: the composition's numerical threads
    (:func:`_env`; default: the libraries' own, one per core)."""
    glb = scratch / "glb" / f"{case.name}.glb"
    report_path = scratch / "reports" / f"{case.name}.json"
    for p in (glb, report_path):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "rigmix.cli", "compose", str(config), "-o", str(glb), "--report",
           str(report_path), "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(threads),
                            cwd=ROOT, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # its own session: the compose and anything it started
        _, err = proc.communicate()
        rc = None
    wall = time.perf_counter() - t0
    row = {"name": case.name, "kind": case.kind, "characters": list(case.characters), "config_sha": case.sha,
           "rc": rc, "timed_out": rc is None, "stderr_last": _last_line(err) if rc is not None
           else f"killed after {timeout:g} s", "wall_s": round(wall, 2)}
    gates = runner_gates(rc, wall)
    report = json.loads(report_path.read_text()) if rc == 0 and report_path.is_file() else None
    if rc == 0 and report is None:
        gates.append(gate("report_written", 0, "==", 1, False, "exit 0 without a report"))
    if report is not None:
        for key in REPORT_FIGURES:
            row[key] = report.get(key)
        row["gates_source"], more = report_gates(report, glb, case)
        gates += [g for g in more if g.get("name") not in {x["name"] for x in gates}]
    if blender and rc == 0 and glb.is_file():
        g, seconds = blender_gate(glb, timeout=timeout)
        gates.append(g)
        row["blender_s"] = round(seconds, 2)
    row["gates"] = gates
    failed = failed_gates(gates)
    row["failed"] = [g["name"] for g in failed]
    row["passed"] = not failed
    row["message"] = failure_message(row, failed)
    return row


def _fmt(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def failure_message(row: dict, failed: list[dict]) -> str:
    """What a failed row says: the last line of stderr when the command failed, else each failed gate
    with its value, bound and note."""
    if row["rc"] != 0:
        return row["stderr_last"] or f"exit status {row['rc']}"
    parts = []
    for g in failed:
        note = f" [{g['note']}]" if g.get("note") else ""
        parts.append(f"{g['name']} = {_fmt(g['value'])} (needs {g.get('op', '<=')} {_fmt(g['bound'])}){note}")
    return "; ".join(parts)


# --------------------------------------------------------------------------- selection and resume


def select(cases, *, only=None, kind=None, ci=False) -> list[Case]:
    """The cases matching ``only`` (shell patterns or substrings, separated by commas: a case
    matching any of them), ``kind`` and the CI slice."""
    if ci:
        cases = ci_slice(cases)
    if kind:
        cases = [c for c in cases if c.kind == kind]
    if only:
        patterns = [p for p in only.split(",") if p]

        def matches(name, p):
            return fnmatch.fnmatchcase(name, p) if any(ch in p for ch in "*?[") else p in name

        cases = [c for c in cases if any(matches(c.name, p) for p in patterns)]
    return list(cases)


def to_run(cases, rows: dict, *, fresh=False, rerun_failed=False, blender=False) -> list[Case]:
    """The cases whose row is missing, or stale (its config changed; with ``blender``, a composed
    row without the Blender gate), or asked for again."""
    out = []
    for c in cases:
        row = rows.get(c.name)
        unmeasured = (blender and row is not None and row.get("rc") == 0
                      and BLENDER_GATE not in {g["name"] for g in row.get("gates", [])})
        if (fresh or row is None or row.get("config_sha") != c.sha or unmeasured
                or (rerun_failed and not row.get("passed"))):
            out.append(c)
    return out


#: A gate as ``corpus.json`` stores it: a list of these values (``note`` left off when absent), so
#: that 19 gates of 358 rows stay small in the repository.
GATE_FIELDS = ("name", "value", "op", "bound", "pass", "note")


def pack_gate(gate: dict) -> list:
    """A gate dict as the list ``corpus.json`` stores (:data:`GATE_FIELDS`)."""
    values = [gate.get(k) for k in GATE_FIELDS]
    return values[:-1] if values[-1] is None else values


def unpack_gate(values) -> dict:
    """The gate dict of a stored list (or of a dict, as older files stored it)."""
    if isinstance(values, dict):
        return dict(values)
    return dict(zip(GATE_FIELDS, values))


def load_rows(path: Path) -> dict:
    """name -> row of a previous run (empty when there is none), its gates as dicts."""
    if not path.is_file():
        return {}
    return {r["name"]: {**r, "gates": [unpack_gate(g) for g in r.get("gates", [])]}
            for r in json.loads(path.read_text()).get("rows", [])}


def load_reference(path: Path) -> dict | None:
    """The reference operation stored with ``corpus.json`` (:func:`benchmarks.common.reference_operation`),
    or None."""
    if not path.is_file():
        return None
    return json.loads(path.read_text()).get("reference")


# --------------------------------------------------------------------------- tables


def summary(cases, rows: dict) -> list[dict]:
    """Pass rate by kind (and a TOTAL row): cases in the matrix, run, passed."""
    out = []
    for kind in list(KINDS) + ["TOTAL"]:
        mine = [c for c in cases if kind == "TOTAL" or c.kind == kind]
        run = [rows[c.name] for c in mine if c.name in rows]
        passed = sum(1 for r in run if r.get("passed"))
        out.append({"kind": kind, "cases": len(mine), "run": len(run), "passed": passed,
                    "pass_rate": round(passed / len(run), 4) if run else None})
    return out


def stage_times(rows, reference: dict | None) -> list[dict]:
    """Per stage (:data:`STAGES`, then ``process``: the row's ``wall_s``), over the rows with
    timings, passing or failing: the count, the median and largest seconds, and the median and
    largest multiple of the reference operation (each row divided by its run's ``reference_s``,
    else by ``reference["seconds"]``; None without either)."""
    timed = [r for r in rows if r.get("timings")]
    names = list(STAGES) + [k for r in timed for k in r["timings"] if k not in STAGES]
    out = []
    for name in list(dict.fromkeys(names)) + ["process"]:
        secs, mult = [], []
        for r in timed:
            v = r.get("wall_s") if name == "process" else r["timings"].get(name)
            if v is None:
                continue
            secs.append(float(v))
            mult.append(ratio(v, r.get("reference_s") or (reference or {}).get("seconds")))
        if not secs:
            continue
        known = [m for m in mult if m is not None]
        out.append({"stage": name, "rows": len(secs), "median_s": round(float(np.median(secs)), 3),
                    "max_s": round(max(secs), 3),
                    "median_ratio": round(float(np.median(known)), 3) if len(known) == len(mult) else None,
                    "max_ratio": round(max(known), 3) if len(known) == len(mult) else None})
    return out


def reference_lines(rows, reference: dict | None) -> list[str]:
    """What the ratios of the time table are divided by: the reference of each row's run, or the
    stored one (named with its commit, machine, date and load)."""
    own = sum(1 for r in rows if r.get("reference_s"))
    lines = []
    if reference:
        lines.append(f"Reference operation: {reference['operation']}; median of {len(reference['runs'])} calls "
                     f"{reference['seconds']:.2f} s, measured on commit {reference['commit']}, {reference['machine']}, "
                     f"{reference['cpus']} CPUs, {reference['date']}, load average {reference['load_average'][0]:g} "
                     "before it.")
    if own:
        lines.append(f"{own} rows are divided by the reference timed in their own run (`reference_s`).")
    if own < len(rows):
        commits = ", ".join(sorted({r.get("commit", "?") for r in rows if not r.get("reference_s")}))
        lines.append(f"{len(rows) - own} rows (commit(s) {commits}) come from runs that did not time it: they "
                     "are divided by the reference above, measured when these tables were written, **not in "
                     "their run** (their machine and load may differ)." if reference else
                     f"{len(rows) - own} rows have no reference: no ratio.")
    return lines


def _cell(g: dict) -> str:
    mark = {True: "✓", False: "✗", None: "·"}[g["pass"]]
    return f"{mark} {_fmt(g['value'])}"


def markdown(cases, rows: dict, *, timeout: float, reference: dict | None = None) -> str:
    """``corpus.md``: header, pass rate by kind, time per stage, failing gates, failures, every row."""
    ordered = [rows[c.name] for c in cases if c.name in rows]
    fallback = sum(1 for r in ordered if r.get("gates_source") == "fallback")
    commits = sorted({r.get("commit", "?") for r in ordered})
    lines = ["# Composition matrix over the corpus (`make corpus`)", "",
             f"{len(cases)} generated compositions over {len({n for c in cases for n in c.characters})} characters, "
             f"{len(ordered)} run; commit(s) {', '.join(commits) or '-'}; timeout {timeout:g} s per composition, "
             f"time gate {TIME_BOUND:g} s. A case passes when every gate passes (✓ pass, ✗ fail, · not measured).",
             ""]
    if fallback:
        lines += [f"**FALLBACK gates** in {fallback} rows (`gates_source = fallback`): the report had no `gates`, "
                  "so they were derived by `benchmarks/corpus.py` from the report, the Khronos validator and the "
                  "input clip counts; the identity gates are not measured there (an identity case may pass without "
                  "them).", ""]
    lines += ["## Pass rate by kind", "", "| kind | cases | run | passed | pass rate |", "|---|---:|---:|---:|---:|"]
    for s in summary(cases, rows):
        rate = "-" if s["pass_rate"] is None else f"{100 * s['pass_rate']:.1f} %"
        lines.append(f"| {s['kind']} | {s['cases']} | {s['run']} | {s['passed']} | {rate} |")
    timed = [r for r in ordered if r.get("timings")]
    lines += ["", "## Time per stage", "",
              f"Over the {len(timed)} rows with timings, passing and failing: seconds, and multiples of the "
              "reference operation (`x ref`; each row's seconds divided by its reference, then the median or "
              "largest). `process`: the whole `rigmix compose` command, interpreter start-up included.", ""]
    lines += reference_lines(timed, reference)
    lines += ["", "| stage | rows | median s | median x ref | max s | max x ref |", "|---|---:|---:|---:|---:|---:|"]
    for t in stage_times(timed, reference):
        lines.append(f"| {t['stage']} | {t['rows']} | {t['median_s']:.2f} | {_fmt(t['median_ratio'])} | "
                     f"{t['max_s']:.2f} | {_fmt(t['max_ratio'])} |")
    counts: dict[str, int] = {}
    for r in ordered:
        for name in r.get("failed", []):
            counts[name] = counts.get(name, 0) + 1
    lines += ["", "## Failing gates", "", "| gate | failing cases |", "|---|---:|"]
    lines += [f"| {n} | {k} |" for n, k in sorted(counts.items(), key=lambda x: (-x[1], x[0]))] or ["| none | 0 |"]
    failures = [r for r in ordered if not r.get("passed")]
    lines += ["", f"## Failures ({len(failures)})", "",
              "| case | kind | failing gates | message |", "|---|---|---|---|"]
    for r in failures:
        msg = r.get("message", "").replace("|", "\\|")
        lines.append(f"| {r['name']} | {r['kind']} | {', '.join(r.get('failed', []))} | {msg} |")
    gate_names = list(dict.fromkeys(g["name"] for r in ordered for g in r.get("gates", [])))
    stages = list(dict.fromkeys(k for r in ordered for k in (r.get("timings") or {})))
    lines += ["", "## Every composition", "", "Gates (value and mark), then seconds per stage.", "",
              "| case | kind | result | gates | " + " | ".join(gate_names + stages) + " |",
              "|---|---|---|---|" + "---:|" * (len(gate_names) + len(stages))]
    for r in ordered:
        by_name = {g["name"]: g for g in r.get("gates", [])}
        cells = [_cell(by_name[n]) if n in by_name else "" for n in gate_names]
        timings = r.get("timings") or {}
        times = [_fmt(timings[s]) if s in timings else "" for s in stages]
        result = "pass" if r.get("passed") else ("timeout" if r.get("timed_out") else "FAIL")
        lines.append(f"| {r['name']} | {r['kind']} | {result} | {r.get('gates_source', '-')} | "
                     + " | ".join(cells + times) + " |")
    return "\n".join(lines) + "\n"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_results(cases, rows: dict, results: Path, *, timeout: float, reference: dict | None = None) -> None:
    """``corpus.json`` (rows of the current matrix, in its order, and the ``reference`` operation)
    and ``corpus.md``."""
    results.mkdir(parents=True, exist_ok=True)
    ordered = [rows[c.name] for c in cases if c.name in rows]
    head = json.dumps({"cases": len(cases), "by_kind": {k: sum(1 for c in cases if c.kind == k) for k in KINDS},
                       "ci_slice": [c.name for c in ci_slice(cases)], "timeout_s": timeout,
                       "time_bound_s": TIME_BOUND, "summary": summary(cases, rows), "reference": reference},
                      separators=(",", ":"))
    # one row a line, gates packed (:func:`pack_gate`): readable in a diff, small in the repository
    packed = [json.dumps({**r, "gates": [pack_gate(g) for g in r.get("gates", [])]}, separators=(",", ":"))
              for r in ordered]
    _atomic_write(results / "corpus.json", head[:-1] + ',"rows":[\n' + ",\n".join(packed) + "\n]}\n")
    _atomic_write(results / "corpus.md", markdown(cases, rows, timeout=timeout, reference=reference))


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.corpus", description=__doc__.split("\n\n")[0])
    ap.add_argument("--fresh", action="store_true", help="run every selected case again")
    ap.add_argument("--rerun-failed", action="store_true", help="run again the selected cases that did not pass")
    ap.add_argument("--only", metavar="PATTERN",
                    help="case names matching a shell pattern (or containing it); several separated by commas")
    ap.add_argument("--kind", choices=KINDS, help="one kind of composition")
    ap.add_argument("--ci", action="store_true", help="the fixed CI slice only")
    ap.add_argument("--limit", type=int, metavar="N", help="run at most N cases")
    ap.add_argument("--jobs", type=int, default=1, metavar="N", help="compositions at once (default 1)")
    ap.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, metavar="S",
                    help=f"seconds before a composition is killed (default {DEFAULT_TIMEOUT:g})")
    ap.add_argument("--no-blender", action="store_true", help="leave out the Blender round trip of each output")
    ap.add_argument("--out", type=Path, default=SCRATCH, help="configs, GLBs and reports (default out/corpus)")
    ap.add_argument("--results", type=Path, default=RESULTS, help="corpus.json and corpus.md (default "
                                                                    "benchmarks/results)")
    ap.add_argument("--list", action="store_true", help="print the selected cases and exit")
    ap.add_argument("--tables", action="store_true", help="time the reference operation and rewrite corpus.json "
                                                           "and corpus.md from the stored rows; compose nothing")
    args = ap.parse_args(argv)

    from rigmix.errors import InputError

    logging.getLogger("rigmix").setLevel(logging.ERROR)  # the inputs' repaired defects, once per file: noise here
    try:
        cases = generate_matrix(load_subjects())
    except InputError as exc:
        print(f"corpus: {exc}", file=sys.stderr)
        return 2
    chosen = select(cases, only=args.only, kind=args.kind, ci=args.ci)
    if args.list:
        for c in chosen:
            print(f"{c.kind:10s} {c.name}")
        return 0
    configs = write_configs(cases, args.out / "configs")
    results_json = args.results / "corpus.json"
    rows = load_rows(results_json)
    pending = to_run(chosen, rows, fresh=args.fresh, rerun_failed=args.rerun_failed, blender=not args.no_blender)
    if args.limit is not None:
        pending = pending[:args.limit]
    if args.tables:
        pending = []
    print(f"corpus: {len(cases)} cases, {len(chosen)} selected, {len(chosen) - len(pending)} kept from "
          f"{results_json}, {len(pending)} to run", flush=True)
    reference = load_reference(results_json)
    if pending or args.tables:  # timed in this run, before its first composition
        reference = reference_operation()
        print(f"corpus: reference operation {reference['seconds']:.2f} s ({reference['operation']})", flush=True)
    commit = git_commit()
    jobs = max(1, args.jobs)
    threads = max(1, (os.cpu_count() or 1) // jobs) if jobs > 1 else None
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(run_case, c, configs[c.name], args.out, timeout=args.timeout,
                               blender=not args.no_blender, threads=threads): c for c in pending}
        for i, fut in enumerate(as_completed(futures), 1):
            row = fut.result()
            row["commit"] = commit
            row["reference_s"] = reference["seconds"]
            rows[row["name"]] = row
            write_results(cases, rows, args.results, timeout=args.timeout, reference=reference)
            verdict = "pass" if row["passed"] else f"FAIL {row['message']}"
            print(f"[{i}/{len(pending)}] {row['name']}: {row['wall_s']} s {verdict}", flush=True)
    write_results(cases, rows, args.results, timeout=args.timeout, reference=reference)
    done = [rows[c.name] for c in chosen if c.name in rows]
    passed = sum(1 for r in done if r.get("passed"))
    print(f"corpus: {passed}/{len(done)} selected cases pass; {args.results / 'corpus.md'}")
    return 0 if passed == len(done) else 1


if __name__ == "__main__":
    sys.exit(main())
