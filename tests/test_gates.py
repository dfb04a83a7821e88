"""Hard gates (rigmix.gates): every report lists them, the self-composition passes them all (the
identity gates included), each gate family fails on a written file broken on purpose, and
``--strict`` turns a failed gate into exit status 3 with one line."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest
from conftest import ROOT, asset
from hostile import glb, set_floats, split_glb

from rigmix.batch import exit_status, read_manifest
from rigmix.cli import main
from rigmix.gates import (
    GATE_NAMES,
    IDENTITY_TOLERANCE,
    MAX_INFLUENCES,
    clip_gates,
    evaluate_gates,
    failure_text,
    fidelity_gate,
    identity_gates,
    identity_mismatch,
    mesh_gates,
    stretch_gate,
    validator_gate,
    weight_gates,
    world_scale_gate,
)
from rigmix.io.accessors import load_document
from rigmix.io.gltf import read_gltf
from rigmix.io.validator import validator_available

SELF = ROOT / "tests" / "configs" / "self_composition.toml"


def by_name(gates) -> dict:
    return {g["name"]: g for g in gates}


def self_config(tmp_path, name: str, extra: str = "", donor: str = "") -> str:
    """A copy of the self-composition config (CesiumMan's left arm replaced by itself) in
    ``tmp_path``, with ``extra`` TOML sections and ``donor`` keys added."""
    asset("CesiumMan")
    text = SELF.read_text().replace('[characters.donor]\npath = "${RIGMIX_ASSETS}/CesiumMan/CesiumMan.glb"\n',
                                    '[characters.donor]\npath = "${RIGMIX_ASSETS}/CesiumMan/CesiumMan.glb"\n'
                                    + donor)
    path = tmp_path / f"{name}.toml"
    path.write_text(text + extra)
    return path


def run_cli(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The self-composition composed once and written: (composition, glb path, export result, report)."""
    from rigmix.export import write_outputs
    from rigmix.pipeline import compose

    asset("CesiumMan")
    comp = compose(SELF)
    out = tmp_path_factory.mktemp("gates")
    result = write_outputs(comp, glb=out / "self.glb", report=out / "self.json")
    return comp, out / "self.glb", result, json.loads((out / "self.json").read_text())


def edit(src, dst, fn):
    """Write ``dst``: the GLB ``src`` with its JSON and BIN edited by ``fn(js, data) -> data``."""
    js, data = split_glb(src.read_bytes())
    data = fn(js, data)
    js["buffers"][0]["byteLength"] = len(data)
    dst.write_bytes(glb(js, data))
    return dst


def weights_accessor(js) -> int:
    prim = next(p for m in js["meshes"] for p in m["primitives"] if "WEIGHTS_0" in p["attributes"])
    return prim["attributes"]["WEIGHTS_0"]


# --------------------------------------------------------------------------------------------
# the report


def test_report_lists_every_gate_in_order(written):
    _, _, result, report = written
    assert [g["name"] for g in report["gates"]] == list(GATE_NAMES)
    assert report["gates"] == list(result.gates)
    for g in report["gates"]:
        assert {"name", "value", "op", "bound", "pass"} <= set(g) and g["op"] in ("<=", ">=")
        assert g["pass"] in (True, False, None)
        assert g["value"] is None or isinstance(g["value"], (int, float))
        if g["value"] is None:
            assert g.get("note"), g  # a gate without a value says why
    assert list(report).index("gates") > list(report).index("quality")
    assert {"write", "gates"} <= set(report["timings"])


def test_self_composition_passes_every_gate_and_reproduces_its_input(written):
    _, _, result, report = written
    gates = by_name(report["gates"])
    assert gates["identity_surface_error"]["value"] <= IDENTITY_TOLERANCE
    assert gates["identity_skinned_error"]["value"] <= IDENTITY_TOLERANCE
    assert "frames" in gates["identity_skinned_error"]["note"]
    # the junction was copied: no generated triangle to measure, which passes
    assert gates["junction_min_angle_p05"]["value"] is None and gates["junction_min_angle_p05"]["pass"] is True
    # one file under two ids: its clip written once, present
    assert len(report["animation"]["clips"]) == 1 and gates["clips_missing"]["value"] == 0
    if validator_available():
        assert gates["validator_errors"]["value"] == 0
    assert not [g for g in report["gates"] if g["pass"] is False], failure_text(report["gates"])


# --------------------------------------------------------------------------------------------
# each family fails on what it guards


def test_weight_gates_fail_on_negative_unnormalized_and_five_influences(written, tmp_path):
    _, path, _, _ = written
    js, data = split_glb(path.read_bytes())
    W = load_document(path).accessor(weights_accessor(js))
    four = int(np.flatnonzero(np.count_nonzero(W, axis=1) == 4)[0])
    assert by_name([g.as_dict() for g in weight_gates(load_document(path))])["weights_max_influences"]["value"] == 4

    def negative(js, data):
        return set_floats(js, data, weights_accessor(js), lambda i, w: [-0.25, 1.25, 0, 0] if i == 0 else w)

    def unnormalized(js, data):
        return set_floats(js, data, weights_accessor(js), lambda i, w: [x * 1.01 for x in w] if i == 3 else w)

    def five(js, data):
        # a second weight set: vertex `four` gets a fifth influence, its first four scaled to keep the sum 1
        data = set_floats(js, data, weights_accessor(js), lambda i, w: [x * 0.8 for x in w] if i == four else w)
        n = js["accessors"][weights_accessor(js)]["count"]
        extra = np.zeros((n, 4), np.float32)
        extra[four, 0] = 0.2
        joints = np.zeros((n, 4), np.uint8)
        joints[four, 0] = 1
        data = bytes(data) + b"\0" * (-len(data) % 4)
        views = []
        for block in (extra.tobytes(), joints.tobytes()):
            views.append(len(js["bufferViews"]))
            js["bufferViews"].append({"buffer": 0, "byteOffset": len(data), "byteLength": len(block)})
            data += block
        for attr, view, ctype in (("WEIGHTS_1", views[0], 5126), ("JOINTS_1", views[1], 5121)):
            js["accessors"].append({"bufferView": view, "componentType": ctype, "count": n, "type": "VEC4"})
            for m in js["meshes"]:
                for p in m["primitives"]:
                    if p["attributes"].get("WEIGHTS_0") == weights_accessor(js):
                        p["attributes"][attr] = len(js["accessors"]) - 1
        return data

    cases = {"weights_min": (negative, -0.25), "weights_unnormalized_vertices": (unnormalized, 1),
             "weights_max_influences": (five, MAX_INFLUENCES + 1)}
    for name, (fn, value) in cases.items():
        broken = edit(path, tmp_path / f"{name}.glb", fn)
        gates = by_name([g.as_dict() for g in weight_gates(load_document(broken))])
        assert gates[name]["pass"] is False and gates[name]["value"] == pytest.approx(value), gates[name]
        # each defect fails its own gate (a negative weight is left out of its row's sum, as the
        # validator adds weights, so that row is off too)
        others = [g for n, g in gates.items() if n != name and not (name == "weights_min" and "unnormalized" in n)]
        assert all(g["pass"] for g in others), gates
        if name == "weights_min" and validator_available():
            assert validator_gate(broken).passed is False  # the validator agrees


def test_clip_gates_fail_on_repeated_key_times_and_a_missing_clip(written, tmp_path):
    comp, path, _, _ = written
    js, _ = split_glb(path.read_bytes())
    first = js["animations"][0]["name"]

    def repeated(js, data):  # the second key time repeats the first (the time span stays)
        index = js["animations"][0]["samplers"][0]["input"]
        times = load_document(path).accessor(index).ravel()
        return set_floats(js, data, index, lambda i, t: [float(times[0])] if i == 1 else t)

    broken = edit(path, tmp_path / "repeated.glb", repeated)
    gates = by_name([g.as_dict() for g in clip_gates(load_document(broken), comp)])
    assert gates["clips_non_increasing_times"]["pass"] is False and first in gates["clips_non_increasing_times"]["note"]
    assert gates["clips_missing"]["pass"] is True

    def drop(count):
        def fn(js, data):
            js["animations"] = js["animations"][count:]
            return data
        return fn

    # one file under two ids has one distinct input clip, written once: without it, it is missing
    assert len(js["animations"]) == 1
    none = by_name([g.as_dict() for g in clip_gates(load_document(edit(path, tmp_path / "none.glb", drop(1))), comp)])
    assert none["clips_missing"]["pass"] is False and none["clips_missing"]["value"] == 1
    assert none["clips_non_increasing_times"]["value"] == 0


def test_identity_gates_fail_on_a_moved_vertex(written, tmp_path):
    comp, path, _, _ = written
    js, _ = split_glb(path.read_bytes())
    prim = js["meshes"][0]["primitives"][0]
    acc = js["accessors"][prim["attributes"]["POSITION"]]
    diag = float(np.linalg.norm(np.subtract(acc["max"], acc["min"])))

    def move(js, data):
        return set_floats(js, data, prim["attributes"]["POSITION"],
                          lambda i, p: [p[0] + 0.05 * diag, p[1], p[2]] if i == 0 else p)

    gates = by_name([g.as_dict() for g in identity_gates(comp, read_gltf(edit(path, tmp_path / "moved.glb", move)))])
    for name in ("identity_surface_error", "identity_skinned_error"):
        assert gates[name]["pass"] is False and gates[name]["value"] > IDENTITY_TOLERANCE, gates[name]


def test_what_makes_a_composition_no_identity(written):
    comp, _, _, _ = written
    assert identity_mismatch(comp) is None
    config = comp.config
    donor = config.characters["donor"]

    def with_donor(**changes):
        chars = {**config.characters, "donor": donor.model_copy(update=changes)}
        return dataclasses.replace(comp, config=config.model_copy(update={"characters": chars}))

    assert "mirrored" in identity_mismatch(with_donor(mirror=True))
    assert "placed" in identity_mismatch(with_donor(placement={"translation": (0, 0, 0)}))
    action = config.actions[0].model_copy(update={"source_joint": "Skeleton_arm_joint_R"})
    other_joint = dataclasses.replace(comp, config=config.model_copy(update={"actions": [action]}))
    assert "replaces" in identity_mismatch(other_joint)
    scaled = dataclasses.replace(comp, plan=dataclasses.replace(comp.plan, scales={**comp.plan.scales, "donor": 1.1}))
    assert "scale 1.1" in identity_mismatch(scaled)
    gates = by_name([g.as_dict() for g in identity_gates(scaled, None)])  # not applicable: the file is not read
    assert gates["identity_surface_error"]["value"] is None and gates["identity_surface_error"]["pass"] is True
    assert "not an identity composition" in gates["identity_surface_error"]["note"]


def test_mesh_and_stretch_gates_read_the_report(written):
    comp, _, _, report = written
    mesh = report["mesh"]
    for name in ("junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges",
                 "junction_self_intersections"):
        gates = by_name([g.as_dict() for g in mesh_gates({**mesh, name: 2})])
        assert gates[name]["pass"] is False and failure_text(list(gates.values())) == f"{name} = 2 (bound <= 0)"
    angle = by_name([g.as_dict() for g in mesh_gates({**mesh, "junction_min_angle_p05": 12.5})])
    assert angle["junction_min_angle_p05"]["pass"] is False
    quality = {**report["quality"], "junction_stretch_ratio": 2.0}
    assert stretch_gate(dataclasses.replace(comp, report={**comp.report, "quality": quality})).passed is False
    quality["junction_stretch_ratio"] = None  # inputs with clips, a fused joint, yet not measured: fails
    assert stretch_gate(dataclasses.replace(comp, report={**comp.report, "quality": quality})).passed is False


def test_missing_validator_leaves_its_gate_unevaluated(written, tmp_path, monkeypatch):
    _, path, _, _ = written
    monkeypatch.setenv("RIGMIX_NODE_MODULES", str(tmp_path))  # no gltf-validator there
    gate = validator_gate(path)
    assert gate.passed is None and gate.value is None and "npm ci" in gate.note


def test_gates_without_a_file_are_not_evaluated(written):
    comp, _, _, _ = written
    gates = evaluate_gates(comp, None, seconds=1.0)
    assert [g["name"] for g in gates] == list(GATE_NAMES)
    from_the_file = {"validator_errors"} | set(GATE_NAMES[GATE_NAMES.index("weights_min"):])
    assert all((g["pass"] is None) == (g["name"] in from_the_file) for g in gates), gates


# --------------------------------------------------------------------------------------------
# --strict


def test_strict_compose_exits_0_when_every_gate_passes(tmp_path):
    asset("CesiumMan")
    status, out, err = run_cli(["compose", str(SELF), "-o", str(tmp_path / "s.glb"), "--strict", "--no-progress"])
    assert status == 0, err
    assert f"gates: {len(GATE_NAMES)}/{len(GATE_NAMES)} passed" in out or "not evaluated" in out


def test_strict_compose_exits_3_with_one_line_and_writes_the_outputs(tmp_path):
    cfg = self_config(tmp_path, "slow", "\n[gates]\nmax_seconds = 0.001\n")
    glb_path, rep = tmp_path / "slow.glb", tmp_path / "slow.json"
    argv = ["compose", str(cfg), "-o", str(glb_path), "--report", str(rep), "--no-progress"]
    status, _, err = run_cli(argv + ["--strict"])
    assert status == 3
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rigmix: gate failed: wall_seconds = "), err
    assert lines[0].endswith("(bound <= 0.001)")
    assert glb_path.is_file() and rep.is_file()  # written all the same
    gate = by_name(json.loads(rep.read_text())["gates"])["wall_seconds"]
    assert gate["pass"] is False and gate["bound"] == 0.001


def test_strict_batch_counts_a_failed_gate(tmp_path):
    slow = self_config(tmp_path, "slow", "\n[gates]\nmax_seconds = 0.001\n")
    placed = self_config(tmp_path, "placed", donor="placement = { translation = [0, 0, 0] }\n")
    out = tmp_path / "batch"
    status, _, err = run_cli(["batch", str(slow), str(placed), "--out", str(out), "--workers", "0", "--strict",
                              "--no-progress"])
    assert status == 3
    lines = [line for line in err.splitlines() if line.startswith("rigmix: gate failed:")]
    assert len(lines) == 1 and lines[0].startswith("rigmix: gate failed: slow.toml: wall_seconds = "), err
    entries = list(read_manifest(out).values())
    assert all(e["status"] == "ok" for e in entries)
    assert exit_status(entries) == 0 and exit_status(entries, strict=True) == 3
    report = json.loads((out / "placed.report.json").read_text())
    identity = by_name(report["gates"])["identity_surface_error"]
    assert identity["value"] is None and identity["pass"] is True and "placed" in identity["note"]


def test_batch_exit_status_orders_failures_before_gates():
    ok = {"status": "ok", "gates_failed": []}
    gated = {"status": "ok", "gates_failed": ["wall_seconds = 9 (bound <= 1)"]}
    bad_input = {"status": "failed", "error_kind": "input"}
    assert exit_status([ok, gated]) == 0 and exit_status([ok, gated], strict=True) == 3
    assert exit_status([gated, bad_input], strict=True) == 2
    assert exit_status([ok, {"status": "ok"}], strict=True) == 0  # an entry written before the gates


def test_fidelity_gate_takes_the_worst_source():
    g = fidelity_gate({"fidelity_max": {"horse": 2e-3, "knight": 1e-7}})
    assert g.passed is False and g.value == 2e-3 and "horse" in g.note
    assert fidelity_gate({"fidelity_max": {"horse": 3e-6}}).passed is True
    none = fidelity_gate({"fidelity_max": {}})
    assert none.value is None and none.passed is True and none.note


def test_world_scale_gate_fails_on_a_scaled_joint(written, tmp_path):
    """A joint carrying a rest scale (a Quaternius armature's 100) fails; the output passes."""
    _, path, _, report = written
    assert by_name(report["gates"])["joint_world_scale_error"]["pass"] is True
    js, _ = split_glb(path.read_bytes())
    joint = js["skins"][0]["joints"][0]

    def scale(js, data):
        js["nodes"][joint]["scale"] = [100.0, 100.0, 100.0]
        js["nodes"][joint].pop("matrix", None)
        return data

    g = world_scale_gate(read_gltf(edit(path, tmp_path / "scaled.glb", scale)))
    assert g.passed is False and g.value == pytest.approx(99.0)
