"""The command line against careless and hostile use (issue 23, findings 4, 6, 7 and 8).

Outputs that would destroy an input are refused; SIGTERM during the write phase leaves no
temporary file and no running worker; a batch worker that dies fails its own job only; names
and paths cannot inject terminal escapes; error lines are short and a failed write names its file.

The signal and crash tests run ``rigmix`` in a subprocess with a ``sitecustomize`` written by the
test on ``PYTHONPATH`` (nothing in rigmix knows of it): it makes the glTF writer stop after
writing its temporary file (a marker says so, then the test sends the signal: no timing guess),
or makes the composition of one config crash its process with a real segmentation fault.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
from conftest import ROOT, asset, tail_config

from rigmix import examples
from rigmix.batch import MANIFEST, exit_status
from rigmix.cli import MAX_ERROR_CHARS, main
from rigmix.describe import describe, format_description, printable
from rigmix.safety import file_digest

BROKEN = """name = "broken"
[characters.human]
path = "builtin:humanoid"
[[actions]]
op = "remove"
target = "human"
target_joint = "NoSuchJoint"
"""

SITECUSTOMIZE = '''
import os

if os.environ.get("RIGMIX_TEST_HOLD"):  # stop in the write phase, once the temporary glTF exists
    import time

    import rigmix.io.gltf as _gltf

    _write = _gltf.write_gltf

    def write_gltf(character, path):
        _write(character, path)
        marker = os.path.join(os.environ["RIGMIX_TEST_HOLD"], str(os.getpid()))
        with open(marker + ".part", "w") as fh:
            fh.write(str(path))
        os.replace(marker + ".part", marker)
        time.sleep(600)

    _gltf.write_gltf = write_gltf

if os.environ.get("RIGMIX_TEST_CRASH"):  # a segmentation fault while composing the named config
    import ctypes

    import rigmix.pipeline as _pipeline

    _compose = _pipeline.compose

    def compose(config, **kw):
        if os.path.basename(str(config)).startswith(os.environ["RIGMIX_TEST_CRASH"]):
            ctypes.string_at(0)
        return _compose(config, **kw)

    _pipeline.compose = compose
'''


def _env(tmp_path, **extra):
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]), **extra)
    return env


def _start(args, env, cwd):
    return subprocess.Popen([sys.executable, "-m", "rigmix.cli", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, timeout=240.0, what="a condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _gone(pid) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _leftovers(folder: Path) -> list:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name.startswith(".rigmix")
                  or ".tmp" in p.name or p.name.startswith("."))


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("rigmix: error: ") and "Traceback" not in err
    return lines[0]


# --------------------------------------------------------------------------------------------
# Output paths (finding 6)
# --------------------------------------------------------------------------------------------


@pytest.fixture
def job(tmp_path, monkeypatch):
    """A folder with a real input character (a copy of the Fox) and a config using it."""
    folder = tmp_path / "job"
    folder.mkdir()
    (folder / "Fox.glb").write_bytes(asset("Fox").read_bytes())
    (folder / "fox.gltf").write_text(json.dumps({"asset": {"version": "2.0"}, "buffers": [
        {"uri": "fox%20data.bin", "byteLength": 4}]}))
    (folder / "fox data.bin").write_bytes(b"\0\0\0\0")
    (folder / "link.glb").symlink_to("Fox.glb")
    (folder / "c.toml").write_text(tail_config(extra='[characters.fox]\npath = "Fox.glb"'))
    monkeypatch.chdir(folder)
    return folder


@pytest.mark.parametrize("args, words", [
    (["-o", "Fox.glb"], "input character 'fox'"),
    (["-o", "./Fox.glb"], "input character 'fox'"),
    (["-o", "link.glb"], "input character 'fox'"),  # a symlink to the input
    (["-o", "out.glb", "--report", "Fox.glb"], "input character 'fox'"),
    (["-o", "out.glb", "--report", "c.toml"], "the config"),
    (["-o", "X.glb", "--report", "X.glb"], "same file"),
    (["-o", "X.glb", "--report", "../job/X.glb"], "same file"),
    (["-o", "out.glb", "--usd", "c.toml.usda", "--report", "c.toml.usda"], "same file"),
    (["-o", "out.glb", "--dump-fields", "c.toml"], "the config"),
])
def test_compose_refuses_outputs_that_are_inputs(job, capsys, args, words):
    before = {p.name: file_digest(p) for p in job.iterdir() if p.is_file()}
    assert main(["compose", "c.toml", *args, "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert words in line and ("choose another" in line or "own path" in line), line
    assert {p.name: file_digest(p) for p in job.iterdir() if p.is_file()} == before  # nothing written


def test_compose_refuses_a_gltf_buffer_as_output(job, capsys):
    (job / "c.toml").write_text(tail_config(extra='[characters.fox]\npath = "fox.gltf"'))
    from rigmix.config import load_config
    from rigmix.export import config_inputs

    assert (job / "fox data.bin").resolve() in [Path(p).resolve() for _, p in config_inputs(load_config("c.toml"))]
    assert main(["compose", "c.toml", "-o", "out.glb", "--report", "fox data.bin"]) == 2
    assert "a file of the input character 'fox'" in _one_error_line(capsys.readouterr().err)
    assert (job / "fox data.bin").read_bytes() == b"\0\0\0\0"


def test_batch_refuses_an_output_folder_where_outputs_hit_inputs(job, capsys):
    (job / "Fox.toml").write_text(tail_config(extra='[characters.fox]\npath = "Fox.glb"'))
    digest = file_digest(job / "Fox.glb")
    # Fox.toml's output Fox.glb would land on the input Fox.glb
    assert main(["batch", "Fox.toml", "--out", ".", "--workers", "0", "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "Fox.glb" in line and "input character 'fox' of Fox.toml" in line
    assert file_digest(job / "Fox.glb") == digest and not (job / MANIFEST).exists()


# --------------------------------------------------------------------------------------------
# Batch exit statuses (finding 7)
# --------------------------------------------------------------------------------------------


def test_exit_status():
    ok = {"status": "ok"}
    bad = {"status": "failed", "error_kind": "input"}
    bug = {"status": "failed", "error_kind": "internal"}
    assert exit_status([ok, dict(ok, skipped=True)]) == 0
    assert exit_status([ok, bad, bad]) == 2
    assert exit_status([ok, bad, bug]) == 1
    assert exit_status([{"status": "failed"}]) == 1  # unknown kind: not known to be the input's fault


def test_batch_of_bad_inputs_exits_2(tmp_path, capsys):
    (tmp_path / "broken.toml").write_text(BROKEN)
    assert main(["batch", str(tmp_path / "broken.toml"), "--out", str(tmp_path / "out"), "--workers", "0",
                 "--no-progress"]) == 2
    assert "NoSuchJoint" in capsys.readouterr().err
    (entry,) = [json.loads(x) for x in (tmp_path / "out" / MANIFEST).read_text().splitlines()]
    assert entry["status"] == "failed" and entry["error_kind"] == "input"


@pytest.mark.slow
def test_a_dying_worker_fails_its_own_job_only(tmp_path):
    """A real segmentation fault in one job: that job fails (internal, exit 1), the others finish."""
    cfgs = tmp_path / "configs"
    cfgs.mkdir()
    names = ["a_crash", "b_tail", "c_tail", "d_broken"]
    for n in names:
        (cfgs / f"{n}.toml").write_text(BROKEN if "broken" in n else tail_config(extra=""))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "rigmix.cli", "batch", *[cfgs / f"{n}.toml" for n in names],
                        "--out", out, "--workers", "2", "--no-progress"], cwd=ROOT, capture_output=True, text=True,
                       env=_env(tmp_path, RIGMIX_TEST_CRASH="a_crash"), timeout=800)
    assert r.returncode == 1, r.stderr
    entries = {Path(e["config"]).stem: e for e in map(json.loads, (out / MANIFEST).read_text().splitlines())}
    assert sorted(entries) == names
    assert entries["a_crash"]["status"] == "failed" and entries["a_crash"]["error_kind"] == "internal"
    assert "worker process died" in entries["a_crash"]["error"]
    assert entries["b_tail"]["status"] == entries["c_tail"]["status"] == "ok"
    assert entries["d_broken"]["error_kind"] == "input"
    assert sorted(p.name for p in out.glob("*.glb")) == ["b_tail.glb", "c_tail.glb"]
    assert _leftovers(out) == []


# --------------------------------------------------------------------------------------------
# Signals (findings 6 and 7)
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_sigterm_while_writing_leaves_nothing(tmp_path):
    (tmp_path / "tail.toml").write_text(tail_config(extra=""))
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    proc = _start(["compose", tmp_path / "tail.toml", "-o", out / "tail.glb", "--report", out / "tail.json",
                   "--no-progress"], _env(tmp_path, RIGMIX_TEST_HOLD=str(hold)), cwd=tmp_path)
    try:
        _wait_for(lambda: _held(hold) or proc.poll() is not None, what="the write phase")
        assert proc.poll() is None, proc.communicate()
        staged = Path((hold / str(proc.pid)).read_text())
        assert staged.is_file() and staged.parent.parent == out and staged.parent.name.startswith(".rigmix-")
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "interrupted (SIGTERM)" in _one_error_line(stderr)
    assert list(out.iterdir()) == []  # no output, no temporary folder or file


def _held(hold):
    """Process ids holding in the write phase: their markers in ``hold`` (a ``.part`` file is one
    being written, not yet a marker)."""
    return sorted(int(p.name) for p in hold.iterdir() if p.name.isdigit())


@pytest.mark.slow
def test_sigterm_stops_the_batch_workers(tmp_path):
    cfgs = tmp_path / "configs"
    cfgs.mkdir()
    paths = []
    for k in range(4):
        paths.append(cfgs / f"t{k}.toml")
        paths[-1].write_text(tail_config(extra=""))
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "out"
    proc = _start(["batch", *paths, "--out", out, "--workers", "2", "--no-progress"],
                  _env(tmp_path, RIGMIX_TEST_HOLD=str(hold)), cwd=tmp_path)
    children = []
    try:
        # both workers are in the write phase, their temporary files in the output folder
        _wait_for(lambda: len(_held(hold)) >= 2 or proc.poll() is not None, timeout=600,
                  what="two workers in the write phase")
        assert proc.poll() is None, proc.communicate()
        workers = _held(hold)
        children = [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
        assert len(workers) == 2 and set(workers) <= set(children)
        assert len(_leftovers(out)) >= 2
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 128 + signal.SIGTERM, stderr
        assert "interrupted (SIGTERM)" in stderr and "Traceback" not in stderr
        _wait_for(lambda: all(_gone(pid) for pid in children), timeout=30, what="the workers to exit")
    finally:
        for pid in children:  # only if the test failed: never leave them running
            if not _gone(pid):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
    assert _leftovers(out) == [] and list(out.glob("*.glb")) == []
    manifest = out / MANIFEST
    assert not manifest.exists() or manifest.read_text() == ""  # nothing finished, nothing recorded


# --------------------------------------------------------------------------------------------
# Terminal injection (finding 8) and error lines (finding 4)
# --------------------------------------------------------------------------------------------

EVIL = ["Hips\x1b[2J\x1b[31m", "Spine\nrigmix: error: forged", "Chest\x9b31m", "Neck\u202eevil", "Head\x7f\u2066x"]


def _evil_character():
    import dataclasses

    h = examples.humanoid()
    names = list(h.skeleton.names)
    names[: len(EVIL)] = EVIL
    skeleton = dataclasses.replace(h.skeleton, names=tuple(names))
    clips = tuple(dataclasses.replace(c, name=c.name + "\x1b]0;title\x07") for c in h.clips)
    return dataclasses.replace(h, skeleton=skeleton, clips=clips)


def _raw_controls(text: str) -> list:
    return [c for c in text if (ord(c) < 32 and c != "\n") or 0x7f <= ord(c) <= 0x9f
            or 0x202a <= ord(c) <= 0x202e or 0x2066 <= ord(c) <= 0x2069]


def test_printable():
    assert printable("a\x1b[31mb") == "a\\x1b[31mb"
    assert printable("x\ny\x9b\u202e\u2066") == "x\\x0ay\\x9b\\u202e\\u2066"
    assert printable("Épaule_L 肩 🦊\u200d") == "Épaule_L 肩 🦊\u200d"  # letters and joiners kept


def test_inspect_escapes_names(tmp_path, capsys):
    from rigmix.io.gltf import write_gltf

    path = tmp_path / "evil\x1b[5m.glb"
    write_gltf(_evil_character(), path)
    assert main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    assert _raw_controls(text) == []
    assert not any(line.startswith("rigmix: error") for line in text.splitlines())  # no forged line
    assert "Hips\\x1b[2J\\x1b[31m  t=(" in text and "Neck\\u202eevil" in text
    assert main(["inspect", str(path), "--json"]) == 0
    raw = capsys.readouterr().out
    assert _raw_controls(raw) == [] and "\\u001b" not in raw  # JSON shows the same escapes as the text
    d = json.loads(raw)
    assert [j["name"] for j in d["joints"]][: len(EVIL)] == [printable(n) for n in EVIL]
    assert d["file"].endswith("evil\\x1b[5m.glb")
    assert all(c["name"].endswith("\\x1b]0;title\\x07") for c in d["clips"])
    assert d["joints"][1]["parent"] == printable(EVIL[0]) and d["joints"][1]["parent_index"] == 0


def test_tree_does_not_depend_on_escaped_names():
    """Two joints whose names escape to the same text: the tree is built by index and ends."""
    import dataclasses

    h = examples.humanoid()
    names = list(h.skeleton.names)
    names[0], names[1] = "a\x1b", "a\\x1b"  # the second is the first one's escaped text, literally
    d = describe(dataclasses.replace(h, skeleton=dataclasses.replace(h.skeleton, names=tuple(names))))
    lines = [ln for ln in format_description(d).splitlines() if "t=(" in ln]
    assert len(lines) == h.skeleton.num_joints


def test_error_lines_are_escaped_and_capped(tmp_path, capsys):
    missing = tmp_path / "no\x1b[2Jsuch\nfile.glb"
    assert main(["inspect", str(missing)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "no\\x1b[2Jsuch" in line and _raw_controls(line) == []
    cfg = tmp_path / "long.toml"
    cfg.write_text(BROKEN.replace("NoSuchJoint", "J" * 20000))
    assert main(["compose", str(cfg), "-o", str(tmp_path / "x.glb"), "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert len(line) <= MAX_ERROR_CHARS and line.endswith("\u2026")


@pytest.mark.slow
def test_a_failed_write_names_the_output(tmp_path):
    """A write that fails half way (here the file-size limit, as a full disk would): exit 2, one short
    line naming the output and the fix, no file and no temporary file left."""
    (tmp_path / "tail.toml").write_text(tail_config(extra=""))
    out = tmp_path / "out"
    out.mkdir()

    def limit():  # files up to 64 kB: the composed GLB (~1 MB) cannot be written
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 << 10, 64 << 10))

    r = subprocess.run([sys.executable, "-m", "rigmix.cli", "compose", tmp_path / "tail.toml", "-o",
                        out / "tail.glb", "--no-progress"], cwd=ROOT, capture_output=True, text=True,
                       preexec_fn=limit, timeout=600)
    assert r.returncode == 2, r.stderr
    line = _one_error_line(r.stderr)
    assert "cannot write" in line and "tail.glb" in line and "free some space" in line, line
    assert len(line) <= MAX_ERROR_CHARS
    assert list(out.iterdir()) == []
