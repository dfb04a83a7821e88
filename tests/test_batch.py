"""``rigmix batch``: 5 configs with one deliberately broken, on the local process pool and on a
Dask LocalCluster: 4 outputs, 1 failure recorded, a second run does nothing new. Five jobs give
each of the two workers more than one, with a job after the broken one (the batch goes on past a
failure); throughput is the batch benchmark's business (``benchmarks/batch_bench.py``).

The 4 good configs each replace a limb of the built-in humanoid by the same limb of the same
character: the batch machinery is what these tests exercise, and such a composition is among the
cheapest (the junction faces coincide and are copied, ``[fusion] copy_coincident``; 1.2 to 1.5 s of
CPU, against 2.5 to 3.1 s for a tail graft or an arm at another scale), and only one built-in
character is built per worker process."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tempfile
import threading

import pytest
from conftest import ROOT, require

from rigmix.batch import MANIFEST, builtin_names, plan_batch, read_manifest, run_batch, run_one
from rigmix.errors import InputError
from rigmix.io.gltf import read_gltf
from rigmix.safety import file_digest

EXAMPLES = ROOT / "examples"

#: A limb of the built-in humanoid replaced by itself (see the module docstring).
_SELF = """name = "self_{k}"
[characters.body]
path = "builtin:humanoid"
[characters.donor]
path = "builtin:humanoid"
scale = 1.0
[[actions]]
op = "replace"
source = "donor"
source_joint = "{joint}"
target = "body"
target_joint = "{joint}"
[weights]
method = "nearest"
"""
_JOINTS = ("Hand.L", "Hand.R", "LowerArm.L", "LowerArm.R")
_BROKEN = """name = "broken"
[characters.human]
path = "builtin:humanoid"
[[actions]]
op = "remove"
target = "human"
target_joint = "NoSuchJoint"
"""


def make_configs(folder, n=5, broken=3):
    """``n`` config files in ``folder``, the one at index ``broken`` naming an unknown joint."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(n):
        text = _BROKEN if k == broken else _SELF.format(k=k, joint=_JOINTS[k % len(_JOINTS)])
        p = folder / f"c{k:02d}.toml"
        p.write_text(text)
        paths.append(p)
    return paths


def check_first_run(entries, configs, out, broken=3):
    assert [e["config"] for e in entries] == [str(p.resolve()) for p in configs]
    failed = [e for e in entries if e["status"] != "ok"]
    assert len(failed) == 1 and failed[0]["stem"] == configs[broken].stem
    assert "NoSuchJoint" in failed[0]["error"] and "\n" not in failed[0]["error"]
    glbs = sorted(p.name for p in out.glob("*.glb"))
    assert glbs == sorted(f"{p.stem}.glb" for i, p in enumerate(configs) if i != broken)
    assert len(list(out.glob("*.report.json"))) == len(configs) - 1
    assert not list(out.glob(".*"))  # no temporary files left
    lines = (out / MANIFEST).read_text().splitlines()
    assert len(lines) == len(configs)
    for e in map(json.loads, lines):
        assert set(e) >= {"config", "config_sha256", "stem", "status", "outputs", "timings", "error", "finished"}
        assert e["timings"]["total"] >= 0
        if e["status"] == "ok":
            assert e["error"] is None and e["timings"]["compose"] > 0
            assert all((out / name).is_file() for name in e["outputs"].values())
            report = json.loads((out / e["outputs"]["report"]).read_text())
            assert "timings" in report
    # a written character reads back and is skinned
    c = read_gltf(out / glbs[0])
    assert c.skinned and c.skeleton.num_joints > 0


def check_second_run(run, configs, out, broken=3):
    """A second run skips the finished jobs (outputs untouched) and retries the broken one."""
    before = {p.name: (p.stat().st_mtime_ns, file_digest(p)) for p in out.glob("*.glb")}
    n_lines = len((out / MANIFEST).read_text().splitlines())
    entries = run()
    assert sum(bool(e.get("skipped")) for e in entries) == len(configs) - 1
    assert [e["status"] for e in entries].count("failed") == 1
    after = {p.name: (p.stat().st_mtime_ns, file_digest(p)) for p in out.glob("*.glb")}
    assert after == before
    lines = (out / MANIFEST).read_text().splitlines()
    assert len(lines) == n_lines + 1 and json.loads(lines[-1])["stem"] == configs[broken].stem


