"""The Khronos glTF-Validator harness, and 0 validator errors on everything rigmix writes."""

from __future__ import annotations

import os
from collections import Counter

import pytest
from conftest import CHARACTERS, asset

from rigmix.io.gltf import read_gltf, write_gltf
from rigmix.io.validator import ValidatorUnavailable, validate_gltf, validator_available


@pytest.fixture(autouse=True)
def need_validator():
    if not validator_available():
        msg = "node or node_modules/gltf-validator missing (run `npm ci`)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)


def codes(report, severity=0):
    return Counter(m["code"] for m in report["issues"]["messages"] if m["severity"] == severity)


@pytest.mark.parametrize("name", sorted(CHARACTERS))
def test_written_files_have_no_errors(name, tmp_path):
    path = tmp_path / f"{name}.glb"
    write_gltf(read_gltf(asset(name)), path)
    report = validate_gltf(path)
    assert report["issues"]["numErrors"] == 0, codes(report)
    assert report["issues"]["numWarnings"] == 0, codes(report, 1)
    assert report["info"]["animationCount"] == len(read_gltf(asset(name)).clips)


def test_embedded_gltf_output_has_no_errors(tmp_path):
    path = tmp_path / "CesiumMan.gltf"
    write_gltf(read_gltf(asset("CesiumMan")), path)
    report = validate_gltf(path)
    assert report["issues"]["numErrors"] == 0, codes(report)


def test_validator_reports_the_known_input_errors():
    """The harness sees real errors: the shared Wasp and Horse are invalid as published."""
    wasp = validate_gltf(asset("Wasp"))
    assert wasp["issues"]["numErrors"] == 42
    assert codes(wasp) == {"ACCESSOR_INVALID_FLOAT": 24, "ACCESSOR_JOINTS_INDEX_DUPLICATE": 18}
    horse = validate_gltf(asset("Horse"))
    assert codes(horse) == {"SKIN_SKELETON_INVALID": 1}


def test_external_resources_are_loaded(tmp_path):
    from test_gltf_io import Synth

    path = Synth().build(tmp_path, "external")
    report = validate_gltf(path)
    # the deliberate duplicate joint slot is found, so the external .bin was read (the synthetic
    # input breaks other rules on purpose: a channel on a matrix node, 6-byte colour elements)
    assert codes(report)["ACCESSOR_JOINTS_INDEX_DUPLICATE"] == 1
    assert not any(m["code"].startswith("IO_") for m in report["issues"]["messages"])


def test_missing_package_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGMIX_NODE_MODULES", str(tmp_path))
    assert not validator_available()
    with pytest.raises(ValidatorUnavailable, match="npm ci"):
        validate_gltf(asset("SimpleSkin"))


def test_a_validator_crash_is_named_by_its_error_line(tmp_path):
    """A node hierarchy 30,000 deep overflows the validator's recursion (it does past about 7,000
    with Node's default stack; 30,000 leaves room for a larger one): the error says so (Node's
    ``RangeError`` line), not the Node version it prints last."""
    import json

    from rigmix.errors import RigmixError

    n = 30_000
    nodes = [{"name": f"n{i}", **({"children": [i + 1]} if i + 1 < n else {})} for i in range(n)]
    path = tmp_path / "deep.gltf"
    path.write_text(json.dumps({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": nodes}))
    with pytest.raises(RigmixError, match=r"deep\.gltf: the validator failed: RangeError: Maximum call stack"):
        validate_gltf(path)
