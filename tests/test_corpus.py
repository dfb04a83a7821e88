"""The composition matrix over the 27 characters (``benchmarks/corpus_matrix.py``) and its runner
(``benchmarks/corpus.py``, ``make corpus``): generated from the limb classifier, every config valid,
a CI slice over every kind, a runner that resumes. Composes nothing but SimpleSkin's identity.
"""

from __future__ import annotations

import json
import tomllib
from itertools import combinations

import pytest
from conftest import CHARACTERS, CORPUS_CHARACTERS, asset, corpus, require

from benchmarks import corpus as runner
from benchmarks.corpus_matrix import KINDS, ci_slice, generate_matrix, load_subjects, write_configs
from rigmix.config import load_config

#: the issue's lists (#24), which the classifier's roles must reproduce
HUMANOIDS = {"Knight", "CesiumMan", "RiggedFigure", "PlatformerCharacter", "CyberpunkCharacter", "Adventurer", "Witch"}
ROBOTS = {"EnemyLarge", "EnemyTwoLegs", "Leela"}
FOUR_LEGGED = {"Horse", "Fox", "Deer", "Wolf", "Bull", "Frog"}
DINOSAURS = {"Velociraptor", "Trex", "Triceratops", "Stegosaurus", "Apatosaurus"}


@pytest.fixture(scope="module")
def subjects():
    for name in CHARACTERS:
        asset(name)  # skips, or fails under CI=true, when a character is missing
    for name in CORPUS_CHARACTERS:
        corpus(name)
    return load_subjects()


@pytest.fixture(scope="module")
def matrix(subjects):
    return generate_matrix(subjects)


def of_kind(matrix, kind):
    return [c for c in matrix if c.kind == kind]


def actions(case):
    return tomllib.loads(case.config)["actions"]


def test_roles_come_from_the_classifier(subjects):
    assert {s.name for s in subjects if s.humanoid} == HUMANOIDS
    assert {s.name for s in subjects if s.walker} == ROBOTS
    assert FOUR_LEGGED <= {s.name for s in subjects if s.quadruped}
    assert DINOSAURS <= {s.name for s in subjects if s.quadruped or s.tailed}


def test_matrix_covers_every_kind_with_the_counts_asked(subjects, matrix):
    assert len(matrix) >= 150
    assert {c.kind for c in matrix} == set(KINDS)
    by = {s.name: s for s in subjects}
    # identity: every limb of every character, with its detached parts, by itself; mirror: every limb of a pair
    identity = {(c.characters[0], a["target_joint"]) for c in of_kind(matrix, "identity") for a in actions(c)}
    limbs = {(s.name, j) for s in subjects for lb in s.plan.limbs for j in [lb.root] + s.detached_tops(lb)}
    assert identity == limbs
    assert all(a["source_joint"] == a["target_joint"] for c in of_kind(matrix, "identity") for a in actions(c))
    mirror = {(c.characters[0], a["target_joint"]) for c in of_kind(matrix, "mirror") for a in actions(c)}
    assert {(s.name, lb.root) for s in subjects for lb in s.plan.limbs if lb.partner} <= mirror
    # the 21 pairs of humanoids, one arm swap each
    arms = of_kind(matrix, "arm_swap")
    assert len(arms) == 21
    assert {frozenset(c.characters) for c in arms} == {frozenset(p) for p in combinations(sorted(HUMANOIDS), 2)}
    # legs: every robot with every humanoid and with each other robot; the four-legged and dinosaurs too
    legs = {frozenset(c.characters) for c in of_kind(matrix, "leg_swap")}
    assert {frozenset((r, h)) for r in ROBOTS for h in HUMANOIDS} <= legs
    assert {frozenset(p) for p in combinations(sorted(ROBOTS), 2)} <= legs
    assert FOUR_LEGGED | DINOSAURS <= {n for pair in legs for n in pair}
    # heads: every character with a head and a limb more gives one and takes one
    heads = of_kind(matrix, "head_swap")
    assert {c.characters[0] for c in heads} == {c.characters[1] for c in heads}
    assert HUMANOIDS | ROBOTS | FOUR_LEGGED | DINOSAURS <= {c.characters[0] for c in heads}
    # a humanoid torso on every four-legged character and dinosaur (and the many-legged Wasp)
    torso = of_kind(matrix, "torso")
    assert FOUR_LEGGED | DINOSAURS | {"Wasp"} <= {c.characters[0] for c in torso}
    assert all(c.characters[1] in HUMANOIDS for c in torso)
    # every tail onto a humanoid; wings onto every humanoid and four-legged character
    tails = of_kind(matrix, "tail")
    assert {c.characters[1] for c in tails} == {s.name for s in subjects if s.limbs("tail")}
    assert all(c.characters[0] in HUMANOIDS and actions(c)[0]["op"] == "attach" for c in tails)
    wings = of_kind(matrix, "wings")
    assert HUMANOIDS | FOUR_LEGGED <= {c.characters[0] for c in wings}
    assert {c.characters[1] for c in wings} == {"Bee", "Wasp"}
    assert all(len(actions(c)) == 2 for c in wings)  # both wings
    three = of_kind(matrix, "three")
    assert len(three) >= 5 and all(len(set(c.characters)) == 3 for c in three)
    # a leg swap takes the IK foot with the leg: the Knight's Foot.L replaces EnemyLarge's
    swap = next(c for c in of_kind(matrix, "leg_swap") if c.characters == ("EnemyLarge", "Knight"))
    assert [(a["source_joint"], a["target_joint"]) for a in actions(swap)] == [("UpperLeg.L", "Leg1.L"),
                                                                                ("Foot.L", "Foot.L")]
    # the generator names no joint: every joint it writes is one the classifier or the skeleton gave
    for c in matrix:
        for a in actions(c):
            assert a["target_joint"] in by[c.characters[0]].names


