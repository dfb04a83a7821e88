"""Helpers shared by the benchmarks (not a benchmark: ``benchmarks.run`` skips this module)."""

from __future__ import annotations

import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def median_seconds(fn, repeats: int = 3) -> float:
    """Median wall-clock seconds of ``repeats`` calls of ``fn()``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


# --------------------------------------------------------------------------- the reference operation

#: Query points of the reference operation (uniform in the mesh's bounding box, fixed seed).
REFERENCE_POINTS = 1_000_000
REFERENCE_SEED = 0
#: Timed calls of the reference operation; their median is the reference.
REFERENCE_REPEATS = 3


def git_commit(root: Path = ROOT) -> str:
    """Short commit of the checkout at ``root`` (``"unknown"`` without git)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def reference_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The shared Horse (``$RIGMIX_ASSETS``, as the tests find it), every mesh as stored, subdivided to
    about 80k faces: one midpoint subdivision (each triangle into 4), then two barycentric ones (each
    into 3), 2,182 x 36 = 78,552 faces.

    Returns
    -------
    V : (n, 3) float64
    F : (m, 3) int64
        An unwelded triangle soup (the file's meshes concatenated).

    Raises
    ------
    FileNotFoundError
        The Horse is not in ``$RIGMIX_ASSETS``.
    """
    import igl

    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import ASSETS, CHARACTERS

    from rigmix.io.gltf import read_gltf

    path = ASSETS / CHARACTERS["Horse"]
    if not path.is_file():
        raise FileNotFoundError(f"reference operation: {path} missing (set RIGMIX_ASSETS to the shared characters)")
    quiet = logging.getLogger("rigmix")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # the file's repaired defects: noise here
    try:
        meshes = read_gltf(path).meshes
    finally:
        quiet.setLevel(level)
    offsets = np.cumsum([0] + [len(m.positions) for m in meshes[:-1]])
    V = np.concatenate([m.positions for m in meshes]).astype(np.float64)
    F = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]).astype(np.int64)
    V, F = igl.upsample(V, F)
    for _ in range(2):
        V, F = igl.false_barycentric_subdivision(V, F)
    return np.ascontiguousarray(V), np.ascontiguousarray(F)


def reference_operation(repeats: int = REFERENCE_REPEATS) -> dict:
    """Time the reference operation of issue 26: libigl's fast winding number
    (``igl.fast_winding_number``, its tree built in the call) of :data:`REFERENCE_POINTS` random
    points against :func:`reference_mesh`, with libigl's default threads.

    Divide a timing by ``seconds`` to compare runs on idle and loaded machines: both slow down
    alike under load.

    Returns
    -------
    dict
        ``seconds`` (the median of ``repeats`` calls), ``runs`` (each call's seconds), ``faces``,
        ``points``, ``commit``, ``machine``, ``cpus``, ``load_average`` (1, 5, 15 min, before the
        calls) and ``date`` (UTC).
    """
    import igl

    V, F = reference_mesh()
    lo, hi = V.min(axis=0), V.max(axis=0)
    Q = np.random.default_rng(REFERENCE_SEED).uniform(lo, hi, size=(REFERENCE_POINTS, 3))
    load = [round(x, 2) for x in os.getloadavg()]
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        igl.fast_winding_number(V, F, Q)
        runs.append(round(time.perf_counter() - t0, 4))
    return {"operation": f"igl.fast_winding_number, {REFERENCE_POINTS} random points (seed {REFERENCE_SEED}), "
                         f"Horse subdivided to {len(F)} faces",
            "seconds": round(float(np.median(runs)), 4), "runs": runs, "faces": int(len(F)),
            "points": REFERENCE_POINTS, "commit": git_commit(), "machine": platform.platform(),
            "cpus": os.cpu_count(), "load_average": load,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def ratio(seconds, reference_seconds) -> float | None:
    """``seconds`` as a multiple of the reference operation's (None when either is missing)."""
    if seconds is None or not reference_seconds:
        return None
    return round(float(seconds) / float(reference_seconds), 3)
