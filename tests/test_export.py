"""Export: ``rigmix compose`` and ``rigmix batch`` write the same files through one writer, all or
none, on a cheap composition of the built-in characters."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import tail_config

from rigmix.batch import run_one
from rigmix.cli import main
from rigmix.errors import InputError
from rigmix.export import json_default, report_json, write_outputs


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = tmp_path_factory.mktemp("configs") / "tail.toml"
    path.write_text(tail_config())
    return path


@pytest.fixture(scope="module")
def composition(config):
    from rigmix.pipeline import compose

    return compose(config)


def key_tree(value):
    """The keys of a parsed JSON value at every level (lists element by element), without values."""
    if isinstance(value, dict):
        return {k: key_tree(v) for k, v in value.items()}
    if isinstance(value, list):
        return [key_tree(v) for v in value]
    return None


def test_json_default():
    data = {"a": np.float32(0.5), "b": np.arange(3), "c": {1, 2}, "d": np.int64(7)}
    assert json.loads(report_json(data)) == {"a": 0.5, "b": [0, 1, 2], "c": [1, 2], "d": 7}
    assert report_json({"b": 1, "a": 2}, sort_keys=True) == '{\n  "a": 2,\n  "b": 1\n}\n'
    with pytest.raises(TypeError, match="not JSON serializable: object"):
        json_default(object())


@pytest.mark.slow
def test_compose_and_batch_write_the_same_report(config, tmp_path):
    glb, rep = tmp_path / "tail.glb", tmp_path / "tail.json"
    assert main(["compose", str(config), "-o", str(glb), "--report", str(rep), "--no-progress"]) == 0
    out = tmp_path / "batch"
    out.mkdir()
    entry = run_one(config, out)
    assert entry["status"] == "ok", entry["error"]
    composed = json.loads(rep.read_text())
    text = (out / entry["outputs"]["report"]).read_text()
    batched = json.loads(text)
    # the same keys at every level; compose adds where it wrote the character, batch sorts the keys
    assert composed.pop("output") == str(glb)
    assert key_tree(composed) == key_tree(batched)
    assert text == json.dumps(batched, indent=2, sort_keys=True) + "\n"
    assert list(composed) != sorted(composed)  # compose keeps the stage order
    composed.pop("timings"), batched.pop("timings")
    for report in (composed, batched):  # measured, so different in each run
        next(g for g in report["gates"] if g["name"] == "wall_seconds").pop("value")
    assert composed == batched
    assert glb.read_bytes() == (out / entry["outputs"]["glb"]).read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["batch", "tail.glb", "tail.json"]  # no temporary file


@pytest.mark.slow
def test_failed_write_leaves_no_file(composition, tmp_path):
    targets = {"glb": tmp_path / "c.glb", "usd": tmp_path / "c.usda", "report": tmp_path / "c.json"}
    # a value the encoder refuses: found before anything is put in place
    bad = dataclasses.replace(composition, report={**composition.report, "oops": object()})
    with pytest.raises(TypeError):
        write_outputs(bad, **targets)
    assert list(tmp_path.iterdir()) == []
    # the report's target is a folder: the files already renamed into place are removed again
    targets["report"].mkdir()
    with pytest.raises(InputError, match="c.json"):
        write_outputs(composition, **targets)
    assert [p.name for p in tmp_path.iterdir()] == ["c.json"] and not any(targets["report"].iterdir())
    targets["report"].rmdir()
    result = write_outputs(composition, **targets)
    assert result.files[0] == targets["glb"] and result.files[-1] == targets["report"] and result.fields == ()
    assert all(p.is_file() for p in targets.values())
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