def test_names_are_unique_and_the_matrix_deterministic(subjects, matrix):
    names = [c.name for c in matrix]
    assert len(set(names)) == len(names)
    assert generate_matrix(list(reversed(subjects))) == matrix


def test_every_config_loads_and_names_existing_joints(tmp_path, subjects, matrix):
    by = {s.name: s for s in subjects}
    paths = write_configs(matrix, tmp_path)
    for case in matrix:
        assert "${RIGMIX_ASSETS}/" in case.config or "${RIGMIX_CORPUS}/" in case.config
        cfg = load_config(paths[case.name])  # missing character files are an InputError
        assert cfg.name == case.name
        files = {cid: c.path for cid, c in cfg.characters.items()}
        for a in cfg.actions:
            target = next(s for s in by.values() if s.path == files[a.target])
            assert a.target_joint in target.names
            if getattr(a, "source", None):
                source = next(s for s in by.values() if s.path == files[a.source])
                names = source.mirrored if cfg.characters[a.source].mirror else source.names
                assert a.source_joint in names, (case.name, a.source_joint)


def test_ci_slice_covers_every_kind(matrix):
    picked = ci_slice(matrix)
    assert len(picked) >= 12
    assert {c.kind for c in picked} == set(KINDS)
    assert len({c.name for c in picked}) == len(picked)
    assert ci_slice(matrix) == picked and all(c in matrix for c in picked)


#: a reference operation as :func:`benchmarks.common.reference_operation` returns it (not timed: seconds)
FAKE_REFERENCE = {"operation": "fake", "seconds": 2.0, "runs": [2.0], "faces": 1, "points": 1, "commit": "abc1234",
                  "machine": "test machine", "cpus": 2, "load_average": [0.5, 0.5, 0.5], "date": "2026-01-01 00:00 UTC"}


@pytest.fixture
def fake_reference(monkeypatch):
    """The runner's reference operation replaced by :data:`FAKE_REFERENCE`; returns the call count."""
    calls = []
    monkeypatch.setattr(runner, "reference_operation", lambda: calls.append(1) or dict(FAKE_REFERENCE))
    return calls


def _fake_row(calls):
    def run_case(case, config, scratch, *, timeout, blender=True, threads=None):
        calls.append(case.name)
        gates = runner.runner_gates(0, 1.0)
        if blender:
            gates.append(runner.measured(runner.BLENDER_GATE, 1e-7, "<=", runner.BLENDER_BOUND))
        return {"name": case.name, "kind": case.kind, "characters": list(case.characters), "config_sha": case.sha,
                "rc": 0, "timed_out": False, "stderr_last": "", "wall_s": 1.0, "gates": gates, "failed": [],
                "passed": True, "message": "", "timings": {"fusion": 0.5, "total": 1.0}}
    return run_case


