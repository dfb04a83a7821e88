"""Bad inputs, generated here (no committed binaries): each gives one clear RigmixError through
the API and the CLI (one line, exit status 2, no traceback), or is repaired with a warning;
the input file is never modified, no output file is left behind, memory stays bounded.

The reader's own messages are tested in ``test_gltf_io.py`` and the CLI's basic cases
(truncated file, corrupted JSON, not glTF) in ``test_cli.py``; this corpus adds the structural
defects (chunk lengths, header bit flips, ranges, NaN, hierarchy, skins, huge sizes, 100k joints)
and runs every one of them both ways, with the hash of the input checked before and after.
"""

from __future__ import annotations

import json
import logging
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import ROOT
from hostile import glb as glb_bytes

from rigmix.config import load_config
from rigmix.errors import InputError, RigmixError, UnsupportedError
from rigmix.io import load_character
from rigmix.io.gltf import read_gltf
from rigmix.safety import file_digest

# --------------------------------------------------------------------------- builders


def tiny_skinned(J: int = 3, *, shape: str = "chain", same_names: bool = False, V=None, F=None, W=None,
                 joints=None) -> tuple[dict, bytes]:
    """A small skinned glTF: ``J`` joints (a chain, or a star under joint 0), one mesh ``Body``
    (default: a unit quad of 2 triangles, vertex ``i`` bound to joint ``i % J``), one clip.

    Returns the JSON dict and the BIN bytes; the skin's joints are nodes ``0..J-1`` and the mesh
    node is node ``J``.
    """
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32) if V is None else np.asarray(V, np.float32)
    F = np.array([[0, 1, 2], [1, 3, 2]], np.uint32) if F is None else np.asarray(F, np.uint32)
    n = len(V)
    big = J > 65535
    if joints is None:
        joints = np.zeros((n, 4), np.uint32 if big else np.uint16)
        joints[:, 0] = np.arange(n) % J
    if W is None:
        W = np.zeros((n, 4), np.float32)
        W[:, 0] = 1.0
    data, views, accs = bytearray(), [], []

    def acc(a, ctype, typ):
        a = np.ascontiguousarray(a)
        data.extend(b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": len(data), "byteLength": a.nbytes})
        data.extend(a.tobytes())
        accs.append({"bufferView": len(views) - 1, "componentType": ctype, "count": len(a), "type": typ})
        return len(accs) - 1

    nodes = [{"name": "Bone" if same_names else f"j{j}",
              "translation": [0.0, 0.1, 0.0] if shape == "chain" else [0.001 * j, 0.0, 0.0]} for j in range(J)]
    if J > 1:
        if shape == "chain":
            for j in range(J - 1):
                nodes[j]["children"] = [j + 1]
        else:
            nodes[0]["children"] = list(range(1, J))
    nodes.append({"name": "Body", "mesh": 0, "skin": 0})
    pos = acc(V, 5126, "VEC3")
    accs[pos]["min"], accs[pos]["max"] = V.min(0).tolist(), V.max(0).tolist()
    ind = acc(F.reshape(-1), 5125, "SCALAR")
    jt = acc(joints, 5125 if joints.dtype == np.uint32 else 5123, "VEC4")
    wt = acc(W, 5126, "VEC4")
    # inverse binds: identity is fine for the reader; rest worlds are only translations here
    ibm = acc(np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (J, 1)), 5126, "MAT4")
    times = acc(np.array([0.0, 1.0], np.float32), 5126, "SCALAR")
    accs[times]["min"], accs[times]["max"] = [0.0], [1.0]
    rots = acc(np.array([[0, 0, 0, 1], [0, 0, 0.38268343, 0.9238795]], np.float32), 5126, "VEC4")
    gl = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, J]}],
        "nodes": nodes,
        "skins": [{"joints": list(range(J)), "inverseBindMatrices": ibm}],
        "meshes": [{"name": "Body", "primitives": [{
            "attributes": {"POSITION": pos, "JOINTS_0": jt, "WEIGHTS_0": wt}, "indices": ind}]}],
        "animations": [{"name": "bend", "samplers": [{"input": times, "output": rots}],
                        "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}]}],
        "accessors": accs,
        "bufferViews": views,
        "buffers": [{"byteLength": len(data) + (-len(data) % 4)}],
    }
    return gl, bytes(data)


def _mutated(mutate=None, **kw) -> bytes:
    gl, data = tiny_skinned(**kw)
    if mutate is not None:
        mutate(gl)
    return glb_bytes(gl, data)


def _chunk_header_offsets(raw: bytes) -> tuple[int, int]:
    """Byte offsets of the JSON and BIN chunk headers."""
    json_len = struct.unpack_from("<I", raw, 12)[0]
    return 12, 20 + json_len


def _set_u32(raw: bytes, offset: int, value: int) -> bytes:
    b = bytearray(raw)
    struct.pack_into("<I", b, offset, value & 0xFFFFFFFF)
    return bytes(b)


def _flip(raw: bytes, offset: int, bit: int) -> bytes:
    b = bytearray(raw)
    b[offset] ^= 1 << bit
    return bytes(b)


def _base() -> bytes:
    return _mutated()


def _set(path: list, value):
    """A mutation setting ``gl[path...] = value``."""

    def mutate(gl):
        obj = gl
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value

    return mutate


def _attr(gl, key):
    return gl["accessors"][gl["meshes"][0]["primitives"][0]["attributes"][key]]


def _cycle(gl):
    gl["nodes"][2]["children"] = [0]  # j0 -> j1 -> j2 -> j0


def _huge_view(gl):
    gl["bufferViews"][0]["byteLength"] = 1 << 40


def _huge_zero_accessor(gl):
    a = _attr(gl, "POSITION")
    del a["bufferView"]
    a["count"] = 1 << 40


def _two_trees(gl):
    gl["nodes"][0]["children"] = []  # j0 and j1 > j2: a forest of 2 roots
    gl["scenes"][0]["nodes"] = [0, 1, 3]


def _mesh_node_is_joint(gl):
    gl["skins"][0]["joints"].append(3)  # the skinned mesh node itself listed as a joint
    gl["accessors"][gl["skins"][0]["inverseBindMatrices"]]["count"] = 3  # still 3 matrices: refused


def _no_primitives(gl):
    gl["meshes"][0]["primitives"] = []


NAN = float("nan")
INF = float("inf")
_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)


