"""Hostile and careless numbers (issue 23, findings 2 to 5): every one is refused with one line
naming the file, the object and the fix (exit status 2), never a crash, an internal error, or a
file with NaN or infinity in it.

Characters are built here from the built-in humanoid (written to a GLB in a temporary folder,
then edited: JSON nodes, inverse bind matrices in the BIN chunk); configs are written beside
them. The native crash (a 1e308 placement reaching libigl) is run 20 times in fresh processes.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import struct
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from rigmix.config import load_config
from rigmix.errors import InputError
from rigmix.geometry import MAX_GRID_VOXELS, check_coordinates, check_float32, check_grid_voxels, check_transforms

BODY = '[characters.body]\npath = "{body}"\n'
DONOR = '[characters.donor]\npath = "builtin:humanoid"\n'
REPLACE = ('[[actions]]\nop = "replace"\nsource = "{source}"\nsource_joint = "{joint}"\ntarget = "body"\n'
           'target_joint = "{joint}"\n')


def _config(tmp_path, text, name="bad.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _arm_config(body="builtin:humanoid", body_extra="", donor_extra="", tail="", joint="UpperArm.L"):
    return (BODY.format(body=body) + body_extra + DONOR + donor_extra
            + REPLACE.format(source="donor", joint=joint) + tail)


def rigmix(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "rigmix.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def _one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip() and "WARNING" not in ln]
    assert len(lines) == 1 and lines[0].startswith("rigmix: error: "), stderr[-2000:]
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr[-2000:]
    return lines[0]


def assert_compose_refused(capsys, tmp_path, cfg, match, name=None):
    """``rigmix compose`` in this process: exit 2, one line naming ``name`` (default: the config)
    and matching ``match``; no output file."""
    from rigmix.cli import main

    out = tmp_path / "out.glb"
    capsys.readouterr()
    rc = main(["compose", str(cfg), "-o", str(out), "--usd", str(tmp_path / "out.usda"), "--no-progress"])
    _, err = capsys.readouterr()
    assert rc == 2, err[-2000:]
    line = _one_line(err)
    assert (name or cfg.name) in line, line
    import re

    assert re.search(match, line), line
    assert not out.exists() and not (tmp_path / "out.usda").exists()
    return line


# --------------------------------------------------------------------------- hostile characters


def _glb_parts(raw: bytes):
    n = struct.unpack_from("<I", raw, 12)[0]
    return json.loads(raw[20:20 + n]), raw[28 + n:]


def _glb(gl: dict, data: bytes) -> bytes:
    text = json.dumps(gl).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(data), 0x004E4942) + data
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


@pytest.fixture(scope="module")
def humanoid_glb(tmp_path_factory):
    from rigmix.examples import humanoid
    from rigmix.io.gltf import write_gltf

    path = tmp_path_factory.mktemp("humanoid") / "base.glb"
    write_gltf(humanoid(), path)
    return path.read_bytes()


def _edit_node(raw, joint, **fields):
    gl, data = _glb_parts(raw)
    gl = copy.deepcopy(gl)
    node = next(n for n in gl["nodes"] if n.get("name") == joint)
    if "matrix" in fields:
        for key in ("translation", "rotation", "scale"):
            node.pop(key, None)
    node.update(fields)
    return _glb(gl, data)


def _edit_ibm(raw, joint, value):
    gl, data = _glb_parts(raw)
    skin = gl["skins"][0]
    acc = gl["accessors"][skin["inverseBindMatrices"]]
    view = gl["bufferViews"][acc["bufferView"]]
    names = [n.get("name") for n in gl["nodes"]]
    j = skin["joints"].index(names.index(joint))
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0) + 64 * j
    b = bytearray(data)
    b[start:start + 64] = np.full(16, value, np.float32).tobytes()
    return _glb(gl, bytes(b))


def _edit_key_times(raw, clip, factor):
    """Every key time of the first sampler of animation ``clip`` multiplied by ``factor``."""
    gl, data = _glb_parts(raw)
    acc = gl["accessors"][gl["animations"][clip]["samplers"][0]["input"]]
    start = gl["bufferViews"][acc["bufferView"]].get("byteOffset", 0) + acc.get("byteOffset", 0)
    b = bytearray(data)
    times = np.frombuffer(data, np.float32, acc["count"], start) * np.float32(factor)
    b[start:start + 4 * acc["count"]] = times.astype(np.float32).tobytes()
    acc["min"], acc["max"] = [float(times.min())], [float(times.max())]
    return _glb(gl, bytes(b))


HOSTILE_CHARACTERS = {
    # case: (edit of the GLB, pattern of the message)
    "zero_scale": (lambda raw: _edit_node(raw, "LowerArm.R", scale=[0.0, 0.0, 0.0]),
                   "joint 'LowerArm.R' rest world matrix is singular.*non-zero scale"),
    "zero_matrix": (lambda raw: _edit_node(raw, "LowerArm.R", matrix=[0.0] * 16),
                    "joint 'LowerArm.R' rest world matrix is singular"),
    "singular_inverse_bind": (lambda raw: _edit_ibm(raw, "LowerArm.R", 0.0),
                              # refused by the reader (not affine) before positioning sees it
                              "joint 'LowerArm.R'.*(inverse bind matri|not affine)"),
    # a mirrored joint composed with exit 0 and clips that turned the wrong way (identity gate 0.51)
    "negative_scale": (lambda raw: _edit_node(raw, "LowerArm.R", scale=[-1.0, 1.0, 1.0]),
                       "joint 'LowerArm.R' rest world matrix mirrors.*Apply Scale"),
    "joint_translation_1e300": (lambda raw: _edit_node(raw, "Hand.R", translation=[1e300, 0.0, 0.0]),
                                "skeleton reaches 1e\\+300 m.*out of range"),
    "joint_translation_1e39": (lambda raw: _edit_node(raw, "Hand.R", translation=[1e39, 0.0, 0.0]),
                               "skeleton reaches 1e\\+39 m"),
    "joint_scale_1e300": (lambda raw: _edit_node(raw, "Hand.R", scale=[1e300, 1e300, 1e300]),
                          "joint 'Hand.R' rest world matrix has NaN or infinite entries"),
    "clip_key_times_1e30": (lambda raw: _edit_key_times(raw, 0, 1e30),
                            "clip 'walk': runs from 0 to 1e\\+30 s.*trim its key times"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_CHARACTERS))
def test_hostile_character_is_refused_by_compose(case, humanoid_glb, tmp_path, capsys):
    """Each of these gave LinAlgError (exit 1) or exit 0 with NaN/Infinity in the GLB."""
    edit, match = HOSTILE_CHARACTERS[case]
    glb = tmp_path / f"{case}.glb"
    glb.write_bytes(edit(humanoid_glb))
    before = glb.read_bytes()
    cfg = _config(tmp_path, _arm_config(body=glb.name, joint="UpperArm.L"))
    line = assert_compose_refused(capsys, tmp_path, cfg, match, name=glb.name)
    assert glb.read_bytes() == before
    assert line.startswith(f"rigmix: error: {glb.name}: ")  # the file first, then the object


@pytest.mark.parametrize("case", sorted(HOSTILE_CHARACTERS))
def test_inspect_refuses_a_hostile_character_with_composes_line(case, humanoid_glb, tmp_path, capsys):
    """``rigmix inspect`` exited 0 on these: it applies compose's check on input files
    (:func:`rigmix.pipeline.check_input`), so both print the same line."""
    from rigmix.cli import main

    edit, match = HOSTILE_CHARACTERS[case]
    glb = tmp_path / f"{case}.glb"
    glb.write_bytes(edit(humanoid_glb))
    capsys.readouterr()
    rc = main(["inspect", str(glb)])
    err = capsys.readouterr().err
    assert rc == 2, err[-2000:]
    line = _one_line(err)
    import re

    assert re.search(match, line) and line.startswith(f"rigmix: error: {glb.name}: "), line
    cfg = _config(tmp_path, _arm_config(body=glb.name, joint="UpperArm.L"))
    assert rc == main(["compose", str(cfg), "-o", str(tmp_path / "out.glb"), "--no-progress"])
    assert _one_line(capsys.readouterr().err) == line


# --------------------------------------------------------------------------- configs


BAD_CONFIGS = {
    # case: (config text, pattern of the message)
    "donor_scale_1e9": (_arm_config(donor_extra="scale = 1e9\n"), "characters.donor.scale.*\\[0.0001, 10000\\]"),
    "donor_scale_1e-9": (_arm_config(donor_extra="scale = 1e-9\n"), "characters.donor.scale.*1e-09"),
    "placement_1e308": (_arm_config(body_extra="placement = { translation = [1e308, 0, 0] }\n"),
                        "characters.body.placement.translation\\[0\\]"),
    "placement_rotation_huge": (_arm_config(body_extra="placement = { rotation = [1e300, 0, 0] }\n"),
                                "characters.body.placement.rotation.euler\\[0\\]"),
    "rest_rotation_huge_quaternion": (_arm_config(body_extra='[characters.body.rotations]\n'
                                                              '"UpperArm.R" = [1e300, 0, 0, 1e300]\n'),
                                      "characters.body.rotations.*quaternion\\[0\\]"),
    "smooth_iterations_text": (_arm_config(tail='[fusion]\nsmooth_iterations = "ten"\n'),
                               "fusion.smooth_iterations"),
    "voxel_factor_negative": (_arm_config(tail="[fusion]\nvoxel_factor = -1\n"), "fusion.voxel_factor"),
    "max_voxels_huge": (_arm_config(tail="[fusion]\nmax_voxels = 2000000000\n"), "fusion.max_voxels"),
    "margin_voxels_huge": (_arm_config(tail="[fusion]\nmargin_voxels = 1000\n"), "margin_voxels.*max_voxels"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_numbers_refused_at_load(case, tmp_path, capsys):
    text, match = BAD_CONFIGS[case]
    cfg = _config(tmp_path, text)
    with pytest.raises(InputError, match=match) as e:
        load_config(cfg)
    assert "\n" not in str(e.value) and "bad.toml" in str(e.value)
    assert_compose_refused(capsys, tmp_path, cfg, match)


def test_native_crash_case_20_times(tmp_path):
    """A 1e308 placement crashed libigl (exit 139) in about 30% of runs: now exit 2, one line,
    in a fresh process each time. The refusal is the config's bound, before any native code: a
    run that gets its message never reached the crash, so a few runs show it as well as 20."""
    cfg = _config(tmp_path, _arm_config(body_extra="placement = { translation = [1e308, 0, 0] }\n"))
    for _ in range(3):
        r = rigmix("compose", cfg, "-o", tmp_path / "out.glb", "--no-progress", timeout=120)
        assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
        line = _one_line(r.stderr)
        assert "bad.toml" in line and "characters.body.placement.translation[0]" in line, line
        assert not (tmp_path / "out.glb").exists()


def test_fusion_entry_refuses_huge_coordinates_in_a_fresh_process(tmp_path):
    """The native kernels are never given 1e308: ``fuse_surfaces`` itself refuses it, in fresh
    processes (the crash was intermittent; the refusal's own message shows that a run stopped
    before the kernels, so a few runs show it as well as 20)."""
    script = tmp_path / "fuse.py"
    script.write_text(
        "import numpy as np\n"
        "from rigmix.errors import InputError\n"
        "from rigmix.fusion import FusionAction, FusionInput, fuse_surfaces\n"
        "V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)\n"
        "F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])\n"
        "W = np.tile([1.0, 0.0], (4, 1))\n"
        "a = FusionInput(V, F, W, np.array([True, True]), name='a')\n"
        "b = FusionInput(V + [1e308, 0, 0], F, W[:, ::-1], np.array([True, True]), name='b')\n"
        "try:\n"
        "    fuse_surfaces([a, b], [FusionAction('replace', 0, 1)])\n"
        "except InputError as e:\n"
        "    print(e)\n"
        "    raise SystemExit(2)\n")
    for _ in range(3):
        r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
        assert "fusion: input 1 ('b') reaches 1e+308 m" in r.stdout


def test_config_that_passes_load_but_overflows_is_refused(tmp_path, capsys):
    """A placement within the load bounds (1e6 m) that puts a 1.8 m body 1e5 m away from its
    donor: refused before the fusion, naming the config and what to change."""
    cfg = _config(tmp_path, _arm_config(body_extra="placement = { translation = [1e5, 0, 0] }\n"))
    load_config(cfg)  # within the load bounds
    assert_compose_refused(capsys, tmp_path, cfg, "character 'body'.*more than 1e\\+04 times.*placement")


def test_removing_the_root_is_refused(tmp_path, capsys):
    """Gave "csgraph must be lil, csr, or csc format" (exit 1); with a second character it gave
    exit 0 and that character alone."""
    text = ('[characters.body]\npath = "builtin:humanoid"\n'
            '[[actions]]\nop = "remove"\ntarget = "body"\ntarget_joint = "Hips"\n')
    why = "actions\\[0\\] removes 'Hips', the root of every joint of character 'body'"
    assert_compose_refused(capsys, tmp_path, _config(tmp_path, text), why)
    two = text.replace('[[actions]]', '[characters.donor]\npath = "builtin:quadruped"\n[[actions]]')
    assert_compose_refused(capsys, tmp_path, _config(tmp_path, two), why)


def test_one_target_joint_replaced_twice_is_refused(tmp_path, capsys):
    """Fused three arms at one shoulder (exit 0)."""
    text = (_arm_config() + '[characters.donor2]\npath = "builtin:humanoid"\n'
            + REPLACE.format(source="donor2", joint="UpperArm.L"))
    assert_compose_refused(capsys, tmp_path, _config(tmp_path, text),
                           "actions\\[0\\] \\(replace\\) and actions\\[1\\] \\(replace\\).*'UpperArm.L'")


def test_automatic_scale_out_of_range_is_refused(humanoid_glb, tmp_path, capsys):
    """A donor 1e6 times smaller than the body (its file's root scale): the automatic scale is
    refused, naming the option to set."""
    glb = tmp_path / "tiny.glb"
    glb.write_bytes(_edit_node(humanoid_glb, "Hips", scale=[1e-6, 1e-6, 1e-6], translation=[0.0, 0.95e-6, 0.0]))
    text = (BODY.format(body="builtin:humanoid") + f'[characters.donor]\npath = "{glb.name}"\n'
            + REPLACE.format(source="donor", joint="UpperArm.L"))
    assert_compose_refused(capsys, tmp_path, _config(tmp_path, text),
                           "automatic scale of character 'donor'.*characters.donor.scale")


# --------------------------------------------------------------------------- the guards


def test_check_coordinates():
    ok = {"a": np.array([[0.0, 0, 0], [1, 1, 1]]), "b": np.zeros((0, 3))}
    assert check_coordinates(ok, where="t", fix="f") == pytest.approx(np.sqrt(3))
    for bad, match in [({"a": [[np.nan, 0, 0]]}, "'?a'? has non-finite"), ({"a": [[0, np.inf, 0]]}, "non-finite"),
                       ({"a": [[2e6, 0, 0]]}, "beyond the limit"),
                       ({"a": [[1e5, 0, 0], [1e5 + 1, 0, 0]], "b": [[1e5, 1, 0]]}, "a lies 1e\\+05")]:
        with pytest.raises(InputError, match=match):
            check_coordinates(bad, where="t", fix="f")


def test_check_transforms():
    M = np.tile(np.eye(4), (3, 1, 1))
    check_transforms(M, ["a", "b", "c"], where="t", what="m", fix="f")
    M[1, :3, :3] = np.diag([1.0, 1.0, 0.0])
    with pytest.raises(InputError, match="joint 'b' m is singular"):
        check_transforms(M, ["a", "b", "c"], where="t", what="m", fix="f")
    M[1] = np.nan
    with pytest.raises(InputError, match="joint 'b' m has NaN"):
        check_transforms(M, ["a", "b", "c"], where="t", what="m", fix="f")


def test_check_float32_and_grid():
    assert check_float32([1.0, -3e38], "x").dtype == np.float32
    for v in (np.nan, 1e39, -np.inf):
        with pytest.raises(InputError, match="x holds"):
            check_float32([0.0, v], "x")
    with pytest.raises(InputError, match="x holds"):
        check_float32([7e4], "x", dtype=np.float16)
    check_grid_voxels((100, 100, 100), where="fusion", limit=4_000_000)
    with pytest.raises(InputError, match="max_voxels is at most"):
        check_grid_voxels((10 ** 7, 10 ** 7, 10 ** 7), where="fusion", limit=4_000_000)  # no int64 overflow
    with pytest.raises(InputError):
        check_grid_voxels((300, 300, 300), where="fusion", limit=10 ** 9)  # capped at MAX_GRID_VOXELS
    assert 300 ** 3 > MAX_GRID_VOXELS


def test_cluster_grid_bounded_before_allocating():
    from rigmix.fusion import FusionParams
    from rigmix.fusion.seams import cluster_grid

    lo, hi = np.zeros(3), np.ones(3)
    grid = cluster_grid(lo, hi, 0.01, FusionParams())
    assert np.prod(grid.shape) <= FusionParams().max_voxels
    with pytest.raises(InputError, match="margin_voxels"):
        cluster_grid(lo, hi, 0.01, FusionParams(margin_voxels=1000.0))


# --------------------------------------------------------------------------- the writers


@pytest.fixture(scope="module")
def character(humanoid_glb, tmp_path_factory):
    from rigmix.io import load_character

    path = tmp_path_factory.mktemp("ch") / "h.glb"
    path.write_bytes(humanoid_glb)
    return load_character(path)


def _variants(ch):
    """In-memory characters that would write NaN or infinity, and the object each names."""
    sk = ch.skeleton
    ib = np.array(sk.inverse_binds)
    ib[3] = np.nan
    yield "ibm_nan", dataclasses.replace(ch, skeleton=dataclasses.replace(sk, inverse_binds=ib)), \
        f"joint '{sk.names[3]}' inverse bind matrix"
    t = np.array(sk.translations)
    t[5, 0] = 1e300
    yield "translation_1e300", dataclasses.replace(ch, skeleton=dataclasses.replace(sk, translations=t)), \
        {".glb": f"joint '{sk.names[5]}' translation", ".usda": "translations holds 1e\\+300"}
    m = ch.meshes[0]
    V = np.array(m.positions)
    V[7, 1] = 1e39
    yield "position_1e39", dataclasses.replace(ch, meshes=(dataclasses.replace(m, positions=V),) + ch.meshes[1:]), \
        {".glb": f"mesh '{m.name}' POSITION holds 1e\\+39", ".usda": f"mesh '{m.name}' points holds 1e\\+39"}
    uv = np.array(m.uvs[0])
    uv[0, 0] = np.nan
    yield "uv_nan", dataclasses.replace(ch, meshes=(dataclasses.replace(m, uvs=(uv,)),) + ch.meshes[1:]), \
        {".glb": f"mesh '{m.name}' TEXCOORD_0 holds nan", ".usda": f"mesh '{m.name}' st holds nan"}
    c = ch.clips[0]
    tr = c.tracks[1]
    vals = np.array(tr.values)
    vals[2, 0] = np.nan
    tracks = list(c.tracks)
    tracks[1] = dataclasses.replace(tr, values=vals)
    yield "clip_nan", dataclasses.replace(ch, clips=(dataclasses.replace(c, tracks=tuple(tracks)),) + ch.clips[1:]), \
        f"clip '{c.name}' {tr.path} track of joint '{sk.names[tr.joint]}' values holds nan"


@pytest.mark.parametrize("suffix", [".glb", ".gltf", ".usda"])
def test_writers_refuse_non_finite_values(character, suffix, tmp_path):
    from rigmix.io.gltf import write_gltf
    from rigmix.io.usd import write_usd

    write = write_usd if suffix == ".usda" else write_gltf
    for case, ch, match in _variants(character):
        match = match.get(suffix, match.get(".glb")) if isinstance(match, dict) else match
        out = tmp_path / f"{case}{suffix}"
        with pytest.raises(InputError, match=match) as e:
            write(ch, out)
        assert out.name in str(e.value) and "\n" not in str(e.value), case
        assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == [], case
    write(character, tmp_path / f"ok{suffix}")  # the unchanged character still writes
    if suffix != ".usda":
        text = (tmp_path / f"ok{suffix}").read_bytes()
        assert b"NaN" not in text and b"Infinity" not in text