def test_runner_resumes_unchanged_rows(tmp_path, monkeypatch, subjects, fake_reference):
    calls = []
    monkeypatch.setattr(runner, "load_subjects", lambda: subjects)
    monkeypatch.setattr(runner, "run_case", _fake_row(calls))
    args = ["--kind", "three", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "out")]
    assert runner.main(args) == 0
    assert len(calls) == 7
    assert runner.main(args) == 0 and len(calls) == 7  # every row kept
    path = tmp_path / "results" / "corpus.json"
    data = json.loads(path.read_text())
    assert [r["name"] for r in data["rows"]] == calls
    data["rows"][0]["config_sha"] = "changed"
    data["rows"][1]["passed"] = False
    path.write_text(json.dumps(data))
    assert runner.main(args) == 1  # the failed row is kept and counted
    assert calls[7:] == [data["rows"][0]["name"]]  # only the changed config ran again
    assert runner.main(args + ["--rerun-failed"]) == 0 and calls[8:] == [data["rows"][1]["name"]]
    assert runner.main(args + ["--fresh", "--limit", "2"]) == 0 and len(calls) == 11
    md = (tmp_path / "results" / "corpus.md").read_text()
    assert "| three | 7 | 7 | 7 | 100.0 % |" in md
    # the reference was timed once per run that composed something, and every row keeps its run's
    assert len(fake_reference) == 4
    assert runner.load_reference(path) == FAKE_REFERENCE
    assert all(r["reference_s"] == 2.0 for r in runner.load_rows(path).values())
    # fusion 0.5 s, total and process 1.0 s: 0.25 and 0.5 times the reference's 2 s
    assert "| fusion | 7 | 0.50 | 0.25 | 0.50 | 0.25 |" in md and "| process | 7 | 1.00 | 0.5 | 1.00 | 0.5 |" in md


def test_a_row_without_the_blender_gate_is_composed_again_unless_it_is_left_out(tmp_path, monkeypatch, subjects,
                                                                               fake_reference):
    calls = []
    monkeypatch.setattr(runner, "load_subjects", lambda: subjects)
    monkeypatch.setattr(runner, "run_case", _fake_row(calls))
    args = ["--kind", "three", "--results", str(tmp_path / "results"), "--out", str(tmp_path / "out")]
    assert runner.main(args + ["--no-blender"]) == 0 and len(calls) == 7
    assert runner.main(args + ["--no-blender"]) == 0 and len(calls) == 7  # kept: the gate is not asked for
    assert runner.main(args) == 0 and len(calls) == 14  # asked for: every row lacked it
    rows = runner.load_rows(tmp_path / "results" / "corpus.json").values()
    assert all(runner.BLENDER_GATE in {g["name"] for g in r["gates"]} for r in rows)
    assert runner.main(args) == 0 and len(calls) == 14


def test_tables_divide_rows_without_a_reference_by_the_one_timed_now(tmp_path, monkeypatch, subjects, fake_reference):
    """``--tables`` composes nothing; rows of a run that did not time the reference are divided by the
    one timed now, and the table says which."""
    calls = []
    monkeypatch.setattr(runner, "load_subjects", lambda: subjects)
    monkeypatch.setattr(runner, "run_case", _fake_row(calls))
    results = tmp_path / "results"
    args = ["--kind", "three", "--results", str(results), "--out", str(tmp_path / "out")]
    assert runner.main(args) == 0 and len(calls) == 7
    path = results / "corpus.json"
    data = json.loads(path.read_text())
    for r in data["rows"][:3]:  # as rows of older runs are stored
        del r["reference_s"]
        r["commit"], r["timings"]["fusion"] = "old1234", 4.0
    del data["reference"]
    path.write_text(json.dumps(data))
    assert runner.main(args + ["--tables"]) == 0 and len(calls) == 7 and len(fake_reference) == 2
    md = (results / "corpus.md").read_text()
    assert "3 rows (commit(s) old1234) come from runs that did not time it" in md
    assert "4 rows are divided by the reference timed in their own run" in md
    assert "measured on commit abc1234, test machine" in md
    # fusion: 0.5 s in 4 rows, 4.0 s in 3, all divided by 2 s
    assert "| fusion | 7 | 0.50 | 0.25 | 4.00 | 2 |" in md
    assert runner.load_rows(path).keys() == {r["name"] for r in data["rows"]}