def _with_nan(a, value, at=(1, 0)):
    a = np.array(a, np.float32)
    a[at] = value
    return a


def _weights(value):
    W = np.zeros((4, 4), np.float32)
    W[:, 0] = 1.0
    W[2, 0] = value
    return W


#: id -> (bytes factory, regex the one-line error must match)
ERRORS = {
    # container: chunk lengths, header bit flips, truncation inside the BIN chunk
    "truncated_bin": (lambda: _base()[:-40], "truncated"),
    "magic_bit_flip": (lambda: _flip(_base(), 0, 5), "not a glTF file"),
    "version_bit_flip": (lambda: _flip(_base(), 4, 0), "GLB version 3"),
    "header_length_huge": (lambda: _set_u32(_base(), 8, 0xFFFFFFFF), "truncated"),
    "json_chunk_length_huge": (lambda: _set_u32(_base(), 12, 0xFFFFFFF0), "truncated"),
    "json_chunk_length_short": (lambda: _set_u32(_base(), 12, struct.unpack_from("<I", _base(), 12)[0] - 8),
                                "truncated|corrupt"),
    "bin_chunk_length_huge": (lambda: _set_u32(_base(), _chunk_header_offsets(_base())[1], 1 << 31), "truncated"),
    "bin_chunk_length_short": (
        lambda: _set_u32(_base(), _chunk_header_offsets(_base())[1],
                         struct.unpack_from("<I", _base(), _chunk_header_offsets(_base())[1])[0] - 16),
        "truncated|declares byteLength"),
    "json_type_bit_flip": (lambda: _flip(_base(), 16, 1), "first chunk is not a JSON chunk"),
    "json_nested_deeply": (lambda: glb_bytes(b'{"asset": {"version": "2.0"}, "extras": ' + b"[" * 100_000
                                             + b"]" * 100_000 + b"}"), "nested too deeply"),
    # declared sizes: refused before anything is allocated
    "buffer_byte_length_huge": (lambda: _mutated(_set(["buffers", 0, "byteLength"], 1 << 40)), "declares byteLength"),
    "buffer_view_huge": (lambda: _mutated(_huge_view), "spans bytes"),
    "accessor_count_huge": (lambda: _mutated(lambda gl: _attr(gl, "POSITION").update(count=1 << 31)), "out of range"),
    "accessor_without_view_huge": (lambda: _mutated(_huge_zero_accessor), "too large to allocate"),
    "nan_json_integer": (lambda: _mutated(lambda gl: _attr(gl, "POSITION").update(count=NAN)),  # json writes NaN
                         "'count' must be an integer, got nan"),
    "infinite_json_integer": (lambda: _mutated(_set(["buffers", 0, "byteLength"], INF)),
                              "'byteLength' must be an integer, got inf"),
    # ranges and references
    "accessor_offset_out_of_range": (lambda: _mutated(lambda gl: _attr(gl, "WEIGHTS_0").update(byteOffset=4096)),
                                     "out of range"),
    "accessor_missing": (lambda: _mutated(_set(["meshes", 0, "primitives", 0, "attributes", "NORMAL"], 99)),
                         "accessors\\[99\\] does not exist"),
    "indices_past_vertex_count": (lambda: _mutated(F=[[0, 1, 2], [1, 3, 7]]), "index 7 is past the vertex count 4"),
    "joints_past_skin": (lambda: _mutated(joints=np.array([[0, 0, 0, 0]] * 3 + [[9, 0, 0, 0]], np.uint16)),
                         "refer to joint 9 but the skin has 3 joints"),
    # values
    "nan_position": (lambda: _mutated(V=_with_nan(_V, NAN)), "mesh 'Body': POSITION must be finite"),
    "infinite_position": (lambda: _mutated(V=_with_nan(_V, -INF, (3, 2))), "mesh 'Body': POSITION must be finite"),
    # hierarchy and skins
    "joint_cycle": (lambda: _mutated(_cycle), "cycle"),
    "skin_joint_not_a_node": (lambda: _mutated(lambda gl: gl["skins"][0]["joints"].append(42)),
                              "skins\\[0\\] refers to a node that does not exist"),
    "skin_joint_not_an_index": (lambda: _mutated(lambda gl: gl["skins"][0]["joints"].__setitem__(1, "j1")),
                                "skins\\[0\\] refers to a node that does not exist"),
    "skin_lists_a_node_twice": (lambda: _mutated(lambda gl: gl["skins"][0]["joints"].append(1)), "same node twice"),
    "skin_on_mesh_node_without_bind": (lambda: _mutated(_mesh_node_is_joint), "inverseBindMatrices must be 4 MAT4"),
    # empty geometry
    "empty_positions": (lambda: _mutated(lambda gl: _attr(gl, "POSITION").update(count=0)), "count 0"),
}

