"""`rigmix compose` end to end on every config of tests/configs: GLB, report, weights, validator.

Each config is composed once, in a child process (``python -m rigmix.cli compose``,
address space capped at ``MEMORY_CAP`` bytes: a native crash or a runaway allocation in one
config fails that config, not the session), and one test per config makes every check on that
run (under ``pytest -n 2`` a config is never composed twice). Issue 4's fusion figures are
asserted per config; a config on which the fusion does not deliver one is listed in
``FUSION_SHORTFALLS`` with the figure, so that a regression and a known shortfall read differently.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from conftest import ROOT, asset, require

from rigmix.cli import main

CONFIGS = sorted((ROOT / "tests" / "configs").glob("*.toml"))
MEMORY_CAP = 12 * 2**30
ASSETS_OF = {
    "centaur": ["Horse", "Knight"], "fox_arm": ["CesiumMan", "Fox"], "limb_swap": ["CesiumMan", "RiggedFigure"],
    "self_composition": ["CesiumMan"], "tail_graft": ["CesiumMan", "Velociraptor"],
    "three_characters": ["Knight", "Fox", "CesiumMan"], "knight_arm": ["CesiumMan", "Knight"],
}
#: Configs whose output is imported into Blender (rigmix.io.blender_check): those that mix armature
#: scales of 100 and 1 (the Knight or the Velociraptor with CesiumMan). Before the output skeleton
#: had unit scale, Blender put their vertices 1.7, 13.4 and 0.69 diagonals away from rigmix's.
BLENDER_CONFIGS = ("knight_arm", "tail_graft", "three_characters")
#: Blender's deformed mesh against rigmix's skinning, over the diagonal (issue 25: 0.1%).
BLENDER_TOLERANCE = 1e-3
#: Clip fidelity bound over the diagonal (issue 25), and the world rest scale tolerance.
FIDELITY_TOLERANCE = 1e-4
SCALE_TOLERANCE = 1e-6
REPORT_KEYS = {
    "timings": ["total", "fusion", "weights", "completion", "assembly"],
    "mesh": ["vertices", "faces", "non_manifold_edges", "junction_boundary_edges", "junction_min_angle_p05",
             "junction_faces", "junction_self_intersections", "grafted_visible", "grafted_visible_min",
             "junction_dihedral_p95", "source_dihedral_p95", "junction_dihedral_ratio"],
    "fields": ["voxel_size", "voxels", "backend"],
    "weights": ["method", "max_influences", "min_sum", "max_sum", "junction_vertices"],
    "quality": ["junction_stretch_ratio", "junction_weight_roughness_p99", "junction_weight_roughness_max",
                "source_weight_roughness_p99", "source_weight_roughness_max"],
}
#: (config, figure) pairs the fusion does not meet yet, reported to the fusion issue; empty when all pass.
FUSION_SHORTFALLS: set = set()

_RUNS: dict = {}


def _compose(cfg: Path, out: Path):
    """Run ``rigmix compose`` on ``cfg`` once per process; returns (status, glb, report, stderr tail)."""
    if cfg.stem not in _RUNS:
        for name in ASSETS_OF.get(cfg.stem, []):
            asset(name)
        glb, rep = out / f"{cfg.stem}.glb", out / f"{cfg.stem}.json"

        def cap():
            resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))

        extra = []
        if cfg.stem == "self_composition":  # the optional outputs, on the cheapest configs
            extra = ["--usd", str(out / "self_composition.usdc"), "--dump-fields", str(out / "fields")]
        if cfg.stem == "tail_graft":
            extra = ["--dump-fields", str(out / "fields")]
        res = subprocess.run([sys.executable, "-m", "rigmix.cli", "compose", str(cfg), "-o", str(glb),
                              "--report", str(rep), "--no-progress", *extra], cwd=ROOT, capture_output=True,
                             text=True, timeout=1200, preexec_fn=cap)
        _RUNS[cfg.stem] = (res.returncode, glb, rep, res.stderr[-2000:])
    status, glb, rep, err = _RUNS[cfg.stem]
    assert status == 0, f"rigmix compose {cfg.name} exited {status}: {err}"
    return status, glb, rep, err


def _read_accessor(g, blob, acc_index):
    acc = g.accessors[acc_index]
    bv = g.bufferViews[acc.bufferView]
    comp = {5126: np.float32, 5121: np.uint8, 5123: np.uint16}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    item = width * np.dtype(comp).itemsize
    start = (bv.byteOffset or 0) + (acc.byteOffset or 0)
    stride = bv.byteStride or item
    raw = np.frombuffer(blob, np.uint8, count=stride * (acc.count - 1) + item, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, (acc.count, item), (stride, 1))
    return np.ascontiguousarray(rows).view(comp).reshape(acc.count, width)


@pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: c.stem)
def test_rigmix_compose_end_to_end(cfg, tmp_path):
    """One composition per config (the expensive part), every check on it."""
    from rigmix.io.validator import validate_gltf, validator_available

    name = cfg.stem
    status, glb, rep, err = _compose(cfg, tmp_path)
    assert status == 0 and glb.is_file() and rep.is_file()

    if name == "self_composition":
        from pxr import Usd, UsdSkel

        stage = Usd.Stage.Open(str(tmp_path / "self_composition.usdc"))
        assert any(p.IsA(UsdSkel.Skeleton) for p in stage.Traverse())
        # a limb replaced by itself: the junction is copied, no field is computed, and the user is told
        assert not list((tmp_path / "fields").glob("*")) and "no junction field was computed" in err
    if name == "tail_graft":
        assert list((tmp_path / "fields").glob("*.npz")) or list((tmp_path / "fields").glob("*.vdb"))

    # the report
    report = json.loads(rep.read_text())
    for section, keys in REPORT_KEYS.items():
        for k in keys:
            assert k in report[section], f"{name}: report[{section!r}] lacks {k!r}"
    assert "animation" in report and report["animation"]["clips"]
    assert "scales" in report and "warnings" in report
    w = report["weights"]
    assert w["method"] == "dfd" and w["max_influences"] <= 4
    assert abs(w["min_sum"] - 1) < 1e-9 and abs(w["max_sum"] - 1) < 1e-9
    assert report["timings"]["total"] >= report["timings"]["fusion"] > 0

    # the GLB: Khronos validator, weights as written (float32)
    if validator_available():
        v = validate_gltf(glb)
        assert v["issues"]["numErrors"] == 0, f"{name}: {v['issues']['messages'][:5]}"
    g = pygltflib.GLTF2().load(str(glb))
    blob = g.binary_blob()
    njoints, seen = len(g.skins[0].joints), 0
    for mesh in g.meshes:
        for prim in mesh.primitives:
            if prim.attributes.WEIGHTS_0 is None:
                continue
            W = _read_accessor(g, blob, prim.attributes.WEIGHTS_0).astype(np.float64)
            J = _read_accessor(g, blob, prim.attributes.JOINTS_0)
            assert np.all(np.isfinite(W)) and np.all(W >= 0)
            assert np.allclose(W.sum(axis=1), 1.0, atol=2e-6)
            assert J.max() < njoints
            seen += len(W)
    assert seen >= report["mesh"]["vertices"]  # every fused vertex is skinned (split per mesh: >=)

    # issue 4's fusion figures; a known shortfall is reported as a warning, anything else fails
    mesh = report["mesh"]
    figures = {"junction_boundary_edges": mesh["junction_boundary_edges"] == 0,
               "new_non_manifold_edges": mesh["new_non_manifold_edges"] == 0,
               # None: no generated triangle (a junction copied from faces both inputs share)
               "junction_min_angle_p05": (mesh["junction_min_angle_p05"] >= 20.0
                                          if mesh["junction_min_angle_p05"] is not None
                                          else 0 < mesh["copied_faces"] == mesh["junction_faces"]),
               # issue 25: every grafted part shows; the junction creases no more than the inputs there
               # (None: a copied junction)
               "grafted_visible": mesh["grafted_visible_min"] is not None and mesh["grafted_visible_min"] >= 0.9,
               "junction_dihedral_ratio": (mesh["junction_dihedral_ratio"] <= 1.5
                                           if mesh["junction_dihedral_ratio"] is not None
                                           else 0 < mesh["copied_faces"] == mesh["junction_faces"])}
    assert mesh["junction_self_intersections"] == 0, mesh  # crossing faces are repaired (fusion/crossings.py)
    failed = [f for f, ok in figures.items() if not ok]
    unexpected = [f for f in failed if (name, f) not in FUSION_SHORTFALLS]
    assert not unexpected, f"{name}: fusion figures {[(f, mesh[f]) for f in unexpected]}"
    for f in failed:
        warnings.warn(f"{name}: known fusion shortfall {f} = {mesh[f]}", stacklevel=1)

    # issue 6 acceptance 3: the junction deforms like the sources (centaur, tail graft)
    if name in ("centaur", "tail_graft"):
        q = report["quality"]
        assert q["junction_stretch_ratio"] is not None and q["junction_stretch_ratio"] <= 1.5, q
    # no weight spike at the seam: no junction vertex departs from its neighbours more than the
    # artists' own sharpest painted transitions do (measured 2026-12-02, dfd: junction / sources
    # max 0.65 / 0.79 centaur, 0.61 / 0.72 fox_arm, 0.37 / 0.62 limb_swap, 0.19 / 0.61
    # self_composition, 0.51 / 0.70 tail_graft, 0.49 / 0.79 three_characters)
    q = report["quality"]
    assert q["junction_weight_roughness_max"] <= q["source_weight_roughness_max"], q

    # issue 25: a unit-scale skeleton (as written), every input's clips replayed by the joints it keeps
    from rigmix.io import load_character

    sk = load_character(glb).skeleton
    scales = np.linalg.norm(sk.rest_worlds()[:, :3, :3], axis=1)
    assert np.abs(scales - 1).max() <= SCALE_TOLERANCE, dict(zip(sk.names, scales.round(6).tolist()))
    anchors = np.linalg.norm(sk.anchor_worlds()[:, :3, :3], axis=1) if sk.anchors else np.ones((0, 3))
    assert np.abs(anchors - 1).max(initial=0) <= SCALE_TOLERANCE
    a = report["animation"]
    assert set(a["fidelity_max"]) == set(report["scales"])
    assert all(f <= FIDELITY_TOLERANCE for f in a["fidelity_max"].values()), (a["fidelity_max"], a["fidelity_worst"])
    if name in BLENDER_CONFIGS:
        _blender_round_trip(glb)


def _blender_round_trip(glb):
    """Blender imports the output and deforms it as rigmix skins it, at rest and in every clip."""
    from rigmix.io.blender_check import blender_available, blender_roundtrip

    require("Blender (Debian package blender)", blender_available())
    r = blender_roundtrip(glb)
    assert r.error <= BLENDER_TOLERANCE, (r.rest_error, r.clip_errors)


def test_compose_failure_writes_nothing(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[characters.a]\npath = "builtin:humanoid"\n[[actions]]\nop = "remove"\n'
                   'target = "a"\ntarget_joint = "NoSuchJoint"\n')
    out = tmp_path / "out.glb"
    rep = tmp_path / "out.json"
    assert main(["compose", str(bad), "-o", str(out), "--report", str(rep), "--no-progress"]) == 2
    assert not out.exists() and not rep.exists()
    assert main(["compose", str(bad), "-o", str(tmp_path / "out.obj"), "--no-progress"]) == 2