def test_runner_composes_a_case_and_records_its_gates(tmp_path, monkeypatch, subjects, fake_reference):
    from rigmix.io.blender_check import blender_available

    require("Blender (Debian package blender)", blender_available())
    monkeypatch.setattr(runner, "load_subjects", lambda: subjects)
    results = tmp_path / "results"
    rc = runner.main(["--only", "identity__SimpleSkin__*", "--results", str(results), "--out", str(tmp_path / "out")])
    row = next(iter(runner.load_rows(results / "corpus.json").values()))
    stored = json.loads((results / "corpus.json").read_text())["rows"][0]["gates"]
    assert [runner.unpack_gate(g) for g in stored] == row["gates"] and all(isinstance(g, list) for g in stored)
    assert row["name"].startswith("identity__SimpleSkin__") and row["rc"] == 0
    assert (tmp_path / "out" / "glb" / f"{row['name']}.glb").is_file()
    names = [g["name"] for g in row["gates"]]
    assert names[:2] == ["exit_status", "process_seconds"] and len(names) > 2
    blender = next(g for g in row["gates"] if g["name"] == runner.BLENDER_GATE)  # issue 25: the round trip
    assert blender["pass"] is True and 0 <= blender["value"] <= runner.BLENDER_BOUND, blender
    assert row["blender_s"] > 0
    assert all({"name", "value", "op", "bound", "pass"} <= set(g) for g in row["gates"])
    assert set(row["timings"]) >= {"load", "fusion", "weights", "total"}
    assert rc == (0 if row["passed"] else 1)
    assert row["name"] in (results / "corpus.md").read_text()


def test_the_report_gates_are_used_when_the_report_has_them(matrix, tmp_path):
    gates = [{"name": "validator_errors", "value": 3, "op": "<=", "bound": 0, "pass": False, "note": "ACCESSOR_X"}]
    report = {"gates": gates, "mesh": {"open_seam_edges": 5}}
    source, got = runner.report_gates(report, tmp_path / "none.glb", matrix[0])
    assert source == "report" and got == gates
    row = {"rc": 0}
    assert runner.failure_message(row, runner.failed_gates(got)) == "validator_errors = 3 (needs <= 0) [ACCESSOR_X]"


def test_a_tail_is_grafted_where_the_legs_meet(subjects, matrix):
    """Every humanoid's pelvis lies among its leg roots, also where the legs hang from an
    armature root on the floor (Witch): the tail cases attach there."""
    import numpy as np

    by = {s.name: s for s in subjects}
    for name in HUMANOIDS:
        s = by[name]
        roots = [lb.root for lb in s.limbs("leg")]
        R = s.positions[[s.names.index(j) for j in roots]]
        spread = np.linalg.norm(R[0] - R[1])
        assert np.linalg.norm(s.positions[s.names.index(s.pelvis)] - R.mean(axis=0)) <= spread, name
        # on the trunk, at or below the legs' common ancestor
        assert s.lca(roots) in s.ancestors(s.pelvis) and s.pelvis in s.ancestors(s.chest)[:-1], name
    assert by["Witch"].pelvis == "Hips"  # its legs' common ancestor is Root, on the floor
    for case in of_kind(matrix, "tail"):
        body = by[case.characters[0]]
        assert actions(case)[0]["target_joint"] == body.pelvis


def test_compositions_run_at_once_share_the_cores_out(monkeypatch):
    """``--jobs N``: each composition's numerical libraries get ``cpu_count // N`` threads; one at
    a time, the libraries' own defaults."""
    from rigmix.batch import THREAD_VARIABLES

    for name in THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert all(name not in runner._env() for name in THREAD_VARIABLES)
    assert all(runner._env(1)[name] == "1" for name in THREAD_VARIABLES)
    assert runner._env(3)["OMP_NUM_THREADS"] == "3"


def test_only_takes_several_patterns_separated_by_commas(matrix):
    names = {c.name for c in runner.select(matrix, only="wings__*Bee,identity__Wasp__Head")}
    bee = {c.name for c in matrix if c.kind == "wings" and c.name.endswith("__Bee")}
    assert bee and names == bee | {"identity__Wasp__Head"}
    # one pattern as before: a shell pattern, or a substring
    assert {c.name for c in runner.select(matrix, only="Wasp__Head")} >= {"identity__Wasp__Head"}
    assert runner.select(matrix, only="wings__*", kind="tail") == []