#: id -> (bytes factory, regex one of the warnings must match): read, repaired, reported.
REPAIRED = {
    "nan_weights": (lambda: _mutated(W=_weights(NAN)), "mesh 'Body': 1 vertices with NaN or infinite weights"),
    "infinite_weights": (lambda: _mutated(W=_weights(INF)), "mesh 'Body': 1 vertices with NaN or infinite weights"),
    "negative_weights": (lambda: _mutated(W=_weights(-1.0)), "mesh 'Body': 1 vertices with zero or negative weights"),
}

#: id -> bytes factory: valid though unusual; read without error (composition is tested below).
ACCEPTED = {
    "joints_in_two_trees": lambda: _mutated(_two_trees),
    "zero_area_and_duplicate_faces": lambda: _mutated(F=[[0, 1, 2], [1, 3, 2], [0, 1, 2], [1, 3, 2], [2, 1, 3],
                                                         [0, 0, 0], [0, 1, 1]]),
    "no_faces": lambda: _mutated(lambda gl: gl["accessors"][gl["meshes"][0]["primitives"][0]["indices"]]
                                 .update(count=2)),  # 2 indices: no whole triangle
    "mesh_without_primitives": lambda: _mutated(_no_primitives),
}


def _write(tmp_path, name, raw) -> tuple:
    path = tmp_path / f"{name}.glb"
    path.write_bytes(raw)
    return path, file_digest(path), sorted(p.name for p in tmp_path.iterdir())