@pytest.mark.slow
def test_batch_process_pool(tmp_path, monkeypatch):
    configs = make_configs(tmp_path / "configs")
    out = tmp_path / "out"
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))  # where the batch's private folder goes
    seen = []
    entries = run_batch(configs, out, workers=2, progress=lambda d, t, e: seen.append((d, t)))
    n = len(configs)
    assert seen[-1] == (n, n) and sorted(d for d, _ in seen) == list(range(1, n + 1))
    check_first_run(entries, configs, out)
    assert all(e["timings"]["cpu"] > 0 for e in entries if e["status"] == "ok")
    # the humanoid was built by one worker and read by the other (rigmix.batch.share_builtins), through
    # a folder removed after the batch: the first two jobs, one per worker, give what this process gives
    assert builtin_names(configs) == ["humanoid"]
    assert not list((tmp_path / "tmp").glob("rigmix-builtins-*"))
    solo = tmp_path / "solo"
    solo.mkdir()
    for p in configs[:2]:
        assert run_one(p, solo)["status"] == "ok"
        assert (solo / f"{p.stem}.glb").read_bytes() == (out / f"{p.stem}.glb").read_bytes(), p.name
    check_second_run(lambda: run_batch(configs, out, workers=2), configs, out)
    # an edited config is run again even though its entry is ok
    configs[0].write_text(configs[0].read_text().replace("scale = 1.0", "scale = 0.95"))
    todo, skipped = plan_batch(configs, out)
    assert [p.name for p in todo] == [configs[0].name, configs[3].name] and len(skipped) == n - 2


@pytest.mark.slow
def test_an_interrupted_pool_leaves_no_thread_behind(tmp_path):
    """An interrupt while a worker composes stops the workers and joins the pools' manager threads:
    one left running races the executor's exit hook on its closed wake-up pipe ("Bad file
    descriptor" at interpreter exit)."""
    configs = make_configs(tmp_path / "configs", n=4, broken=-1)

    def interrupt(done, total, entry):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(configs, tmp_path / "out", workers=2, progress=interrupt)
    managers = [t for t in threading.enumerate() if type(t).__name__ == "_ExecutorManagerThread"]
    assert not [t for t in managers if t.is_alive()]


@pytest.mark.slow
def test_batch_dask_local_cluster(tmp_path):
    require("dask.distributed (the rigmix[dask] extra, installed by `make env`)",
            importlib.util.find_spec("distributed") is not None)
    configs = make_configs(tmp_path / "configs")
    out = tmp_path / "out"
    entries = run_batch(configs, out, scheduler="local-dask", workers=2)
    check_first_run(entries, configs, out)
    check_second_run(lambda: run_batch(configs, out, scheduler="local-dask", workers=2), configs, out)


def test_run_one_failure_leaves_nothing(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(_BROKEN)
    digest = file_digest(cfg)
    out = tmp_path / "out"
    out.mkdir()
    entry = run_one(cfg, out)
    assert entry["status"] == "failed" and "NoSuchJoint" in entry["error"]
    assert entry["config_sha256"] == digest == file_digest(cfg)
    assert list(out.iterdir()) == []


def test_missing_config_is_recorded_not_raised(tmp_path):
    out = tmp_path / "out"
    entries = run_batch([tmp_path / "nope.toml"], out, workers=0)
    (e,) = entries
    assert e["status"] == "failed" and "nope.toml" in e["error"]
    assert read_manifest(out)[str((tmp_path / "nope.toml").resolve())]["status"] == "failed"


def test_colliding_names_are_refused(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for d in "ab":
        (tmp_path / d / "x.toml").write_text(_BROKEN)
    with pytest.raises(InputError, match="same name"):
        run_batch([tmp_path / "a" / "x.toml", tmp_path / "b" / "x.toml"], tmp_path / "out")
    with pytest.raises(InputError, match="listed twice"):
        plan_batch([tmp_path / "a" / "x.toml", tmp_path / "a" / "x.toml"], tmp_path / "out")
    with pytest.raises(InputError, match="no config"):
        plan_batch([], tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_manifest_with_a_cut_last_line(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    good = {"config": "/x/a.toml", "status": "ok", "outputs": {}}
    (out / MANIFEST).write_text(json.dumps(good) + "\n" + '{"config": "/x/b.toml", "sta')
    assert read_manifest(out) == {"/x/a.toml": good}


def test_batch_cli_reports_failures(tmp_path):
    """The CLI: one broken config, exit status 2 (every failure is a bad input), no traceback."""
    cfg = tmp_path / "broken.toml"
    cfg.write_text(_BROKEN)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "rigmix.cli", "batch", str(cfg), "--out", str(out), "--workers", "0"],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "NoSuchJoint" in r.stderr
    assert "1 failed" in r.stdout + r.stderr
    assert read_manifest(out)[str(cfg.resolve())]["status"] == "failed"


def test_pool_workers_share_the_cores_out_among_their_threads(tmp_path):
    """Two workers on this machine each run at most ``cpu_count // 2`` numerical threads: the
    OpenBLAS that numpy loaded before the worker's start-up, and the libraries loaded later
    through the thread variables. Without the limit, each worker starts a thread per core."""
    import os

    from batch_probe import thread_limits

    from rigmix.batch import THREAD_VARIABLES, run_pool

    configs = make_configs(tmp_path / "configs", n=4, broken=-1)
    entries = []
    run_pool(configs, tmp_path / "out", 2, entries.append, job=thread_limits)
    share = str(max(1, (os.cpu_count() or 1) // 2))
    assert len(entries) == 4 and len({e["pid"] for e in entries}) == 2
    for e in entries:
        assert e["variables"] == {name: share for name in THREAD_VARIABLES}
        blas = {k: v for k, v in e["pools"].items() if k.startswith("openblas")}
        assert blas and all(v <= int(share) for v in blas.values()), e["pools"]