def _unchanged(tmp_path, path, digest, listing):
    assert file_digest(path) == digest, f"{path.name} was modified"
    assert sorted(p.name for p in tmp_path.iterdir()) == listing, "a file was left behind"


def rigmix(*args, timeout=300):
    """``python -m rigmix.cli ARGS`` in a fresh process."""
    return subprocess.run([sys.executable, "-m", "rigmix.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def assert_main_error(capsys, argv, path=None, match=None):
    """``rigmix.cli.main(argv)`` in this process: exit status 2 and one error line on stderr."""
    from rigmix.cli import main

    capsys.readouterr()
    rc = main(argv)
    out, err = capsys.readouterr()
    return assert_cli_error(subprocess.CompletedProcess(argv, rc, out, err), path, match)


def assert_cli_error(result, path=None, match=None):
    """Exit status 2, one line ``rigmix: error: ...`` (naming ``path``), no traceback; the
    reader's repair warnings (``rigmix: WARNING: ...``) may come before it."""
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr, result.stderr[-2000:]
    lines = [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.startswith("rigmix: WARNING: ")]
    assert len(lines) == 1 and lines[0].startswith("rigmix: error: "), result.stderr[-2000:]
    if path is not None:
        assert path.name in lines[0]
    if match is not None:
        import re

        assert re.search(match, lines[0]), lines[0]
    return lines[0]


# --------------------------------------------------------------------------- the corpus


def test_corpus_cases_differ_from_the_base_file():
    """Every factory builds bytes different from the valid base file (no case silently valid)."""
    base = _base()
    built = [f() for f, _ in ERRORS.values()] + [f() for f, _ in REPAIRED.values()] + [f() for f in ACCEPTED.values()]
    assert all(raw != base for raw in built)


def test_base_file_reads(tmp_path):
    path, digest, listing = _write(tmp_path, "base", _base())
    c = read_gltf(path)
    assert c.skeleton.names == ("j0", "j1", "j2") and c.skinned and not c.warnings
    assert len(c.meshes[0].faces) == 2 and len(c.clips) == 1
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.parametrize("case", sorted(ERRORS))
def test_bad_glb_api(case, tmp_path):
    factory, match = ERRORS[case]
    path, digest, listing = _write(tmp_path, case, factory())
    with pytest.raises(RigmixError, match=match) as e:
        load_character(path)
    msg = str(e.value)
    assert "\n" not in msg and path.name in msg
    _unchanged(tmp_path, path, digest, listing)


def _compose_config(tmp_path, character_file, name="cfg.toml") -> object:
    """A config composing ``character_file`` (no actions: the file is loaded, then refused)."""
    cfg = tmp_path / name
    cfg.write_text(f'[characters.a]\npath = "{character_file.name}"\n')
    return cfg


@pytest.mark.parametrize("case", sorted(ERRORS))
def test_bad_glb_cli(case, tmp_path):
    factory, match = ERRORS[case]
    path, digest, listing = _write(tmp_path, case, factory())
    result = rigmix("inspect", path, "--json")
    assert_cli_error(result, path, match)
    assert result.stdout == ""
    _unchanged(tmp_path, path, digest, listing)



@pytest.mark.parametrize("case", sorted(ERRORS))
def test_bad_glb_compose(case, tmp_path, capsys):
    """The same files as composition inputs (``rigmix compose`` in this process): the same
    one-line error, exit status 2, no output, no report."""
    factory, match = ERRORS[case]
    path, digest, _ = _write(tmp_path, case, factory())
    cfg = _compose_config(tmp_path, path)
    listing = sorted(p.name for p in tmp_path.iterdir())
    assert_main_error(capsys, ["compose", str(cfg), "-o", str(tmp_path / "out.glb"), "--report",
                               str(tmp_path / "out.json"), "--no-progress"], path, match)
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.parametrize("case", sorted(REPAIRED))
def test_repaired_glb(case, tmp_path):
    factory, match = REPAIRED[case]
    path, digest, listing = _write(tmp_path, case, factory())
    c = read_gltf(path)
    assert any(__import__("re").search(match, w) for w in c.warnings), c.warnings
    W = c.meshes[0].weights
    assert np.all(np.isfinite(W)) and W.min() >= 0 and np.allclose(W.sum(1), 1.0)
    result = rigmix("inspect", path, "--json")
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    d = json.loads(result.stdout)
    assert d["warnings"] == list(c.warnings)
    assert "rigmix: WARNING:" in result.stderr  # the repair is reported on stderr too
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.parametrize("case", sorted(ACCEPTED))
def test_unusual_but_valid_glb(case, tmp_path):
    path, digest, listing = _write(tmp_path, case, ACCEPTED[case]())
    c = read_gltf(path)
    if case == "joints_in_two_trees":
        assert list(c.skeleton.parents) == [-1, -1, 1] and c.skinned
    elif case == "zero_area_and_duplicate_faces":
        assert len(c.meshes[0].faces) == 7  # kept as they are: the stages that need it drop them
    elif case == "no_faces":
        assert c.meshes[0].faces.shape == (0, 3)
    elif case == "mesh_without_primitives":
        assert not c.skinned
        with pytest.raises(UnsupportedError, match="no skinned mesh"):
            c.require_skinned()
    result = rigmix("inspect", path)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    _unchanged(tmp_path, path, digest, listing)


# --------------------------------------------------------------------------- memory and size bounds

_PEAK = textwrap.dedent("""
    import resource, subprocess, sys
    r = subprocess.run([sys.executable, "-m", "rigmix.cli", *sys.argv[1:]], capture_output=True, text=True)
    sys.stderr.write(r.stderr)
    print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
""")


def cli_peak_rss_mib(*args) -> tuple[int, float, str]:
    """Run the CLI in a child of a fresh process: (exit status, peak RSS in MiB, stderr)."""
    r = subprocess.run([sys.executable, "-c", _PEAK, *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, timeout=600)
    rc, kib = r.stdout.split()
    return int(rc), int(kib) / 1024.0, r.stderr


@pytest.mark.parametrize("case", ["buffer_byte_length_huge", "buffer_view_huge", "accessor_count_huge",
                                  "accessor_without_view_huge", "bin_chunk_length_huge"])
def test_huge_declared_sizes_are_not_allocated(case, tmp_path):
    path, digest, listing = _write(tmp_path, case, ERRORS[case][0]())
    rc, peak, err = cli_peak_rss_mib("inspect", path)
    assert rc == 2 and "Traceback" not in err
    assert peak < 400, f"peak RSS {peak:.0f} MiB"  # the declared sizes are >= 2 GiB
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.slow
def test_100k_joint_chain_through_the_cli(tmp_path):
    """A chain 100k joints deep: read and printed as a tree by the CLI with bounded memory (an
    indentation that grew with the depth would print ~10 GB of text)."""
    gl, data = tiny_skinned(100_000, shape="chain")
    path, digest, listing = _write(tmp_path, "chain", glb_bytes(gl, data))
    rc, peak, err = cli_peak_rss_mib("inspect", path)
    assert rc == 0 and "Traceback" not in err, err[-2000:]
    assert peak < 1500, f"peak RSS {peak:.0f} MiB for 100k joints"
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.slow
def test_100k_joints_with_one_name(tmp_path, caplog):
    """A star of 100k joints all named 'Bone': renamed Bone.1... in linear time (a renaming that
    restarted at .1 for each duplicate would be quadratic: hours for this file)."""
    caplog.set_level(logging.ERROR, logger="rigmix")  # 99,999 rename warnings: counted below, not logged
    gl, data = tiny_skinned(100_000, shape="star", same_names=True)
    path, digest, listing = _write(tmp_path, "star", glb_bytes(gl, data))
    sk = (c := read_gltf(path)).skeleton
    assert sk.num_joints == 100_000 and (sk.parents[1:] == 0).all() and len(set(sk.names)) == 100_000
    assert sk.names[:3] == ("Bone", "Bone.1", "Bone.2") and sk.names[-1] == "Bone.99999"
    assert sum("used twice" in w for w in c.warnings) == 99_999
    _unchanged(tmp_path, path, digest, listing)


# --------------------------------------------------------------------------- configs

BAD_CONFIGS = {
    "negative_scale": ('[characters.a]\npath = "builtin:humanoid"\nscale = -2.0\n', "characters.a.scale"),
    "nan_scale": ('[characters.a]\npath = "builtin:humanoid"\nscale = nan\n', "characters.a.scale.*finite"),
    "infinite_scale": ('[characters.a]\npath = "builtin:humanoid"\nscale = inf\n', "characters.a.scale.*finite"),
    "nan_rotation": ('[characters.a]\npath = "builtin:humanoid"\n[characters.a.rotations]\nHips = [0, nan, 0]\n',
                     "characters.a.rotations.Hips.euler\\[1\\].*finite"),
    "infinite_translation": ('[characters.a]\npath = "builtin:humanoid"\n'
                             '[characters.a.placement]\ntranslation = [0, -inf, 0]\n',
                             "characters.a.placement.translation\\[1\\].*finite"),
    "nan_bonus": ('[characters.a]\npath = "builtin:humanoid"\n[mapping]\ninjectivity_bonus = [nan, 0.1]\n',
                  "mapping.injectivity_bonus\\[0\\].*finite"),
    "unknown_op": ('[characters.a]\npath = "builtin:humanoid"\n[[actions]]\nop = "explode"\ntarget = "a"\n'
                   'target_joint = "Hips"\n', "actions\\[0\\]"),
    "characters_not_a_table": ('characters = 5\n', "characters"),
    "path_not_a_string": ('[characters.a]\npath = 3\n', "characters.a.path"),
    "actions_not_a_list": ('actions = "attach"\n[characters.a]\npath = "builtin:humanoid"\n', "actions"),
    "scale_a_string": ('[characters.a]\npath = "builtin:humanoid"\nscale = "big"\n', "characters.a.scale"),
    "rotation_wrong_length": ('[characters.a]\npath = "builtin:humanoid"\n'
                              '[characters.a.rotations]\nHips = [1, 2, 3, 4, 5]\n',
                              "characters.a.rotations.Hips"),
    "zero_quaternion": ('[characters.a]\npath = "builtin:humanoid"\n[characters.a.rotations]\nHips = [0, 0, 0, 0]\n',
                        "zero length"),
    "not_toml": ('[characters.a\npath = "x"\n', "not valid TOML"),
    "not_utf8": (b"name = \"\xff\xfe\"\n", "cannot read"),
}


def _write_config(tmp_path, text) -> tuple:
    path = tmp_path / "bad.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path, file_digest(path), sorted(p.name for p in tmp_path.iterdir())


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_config_api(case, tmp_path):
    text, match = BAD_CONFIGS[case]
    path, digest, listing = _write_config(tmp_path, text)
    with pytest.raises(InputError, match=match) as e:
        load_config(path)
    assert "\n" not in str(e.value) and "bad.toml" in str(e.value)
    _unchanged(tmp_path, path, digest, listing)


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_bad_config_cli(case, tmp_path, capsys):
    text, match = BAD_CONFIGS[case]
    path, digest, listing = _write_config(tmp_path, text)
    assert_main_error(capsys, ["compose", str(path), "-o", str(tmp_path / "out.glb"), "--report",
                               str(tmp_path / "out.json"), "--no-progress"], path, match)
    _unchanged(tmp_path, path, digest, listing)


def test_bad_config_subprocess(tmp_path):
    """One bad config through a fresh process: no traceback anywhere on stderr."""
    text, match = BAD_CONFIGS["nan_scale"]
    path, digest, listing = _write_config(tmp_path, text)
    result = rigmix("compose", path, "-o", tmp_path / "out.glb", "--report", tmp_path / "out.json", "--no-progress")
    assert_cli_error(result, path, match)
    _unchanged(tmp_path, path, digest, listing)


def test_input_without_skinned_mesh_cannot_be_composed(tmp_path, capsys):
    path, digest, listing = _write(tmp_path, "static", ACCEPTED["mesh_without_primitives"]())
    cfg = _compose_config(tmp_path, path)
    listing = sorted(p.name for p in tmp_path.iterdir())
    assert_main_error(capsys, ["compose", str(cfg), "-o", str(tmp_path / "out.glb"), "--no-progress"], path,
                      "no skinned mesh")
    _unchanged(tmp_path, path, digest, listing)


def _poke_nan_weights(raw: bytes, rows) -> bytes:
    """Set the WEIGHTS_0 rows ``rows`` of the first primitive of a GLB to NaN (in the BIN chunk)."""
    n = struct.unpack_from("<I", raw, 12)[0]
    gl = json.loads(raw[20:20 + n])
    acc = gl["accessors"][gl["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"]]
    view = gl["bufferViews"][acc["bufferView"]]
    assert acc["componentType"] == 5126 and view.get("byteStride", 16) == 16
    start = 28 + n + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    b = bytearray(raw)
    for r in rows:
        b[start + 16 * r: start + 16 * r + 16] = np.full(4, np.nan, np.float32).tobytes()
    return bytes(b)


@pytest.mark.slow
def test_compose_copes_with_repairable_defects(tmp_path):
    """The built-in humanoid with duplicate faces (same and flipped winding), zero-area faces and
    NaN weights, composed with a donor's arm: repaired, composed, the repairs in the report."""
    import dataclasses

    from rigmix.examples import humanoid
    from rigmix.io.gltf import write_gltf

    h = humanoid()
    m = h.meshes[0]
    F = m.faces
    extra = np.concatenate([F[:50], F[100:110, ::-1], np.stack([F[:20, 0], F[:20, 0], F[:20, 1]], 1),
                            np.repeat(F[:5, :1], 3, axis=1)])
    messy = dataclasses.replace(h, meshes=(dataclasses.replace(m, faces=np.concatenate([F, extra])),) + h.meshes[1:])
    clean = tmp_path / "clean.glb"
    write_gltf(messy, clean)
    path, digest, _ = _write(tmp_path, "messy", _poke_nan_weights(clean.read_bytes(), range(10)))
    cfg = tmp_path / "messy.toml"
    cfg.write_text('[characters.body]\npath = "messy.glb"\n[characters.donor]\npath = "builtin:humanoid"\n'
                   '[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "UpperArm.L"\n'
                   'target = "body"\ntarget_joint = "UpperArm.L"\n[weights]\nmethod = "nearest"\n')
    out, report = tmp_path / "out.glb", tmp_path / "out.json"
    result = rigmix("compose", cfg, "-o", out, "--report", report, "--no-progress")
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert "10 vertices with NaN or infinite weights" in result.stderr  # the repair, on stderr
    warnings = json.loads(report.read_text())["warnings"]
    assert any("messy.glb" in w and "10 vertices with NaN or infinite weights" in w for w in warnings), warnings
    c = read_gltf(out)
    assert c.skinned and np.isfinite(c.meshes[0].positions).all()
    assert file_digest(path) == digest
