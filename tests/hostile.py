"""The hostile-input corpus (issue 23): corrupt and hostile character files and bad configs,
generated deterministically from the shared characters, and the judge that runs one case in a
subprocess and says what went wrong.

Used by ``tests/test_hostile.py`` (a fast slice) and ``benchmarks/fuzz.py`` (``make fuzz``, the
whole set). No pytest import here: the runner imports this module too.

A :class:`Case` is a category, an expectation and a builder that writes the case's files into its
own folder (the "asset folder": a hostile file may only make rigmix read files inside it):

``refuse``
    exit status 2 with one line ``rigmix: error: ...``.
``refuse-or-repair``
    exit 2, or exit 0 with a repair warning (a ``rigmix: WARNING:`` line, or repaired defects listed
    by ``inspect``), as the README's repair list says.
``any``
    the input may be valid (a flipped float, a unicode name): anything but a failure.

Whatever the expectation, a run fails on a traceback, exit 1 (internal error), a signal, a timeout,
a file opened outside the asset folder (audit hook on ``open``), a sentinel file's bytes in an
output, an output left behind by a failed run, or a modified input. A file case that exits 0
without a warning is "silently accepted" when the Khronos validator reports errors on it.

Files outside the asset folder that hostile URIs point at are sentinels (``Workspace.outside``):
a PNG and a float buffer with unique byte patterns that must never appear in any output.
"""

from __future__ import annotations

import base64
import copy
import hashlib
import json
import math
import os
import random
import resource
import signal
import struct
import subprocess
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parent.parent
ASSETS = Path(os.environ.get("RIGMIX_ASSETS", ROOT.parent / "shared" / "data" / "characters"))

#: Seed characters: name -> (path under ASSETS, a joint for a self-composition).
SEEDS = {
    "RiggedFigure": ("RiggedFigure/RiggedFigure.glb", "arm_joint_L_1"),
    "Fox": ("Fox/Fox.glb", "b_LeftUpperArm_09"),
    "CesiumMan": ("CesiumMan/CesiumMan.glb", "Skeleton_arm_joint_L__4_"),
    "SimpleSkin": ("SimpleSkin/SimpleSkin.gltf", "joint_2"),
}
GLB_SEEDS = ("RiggedFigure", "Fox", "CesiumMan")

TIMEOUT = 120.0
#: Address-space limit of every run: a reader that swallows /dev/zero fails fast instead of taking
#: the machine's memory (the acceptance is a peak RSS under 2 GB; torch maps ~3 GB of address space).
MEMORY_LIMIT = 8 << 30

SENTINEL_MARK = b"RIGMIX-SENTINEL"


# --------------------------------------------------------------------------- GLB helpers


def split_glb(raw: bytes) -> tuple[dict, bytes]:
    """A valid GLB's JSON (dict) and BIN chunk (b"" when there is none)."""
    n = struct.unpack_from("<I", raw, 12)[0]
    js = json.loads(raw[20:20 + n])
    return js, (raw[28 + n:] if len(raw) > 20 + n else b"")


def glb(js, data: bytes = b"") -> bytes:
    """A GLB container around ``js`` (a dict, or JSON text as bytes) and ``data`` (BIN, padded)."""
    text = js if isinstance(js, bytes) else json.dumps(js).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text
    if data:
        data = bytes(data) + b"\0" * (-len(data) % 4)
        body += struct.pack("<II", len(data), 0x004E4942) + data
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


_SEED_CACHE: dict[str, bytes] = {}


def seed_bytes(name: str) -> bytes:
    """The bytes of a seed character (FileNotFoundError when the shared assets are missing)."""
    if name not in _SEED_CACHE:
        _SEED_CACHE[name] = (ASSETS / SEEDS[name][0]).read_bytes()
    return _SEED_CACHE[name]


def seed_doc(name: str) -> tuple[dict, bytes]:
    """A fresh copy of a seed's JSON and BIN (SimpleSkin: its JSON, buffers as data URIs)."""
    raw = seed_bytes(name)
    if name == "SimpleSkin":
        return json.loads(raw), b""
    js, data = split_glb(raw)
    return js, data


def _prim(js) -> dict:
    """The first primitive of the mesh of the first skinned node (or of mesh 0)."""
    mesh = next((n["mesh"] for n in js["nodes"] if "skin" in n and "mesh" in n), 0)
    return js["meshes"][mesh]["primitives"][0]


def _accessor_floats(js, data: bytes, index: int):
    """(byte offsets, component count) of a float accessor's elements in ``data``."""
    acc = js["accessors"][index]
    view = js["bufferViews"][acc["bufferView"]]
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc["type"]]
    stride = view.get("byteStride", 4 * ncomp)
    base = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return [base + i * stride for i in range(acc["count"])], ncomp


def set_floats(js, data: bytes, index: int, fn: Callable[[int, list], list]) -> bytes:
    """``data`` with element ``i`` of float accessor ``index`` replaced by ``fn(i, values)``."""
    out = bytearray(data)
    offsets, ncomp = _accessor_floats(js, data, index)
    for i, off in enumerate(offsets):
        vals = list(struct.unpack_from(f"<{ncomp}f", out, off))
        struct.pack_into(f"<{ncomp}f", out, off, *fn(i, vals))
    return bytes(out)


def _drop_minmax(js, index):
    js["accessors"][index].pop("min", None)
    js["accessors"][index].pop("max", None)


# --------------------------------------------------------------------------- workspace


SITECUSTOMIZE = '''\
"""Installed by tests/hostile.py: log every `open` audit event of this process to a file."""
import os, sys
_log = os.environ.get("RIGMIX_FUZZ_OPEN_LOG")
if _log:
    _fd = os.open(_log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.write(_fd, ("#syspath\\t" + "\\t".join(os.path.abspath(p) for p in sys.path if p) + "\\n").encode())

    def _rigmix_fuzz_hook(event, args, _fd=_fd, _w=os.write, _abs=os.path.abspath, _dec=os.fsdecode):
        if event == "open" and args and not isinstance(args[0], int):
            try:
                line = "%s\\t%s\\t%s\\n" % (_abs(_dec(args[0])), args[1], args[2])
                _w(_fd, line.encode("utf-8", "backslashreplace"))
            except Exception:
                pass

    sys.addaudithook(_rigmix_fuzz_hook)
'''


def _png(text: bytes) -> bytes:
    """A 2x2 RGB PNG carrying ``text`` in a tEXt chunk."""
    def chunk(kind, payload):
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))
    raw = b"".join(b"\0" + b"\xff\x00\x80" * 2 for _ in range(2))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 8, 2, 0, 0, 0))
            + chunk(b"tEXt", b"Comment\0" + text) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


class Workspace:
    """A scratch folder: ``outside/`` (sentinels), ``cases/<id>/`` (asset folders), ``out/<id>/``
    (outputs) and ``hook/sitecustomize.py`` (the audit hook)."""

    def __init__(self, root):
        self.root = Path(root).resolve()
        self.outside = self.root / "outside"
        self.cases = self.root / "cases"
        self.out = self.root / "out"
        self.hook = self.root / "hook"
        for d in (self.outside, self.cases, self.out, self.hook):
            d.mkdir(parents=True, exist_ok=True)
        (self.hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
        tag = hashlib.sha256(str(self.root).encode()).hexdigest()[:16].encode()
        self.sentinel_png = self.outside / "sentinel.png"
        self.sentinel_png.write_bytes(_png(SENTINEL_MARK + b"-PNG-" + tag))
        # a float buffer: 16 KiB of distinctive float32 values (usable as COLOR_0/POSITION data)
        rng = random.Random(tag)
        floats = [0.25 + 0.5 * rng.random() for _ in range(4096)]
        self.sentinel_bin = self.outside / "sentinel.bin"
        self.sentinel_bin.write_bytes(struct.pack("<4096f", *floats))
        self.sentinel_blocks = [self.sentinel_bin.read_bytes()[i:i + 24] for i in range(0, 16384, 512)]
        glb_raw = seed_bytes("RiggedFigure")
        self.sentinel_glb = self.outside / "sentinel.glb"
        js, data = split_glb(glb_raw)
        js["asset"]["generator"] = (SENTINEL_MARK + b"-GLB-" + tag).decode()
        self.sentinel_glb.write_bytes(glb(js, data))

    def leaked(self, blob: bytes) -> bool:
        """Whether ``blob`` holds bytes of a sentinel."""
        return SENTINEL_MARK in blob or any(b in blob for b in self.sentinel_blocks)

    def materialize(self, case: "Case") -> Path:
        """Write the case's files into a fresh ``cases/<id>/``; returns the path to run."""
        folder = self.cases / case.id
        if folder.exists():
            _rmtree(folder)
        folder.mkdir(parents=True)
        return case.make(folder, self)


def _rmtree(path: Path) -> None:
    for p in sorted(path.rglob("*"), key=lambda p: -len(p.parts)):
        if p.is_symlink() or not p.is_dir():
            p.unlink()
        else:
            p.rmdir()
    path.rmdir()


# --------------------------------------------------------------------------- cases


@dataclass(frozen=True)
class Case:
    """One hostile input.

    Attributes
    ----------
    id : str
        Unique, a valid file name.
    category : str
    kind : str
        ``"file"`` (a character file, run with ``inspect``) or ``"config"`` (run with ``compose``).
    expect : str
        ``"refuse"``, ``"refuse-or-repair"`` or ``"any"`` (module docstring).
    note : str
    finding : int or None
        The issue-23 finding it exercises.
    make : callable
        ``make(folder, workspace) -> Path`` writes the case's files into ``folder`` and returns the
        file to run.
    special : bool
        A FIFO, device or folder is involved: the validator is not run on it (it would block).
    argv : tuple of str
        Config cases: the compose command, with ``{config}``, ``{out}`` and ``{case}`` replaced.
    """

    id: str
    category: str
    kind: str
    expect: str
    note: str
    finding: int | None
    make: Callable = field(repr=False, compare=False)
    special: bool = False
    argv: tuple = ()


def _file(folder: Path, name: str, data: bytes) -> Path:
    path = folder / name
    path.write_bytes(data)
    return path


def _glb_case(cid, category, expect, note, fn, finding=None, seed="RiggedFigure") -> Case:
    """A GLB case: ``fn(js, data) -> (js, data)`` edits a seed's JSON and BIN (or returns bytes)."""
    def make(folder, ws):
        js, data = seed_doc(seed)
        res = fn(js, data)
        raw = res if isinstance(res, (bytes, bytearray)) else glb(*res)
        return _file(folder, f"{seed}.glb", bytes(raw))
    return Case(cid, category, "file", expect, note, finding, make)


def _raw_case(cid, category, expect, note, fn, finding=None, seed="RiggedFigure", name=None) -> Case:
    """A case from the seed's raw bytes: ``fn(raw) -> bytes``."""
    def make(folder, ws):
        return _file(folder, name or Path(SEEDS[seed][0]).name, fn(seed_bytes(seed)))
    return Case(cid, category, "file", expect, note, finding, make)


def _rng(cid: str) -> random.Random:
    return random.Random(cid)


def truncation_cases() -> list[Case]:
    out = []
    for seed in GLB_SEEDS + ("SimpleSkin",):
        for frac in (0.0, 0.001, 0.01, 0.05, 0.2, 0.5, 0.8, 0.97, 0.999):
            def fn(raw, frac=frac):
                return raw[: int(frac * len(raw))]
            out.append(_raw_case(f"trunc-{seed}-{frac:g}", "truncation", "refuse", f"first {frac:.1%} of {seed}",
                                 fn, seed=seed))
        # a .gltf ends with a newline: cutting that leaves valid JSON, so its last non-blank byte goes
        out.append(_raw_case(f"trunc-{seed}-minus1", "truncation", "refuse", "last (non-blank) byte cut",
                             lambda raw, text=seed == "SimpleSkin": (raw.rstrip() if text else raw)[:-1],
                             seed=seed))
    return out


def header_cases() -> list[Case]:
    def put(offset, fmt, value):
        def fn(raw):
            b = bytearray(raw)
            struct.pack_into(fmt, b, offset, value)
            return bytes(b)
        return fn

    def bin_at(raw):
        return 20 + struct.unpack_from("<I", raw, 12)[0]

    def put_bin(delta, fmt, value):
        def fn(raw):
            b = bytearray(raw)
            struct.pack_into(fmt, b, bin_at(raw) + delta, value)
            return bytes(b)
        return fn

    variants = [
        ("magic", put(0, "<4s", b"gLTF"), "refuse"),
        ("version1", put(4, "<I", 1), "refuse"),
        ("version3", put(4, "<I", 3), "refuse"),
        ("length0", put(8, "<I", 0), "refuse"),
        ("length-small", put(8, "<I", 20), "refuse"),
        ("length-huge", put(8, "<I", 2**32 - 1), "refuse"),
        ("length-plus4", lambda r: put(8, "<I", len(r) + 4)(r), "refuse"),
        ("json-len0", put(12, "<I", 0), "refuse"),
        ("json-len1", put(12, "<I", 1), "refuse"),
        ("json-len-huge", put(12, "<I", 2**31), "refuse"),
        ("json-len-odd", lambda r: put(12, "<I", struct.unpack_from("<I", r, 12)[0] - 3)(r), "refuse"),
        ("json-type-bin", put(16, "<I", 0x004E4942), "refuse"),
        ("json-type-unknown", put(16, "<I", 0x12345678), "refuse"),
        ("bin-len-huge", put_bin(0, "<I", 2**32 - 4), "refuse"),
        ("bin-len0", put_bin(0, "<I", 0), "refuse"),
        ("bin-type-json", put_bin(4, "<I", 0x4E4F534A), "refuse"),
        ("bin-type-unknown", put_bin(4, "<I", 0x41414141), "refuse"),
        ("no-bin", lambda r: glb(*(split_glb(r)[0], b"")), "refuse"),
        ("extra-chunk", lambda r: _extra_chunk(r), "any"),
        ("two-json", lambda r: _two_json(r), "refuse"),
    ]
    out = []
    for seed in GLB_SEEDS:
        for name, fn, expect in variants:
            out.append(_raw_case(f"header-{seed}-{name}", "header", expect, name, fn, seed=seed))
    return out


def _extra_chunk(raw: bytes) -> bytes:
    """An unknown chunk type after BIN (the spec says: ignore it)."""
    extra = struct.pack("<II", 8, 0x58595A57) + b"ABCDEFGH"
    b = bytearray(raw + extra)
    struct.pack_into("<I", b, 8, len(b))
    return bytes(b)


def _two_json(raw: bytes) -> bytes:
    n = struct.unpack_from("<I", raw, 12)[0]
    chunk = raw[12:20 + n]
    b = bytearray(raw[:20 + n] + chunk + raw[20 + n:])
    struct.pack_into("<I", b, 8, len(b))
    return bytes(b)


def flip_cases() -> list[Case]:
    out = []
    for seed in GLB_SEEDS:
        for k in range(10):
            cid = f"jsonflip-{seed}-{k}"

            def fn(raw, cid=cid):
                rng = _rng(cid)
                n = struct.unpack_from("<I", raw, 12)[0]
                b = bytearray(raw)
                for _ in range(rng.randint(1, 4)):
                    b[20 + rng.randrange(n)] ^= rng.randint(1, 255)
                return bytes(b)
            out.append(_raw_case(cid, "json-flip", "any", "1-4 bytes of the JSON chunk flipped", fn, seed=seed))
        for k in range(8):
            cid = f"binflip-{seed}-{k}"

            def fn(raw, cid=cid):
                rng = _rng(cid)
                start = 28 + struct.unpack_from("<I", raw, 12)[0]
                b = bytearray(raw)
                for _ in range(rng.randint(1, 16)):
                    b[start + rng.randrange(len(raw) - start)] ^= rng.randint(1, 255)
                return bytes(b)
            out.append(_raw_case(cid, "bin-flip", "any", "1-16 bytes of the BIN chunk flipped", fn, seed=seed))
    for k in range(6):
        cid = f"jsonflip-SimpleSkin-{k}"

        def fn(raw, cid=cid):
            rng = _rng(cid)
            b = bytearray(raw)
            for _ in range(rng.randint(1, 3)):
                b[rng.randrange(len(b))] ^= rng.randint(1, 255)
            return bytes(b)
        out.append(_raw_case(cid, "json-flip", "any", "bytes of the .gltf flipped", fn, seed="SimpleSkin"))
    return out


# -- structured JSON edits: (id, fn(js, data) -> (js, data), expect, finding)


def _set(path, value):
    """An edit that sets ``js[path...] = value`` (paths use callables for computed indices)."""
    def fn(js, data):
        parent = js
        for k in path[:-1]:
            parent = parent[k(js) if callable(k) else k]
        last = path[-1]
        parent[last(js) if callable(last) else last] = copy.deepcopy(value)
        return js, data
    return fn


def _delete(path):
    def fn(js, data):
        parent = js
        for k in path[:-1]:
            parent = parent[k(js) if callable(k) else k]
        last = path[-1]
        del parent[last(js) if callable(last) else last]
        return js, data
    return fn


def _pos(js):
    return _prim(js)["attributes"]["POSITION"]


def _weights(js):
    return _prim(js)["attributes"]["WEIGHTS_0"]


def _joints(js):
    return _prim(js)["attributes"]["JOINTS_0"]


def _ibm(js):
    return js["skins"][0]["inverseBindMatrices"]


def _joint_node(k):
    return lambda js: js["skins"][0]["joints"][k]


def _anim_sampler(path):
    """(sampler dict index path) of the first channel animating ``path``."""
    def find(js):
        for a, anim in enumerate(js.get("animations", [])):
            for ch in anim["channels"]:
                if ch["target"].get("path") == path:
                    return a, ch["sampler"]
        raise LookupError(path)
    return find


def _anim_acc(path, which):
    def idx(js):
        a, s = _anim_sampler(path)(js)
        return js["animations"][a]["samplers"][s][which]
    return idx


def structure_edits() -> list[tuple]:
    first = lambda js: 0  # noqa: E731
    E = []
    add = E.append
    # types and ranges of accessor fields
    for name, value in (("count-neg", -1), ("count-str", "12"), ("count-float", 1.5), ("count-zero", 0),
                        ("count-plus1", None)):
        if value is None:
            def fn(js, data):
                js["accessors"][_pos(js)]["count"] += 1
                return js, data
        else:
            fn = _set(["accessors", _pos, "count"], value)
        add((f"pos-{name}", fn, "refuse", None))
    add(("comptype-9999", _set(["accessors", _pos, "componentType"], 9999), "refuse", None))
    add(("type-vec9", _set(["accessors", _pos, "type"], "VEC9"), "refuse", None))
    add(("type-scalar", _set(["accessors", _pos, "type"], "SCALAR"), "refuse", None))
    add(("bufferview-oob", _set(["accessors", _pos, "bufferView"], 9999), "refuse", None))
    add(("bufferview-neg", _set(["accessors", _pos, "bufferView"], -1), "refuse", None))
    add(("byteoffset-huge", _set(["accessors", _pos, "byteOffset"], 2**40), "refuse", None))
    add(("byteoffset-unaligned", _set(["accessors", _pos, "byteOffset"], 1), "refuse", None))
    add(("bytestride-3", _set(["bufferViews", lambda js: js["accessors"][_pos(js)]["bufferView"], "byteStride"], 3),
         "refuse", None))
    add(("bytestride-huge", _set(["bufferViews", lambda js: js["accessors"][_pos(js)]["bufferView"],
                                  "byteStride"], 252), "refuse", None))
    add(("view-buffer-oob", _set(["bufferViews", first, "buffer"], 7), "refuse", None))
    add(("view-len-neg", _set(["bufferViews", first, "byteLength"], -4), "refuse", None))
    add(("buffer-len-small", _set(["buffers", first, "byteLength"], 4), "refuse", None))
    add(("buffer-len-str", _set(["buffers", first, "byteLength"], "many"), "refuse", None))
    add(("sparse-bogus", _set(["accessors", _pos, "sparse"], {"count": 3, "indices": {"bufferView": 0,
                                                                                        "componentType": 5123},
                                                                "values": {"bufferView": 99}}), "refuse", None))
    # deletions
    add(("del-asset", _delete(["asset"]), "refuse", None))
    add(("asset-version-1", _set(["asset", "version"], "1.0"), "refuse", None))
    add(("asset-version-num", _set(["asset", "version"], 2), "refuse", None))
    add(("del-accessors", _delete(["accessors"]), "refuse", None))
    add(("del-bufferviews", _delete(["bufferViews"]), "refuse", None))
    add(("del-buffers", _delete(["buffers"]), "refuse", None))
    add(("del-view-buffer", _delete(["bufferViews", first, "buffer"]), "refuse", None))
    # a mesh without primitives is dropped, a primitive without POSITION skipped (glTF 2.0 3.7.2.1:
    # clients SHOULD skip it), each with a warning: nothing the file validly holds is lost
    add(("del-primitives", _delete(["meshes", first, "primitives"]), "refuse-or-repair", None))
    add(("del-position", lambda js, d: (_prim(js)["attributes"].pop("POSITION"), (js, d))[1], "refuse-or-repair",
         None))
    add(("del-joints0", lambda js, d: (_prim(js)["attributes"].pop("JOINTS_0"), (js, d))[1], "refuse-or-repair",
         None))
    add(("del-weights0", lambda js, d: (_prim(js)["attributes"].pop("WEIGHTS_0"), (js, d))[1], "refuse-or-repair",
         None))
    add(("del-skin-joints", _delete(["skins", first, "joints"]), "refuse", None))
    add(("del-nodes", _delete(["nodes"]), "refuse", None))
    # a channel without target animates nothing: ignored with a warning
    add(("del-channel-target", _delete(["animations", first, "channels", first, "target"]), "refuse-or-repair",
         None))
    # wrong types
    add(("nodes-dict", _set(["nodes"], {"0": {}}), "refuse", None))
    add(("accessors-str", _set(["accessors"], "all"), "refuse", None))
    add(("node-name-int", _set(["nodes", _joint_node(0), "name"], 12), "refuse-or-repair", None))  # name ignored
    add(("node-translation-str", _set(["nodes", _joint_node(1), "translation"], "up"), "refuse", None))
    add(("node-translation-2", _set(["nodes", _joint_node(1), "translation"], [1, 2]), "refuse", None))
    add(("node-matrix-15", _set(["nodes", _joint_node(1), "matrix"], [1] * 15), "refuse", None))
    add(("node-matrix-and-trs", _set(["nodes", _joint_node(1), "matrix"], [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0,
                                                                             0, 0, 0, 1]), "refuse-or-repair", None))
    add(("skin-joints-str", _set(["skins", first, "joints"], "all"), "refuse", None))
    add(("skin-ibm-oob", _set(["skins", first, "inverseBindMatrices"], 9999), "refuse", None))
    add(("skin-ibm-wrongtype", lambda js, d: (js["skins"][0].__setitem__("inverseBindMatrices", _pos(js)),
                                              (js, d))[1], "refuse", None))
    add(("skin-skeleton-oob", _set(["skins", first, "skeleton"], 9999), "refuse-or-repair", None))
    add(("anim-interp-bogus", _set(["animations", first, "samplers", first, "interpolation"], "BOUNCY"),
         "refuse", None))
    add(("anim-cubic-wrong-count", _set(["animations", first, "samplers", first, "interpolation"], "CUBICSPLINE"),
         "refuse", None))
    add(("anim-path-bogus", _set(["animations", first, "channels", first, "target", "path"], "shear"),
         "refuse-or-repair", None))
    add(("anim-sampler-oob", _set(["animations", first, "channels", first, "sampler"], 999), "refuse", None))
    add(("scene-str", _set(["scene"], "main"), "refuse", None))
    # out-of-range indices
    add(("node-mesh-oob", lambda js, d: (next(n for n in js["nodes"] if "mesh" in n).__setitem__("mesh", 999),
                                         (js, d))[1], "refuse", None))
    add(("node-skin-oob", lambda js, d: (next(n for n in js["nodes"] if "skin" in n).__setitem__("skin", 999),
                                         (js, d))[1], "refuse", None))
    add(("child-oob", lambda js, d: (js["nodes"][_joint_node(0)(js)].setdefault("children", []).append(99999),
                                     (js, d))[1], "refuse", None))
    add(("child-neg", lambda js, d: (js["nodes"][_joint_node(0)(js)].setdefault("children", []).append(-1),
                                     (js, d))[1], "refuse", None))
    add(("skin-joint-oob", lambda js, d: (js["skins"][0]["joints"].append(99999), (js, d))[1], "refuse", None))
    add(("skin-joint-dup", lambda js, d: (js["skins"][0]["joints"].append(js["skins"][0]["joints"][0]), (js, d))[1],
         "refuse-or-repair", None))
    add(("channel-node-oob", _set(["animations", first, "channels", first, "target", "node"], 99999),
         "refuse", None))
    add(("indices-oob", lambda js, d: _indices_oob(js, d), "refuse", None))
    add(("joints-oob", lambda js, d: _joints_oob(js, d), "refuse", None))
    add(("texcoord-oob", lambda js, d: (_prim(js)["attributes"].__setitem__("TEXCOORD_0", 99999), (js, d))[1],
         "refuse", None))
    add(("material-oob", lambda js, d: (_prim(js).__setitem__("material", 99999), (js, d))[1], "refuse", None))
    return E


def _indices_oob(js, data):
    prim = _prim(js)
    acc = js["accessors"][prim["indices"]]
    view = js["bufferViews"][acc["bufferView"]]
    fmt = {5121: "<B", 5123: "<H", 5125: "<I"}[acc["componentType"]]
    b = bytearray(data)
    struct.pack_into(fmt, b, view.get("byteOffset", 0) + acc.get("byteOffset", 0),
                     {5121: 255, 5123: 65535, 5125: 2**31}[acc["componentType"]])
    acc.pop("max", None)
    return js, bytes(b)


def _joints_oob(js, data):
    acc = js["accessors"][_joints(js)]
    view = js["bufferViews"][acc["bufferView"]]
    fmt = {5121: "<B", 5123: "<H"}[acc["componentType"]]
    b = bytearray(data)
    struct.pack_into(fmt, b, view.get("byteOffset", 0) + acc.get("byteOffset", 0), 250)
    return js, bytes(b)


def huge_edits() -> list[tuple]:
    first = lambda js: 0  # noqa: E731
    E = []
    for v in (2**31, 2**32 - 1, 2**53, 10**30):
        E.append((f"pos-count-{v:.0e}", _set(["accessors", _pos, "count"], v), "refuse", 5))
    for v in (2**40, 2**62):
        E.append((f"view-len-{v:.0e}", _set(["bufferViews", first, "byteLength"], v), "refuse", 5))
        E.append((f"buffer-len-{v:.0e}", _set(["buffers", first, "byteLength"], v), "refuse", 5))
    E.append(("sparse-count-huge", _set(["accessors", _pos, "sparse"], {
        "count": 2**31, "indices": {"bufferView": 0, "componentType": 5125}, "values": {"bufferView": 0}}),
        "refuse", 5))
    E.append(("skin-joints-100k", lambda js, d: (js["skins"][0].__setitem__(
        "joints", list(range(len(js["nodes"]))) * (100000 // len(js["nodes"]))), (js, d))[1], "refuse", 5))
    E.append(("anim-count-huge", _set(["accessors", _anim_acc("rotation", "input"), "count"], 2**31 - 1),
              "refuse", 5))
    E.append(("ibm-count-huge", _set(["accessors", _ibm, "count"], 2**30), "refuse", 5))
    E.append(("many-accessors", lambda js, d: (js["accessors"].extend([copy.deepcopy(js["accessors"][0])] * 200000),
                                               (js, d))[1], "any", 5))
    return E


def cycle_edits() -> list[tuple]:
    E = []

    def child(a, b):
        def fn(js, data):
            na, nb = _joint_node(a)(js), _joint_node(b)(js)
            js["nodes"][na].setdefault("children", []).append(nb)
            return js, data
        return fn
    E.append(("self-child", child(1, 1), "refuse", None))
    E.append(("child-to-root", child(3, 0), "refuse", None))
    E.append(("child-to-parent", child(2, 1), "refuse", None))
    E.append(("two-parents", child(0, 2), "refuse", None))

    def scene_dup(js, data):
        js["scenes"][js.get("scene", 0)]["nodes"] = js["scenes"][js.get("scene", 0)]["nodes"] * 2
        return js, data
    E.append(("scene-dup", scene_dup, "refuse-or-repair", None))

    def skel_cycle(js, data):
        child(4, 0)(js, data)
        js["skins"][0]["skeleton"] = _joint_node(2)(js)
        return js, data
    E.append(("skin-skeleton-in-cycle", skel_cycle, "refuse", None))

    def all_cycle(js, data):
        joints = js["skins"][0]["joints"]
        for a, b in zip(joints, joints[1:] + joints[:1]):
            js["nodes"][a]["children"] = [b]
        return js, data
    E.append(("skin-ring", all_cycle, "refuse", None))

    def mesh_node_child_of_joint(js, data):
        mesh_node = next(i for i, n in enumerate(js["nodes"]) if "skin" in n)
        js["nodes"][mesh_node].setdefault("children", []).append(_joint_node(0)(js))
        js["nodes"][_joint_node(len(js["skins"][0]["joints"]) - 1)(js)].setdefault("children", []).append(mesh_node)
        return js, data
    E.append(("mesh-joint-cycle", mesh_node_child_of_joint, "refuse", None))
    return E


def _nan_bin(accessor, value, k=0, comp=0):
    def fn(js, data):
        data = set_floats(js, data, accessor(js), lambda i, v: [value if (i == k and c == comp) else x
                                                                for c, x in enumerate(v)])
        _drop_minmax(js, accessor(js))
        return js, data
    return fn


def numeric_edits() -> list[tuple]:
    nan, inf = math.nan, math.inf
    E = []
    for name, value in (("nan", nan), ("inf", inf), ("ninf", -inf), ("huge", 3e38)):
        E.append((f"position-{name}", _nan_bin(_pos, value, k=3), "refuse-or-repair", 3))
        E.append((f"weights-{name}", _nan_bin(_weights, value, k=2), "refuse-or-repair", 3))
        E.append((f"ibm-{name}", _nan_bin(_ibm, value, k=1, comp=5), "refuse", 3))
        E.append((f"anim-rot-{name}", _nan_bin(_anim_acc("rotation", "output"), value, k=1), "refuse-or-repair", 3))
        E.append((f"anim-time-{name}", _nan_bin(_anim_acc("rotation", "input"), value, k=1), "refuse", 3))
    E.append(("ibm-zero", lambda js, d: (js, set_floats(js, d, _ibm(js), lambda i, v: [0.0] * 16 if i == 1 else v)),
              "refuse", 4))
    E.append(("ibm-singular", lambda js, d: (js, set_floats(js, d, _ibm(js), lambda i, v: v[:4] * 4 if i == 1 else v)),
              "refuse", 4))
    E.append(("ibm-1e30", lambda js, d: (js, set_floats(js, d, _ibm(js), lambda i, v: [x * 1e30 for x in v]
                                                         if i == 2 else v)), "refuse", 3))
    for name, value in (("nan", [nan, 0, 0]), ("inf", [inf, 0, 0]), ("1e300", [1e300, 0, 0]),
                        ("1e38", [1e38, 0, 0])):
        E.append((f"node-translation-{name}", _set(["nodes", _joint_node(1), "translation"], value), "refuse", 3))
    for name, value in (("zero", [0, 0, 0]), ("nan", [nan, 1, 1]), ("1e300", [1e300, 1e300, 1e300]),
                        ("neg", [-1, 1, 1])):
        E.append((f"node-scale-{name}", _set(["nodes", _joint_node(1), "scale"], value),
                  "refuse-or-repair" if name == "neg" else "refuse", 4))
    E.append(("node-matrix-zero", lambda js, d: (_matrix_node(js, [0.0] * 16), (js, d))[1], "refuse", 4))
    E.append(("node-matrix-nan", lambda js, d: (_matrix_node(js, [nan] + [0.0] * 15), (js, d))[1], "refuse", 3))
    E.append(("root-translation-1e300", _set(["nodes", _joint_node(0), "translation"], [1e300, 0, 0]), "refuse", 3))
    return E


def _matrix_node(js, m):
    node = js["nodes"][_joint_node(1)(js)]
    for k in ("translation", "rotation", "scale"):
        node.pop(k, None)
    node["matrix"] = m


def quaternion_edits() -> list[tuple]:
    E = []
    # [1e300, 0, 0, 1e300] has a direction like [2, 0, 0, 0]: normalized (without overflow) with a warning
    for name, q, expect in (("zero", [0, 0, 0, 0], "refuse-or-repair"),
                            ("1e300", [1e300, 0, 0, 1e300], "refuse-or-repair"),
                            ("unnormalized", [2, 0, 0, 0], "refuse-or-repair"), ("nan", [math.nan, 0, 0, 1], "refuse"),
                            ("tiny", [1e-30, 0, 0, 1e-30], "refuse-or-repair"),
                            ("3-values", [0, 0, 1], "refuse")):
        E.append((f"node-rot-{name}", _set(["nodes", _joint_node(1), "rotation"], q), expect, 10))
    E.append(("anim-rot-zero", lambda js, d: (js, set_floats(js, d, _anim_acc("rotation", "output")(js),
                                                             lambda i, v: [0.0] * 4 if i == 1 else v)),
              "refuse-or-repair", 10))
    E.append(("anim-rot-1e30", lambda js, d: (js, set_floats(js, d, _anim_acc("rotation", "output")(js),
                                                             lambda i, v: [1e30, 0, 0, 1e30] if i == 1 else v)),
              "refuse-or-repair", 10))
    return E


def time_edits() -> list[tuple]:
    def times(fn):
        def edit(js, data):
            idx = _anim_acc("rotation", "input")(js)
            data = set_floats(js, data, idx, lambda i, v: [fn(i, v[0])])
            _drop_minmax(js, idx)
            return js, data
        return edit
    return [
        ("anim-times-negative", times(lambda i, t: t - 5.0), "refuse-or-repair", 10),
        ("anim-time-first-neg", times(lambda i, t: -1.0 if i == 0 else t), "refuse-or-repair", 10),
        ("anim-times-decreasing", times(lambda i, t: -t), "refuse", 10),
        # equal key times are the documented repair (sorted, duplicates dropped), however many are equal
        ("anim-times-constant", times(lambda i, t: 0.5), "refuse-or-repair", 10),
        ("anim-times-1e30", times(lambda i, t: t * 1e30), "refuse", 10),
        ("anim-times-1e38-last", times(lambda i, t: 3e38 if i > 0 else t), "refuse", 10),
        ("anim-output-count-short", lambda js, d: (js["accessors"][_anim_acc("rotation", "output")(js)].__setitem__(
            "count", 1), (js, d))[1], "refuse", None),
    ]


def extension_edits() -> list[tuple]:
    def ext(required, used=None):
        def fn(js, data):
            js["extensionsUsed"] = list(used if used is not None else required)
            if required:
                js["extensionsRequired"] = list(required)
            return js, data
        return fn
    return [
        ("ext-required-unknown", ext(["RIGMIX_unknown_extension"]), "refuse", 10),
        ("ext-required-draco", ext(["KHR_draco_mesh_compression"]), "refuse", 10),
        ("ext-required-not-used", lambda js, d: (js.__setitem__("extensionsRequired", ["EXT_foo"]), (js, d))[1],
         "refuse", 10),
        ("ext-used-unknown", ext([], ["EXT_something_else"]), "any", None),
        ("ext-required-str", lambda js, d: (js.__setitem__("extensionsRequired", "KHR_x"), (js, d))[1], "refuse",
         10),
        ("ext-node-bogus", lambda js, d: (js["nodes"][0].__setitem__("extensions", {"X_bogus": {"a": [1, 2]}}),
                                          js.setdefault("extensionsUsed", []).append("X_bogus"), (js, d))[2],
         "any", None),
    ]


def component_edits() -> list[tuple]:
    E = []
    for name, ctype in (("uint", 5125), ("short", 5122), ("ushort", 5123), ("byte", 5120)):
        E.append((f"position-{name}", _set(["accessors", _pos, "componentType"], ctype), "refuse-or-repair", 10))
    for name, ctype in (("uint", 5125), ("byte", 5120), ("short", 5122)):
        E.append((f"weights-{name}", _set(["accessors", _weights, "componentType"], ctype), "refuse-or-repair", 10))
    for name, ctype in (("float", 5126), ("byte", 5120), ("uint", 5125)):
        E.append((f"joints-{name}", _set(["accessors", _joints, "componentType"], ctype), "refuse-or-repair", 10))
    E.append(("indices-float", lambda js, d: (js["accessors"][_prim(js)["indices"]].__setitem__("componentType",
                                                                                                 5126), (js, d))[1],
              "refuse", None))
    E.append(("ibm-ushort", _set(["accessors", _ibm, "componentType"], 5123), "refuse", 10))
    E.append(("anim-time-ubyte", _set(["accessors", _anim_acc("rotation", "input"), "componentType"], 5121),
              "refuse", 10))
    return E


def scene_edits() -> list[tuple]:
    first = lambda js: 0  # noqa: E731
    return [
        ("scene-nodes-999", _set(["scenes", first, "nodes"], [999]), "refuse", 10),
        ("scene-nodes-neg", _set(["scenes", first, "nodes"], [-1]), "refuse", 10),
        ("scene-index-5", _set(["scene"], 5), "refuse", 10),
        ("scenes-empty", _set(["scenes"], []), "refuse", 10),
        # read with a warning: rigmix reads every node, whatever the scene lists
        ("scene-nodes-empty", _set(["scenes", first, "nodes"], []), "refuse-or-repair", None),
        ("scene-nodes-midjoint", lambda js, d: (js["scenes"][js.get("scene", 0)]["nodes"].append(_joint_node(2)(js)),
                                                (js, d))[1], "refuse", 10),
    ]


def name_edits() -> list[tuple]:
    """Valid glTF (names are free text): what ``inspect`` prints must be escaped (finding 8)."""
    names = {
        "ansi": "\x1b[2J\x1b[31mRED\x1b[0m",
        "newline": "arm\nrigmix: error: forged line",
        "cr": "arm\rOVERWRITE",
        "nul": "arm\x00hidden",
        "bell-bs": "a\x07\x08\x08b",
        "bidi": "arm\u202egnp.exe",
        "osc": "\x1b]0;owned\x07title",
        "long": "J" * 200000,
    }
    E = []
    for name, text in names.items():
        E.append((f"name-joint-{name}", _set(["nodes", _joint_node(1), "name"], text), "any", 8))
    E.append(("name-anim-ansi", _set(["animations", lambda js: 0, "name"], names["ansi"]), "any", 8))
    E.append(("name-mesh-newline", _set(["meshes", lambda js: 0, "name"], names["newline"]), "any", 8))
    return E


def size_edits() -> list[tuple]:
    def deep_chain(n):
        def fn(js, data):
            base = len(js["nodes"])
            js["nodes"].extend({"name": f"deep{i}", "children": [base + i + 1]} for i in range(n - 1))
            js["nodes"].append({"name": f"deep{n - 1}"})
            js["scenes"][js.get("scene", 0)]["nodes"].append(base)
            return js, data
        return fn

    def joint_chain(n):
        def fn(js, data):
            base = len(js["nodes"])
            js["nodes"].extend({"name": f"c{i}", "translation": [0, 0.001, 0], "children": [base + i + 1]}
                               for i in range(n - 1))
            js["nodes"].append({"name": f"c{n - 1}"})
            last = js["skins"][0]["joints"][-1]
            js["nodes"][last].setdefault("children", []).append(base)
            js["skins"][0]["joints"] = js["skins"][0]["joints"] + list(range(base, base + n))
            js["skins"][0].pop("inverseBindMatrices", None)
            return js, data
        return fn

    def whitespace(js, data):
        return glb(json.dumps(js).encode() + b" " * (64 << 20), data)

    return [
        ("deep-nodes-100k", deep_chain(100000), "any", 5),
        ("deep-nodes-5k", deep_chain(5000), "any", 5),
        ("joint-chain-20k", joint_chain(20000), "any", 5),
        ("json-64mb-spaces", whitespace, "any", 5),
        ("nodes-1m-empty", lambda js, d: (js["nodes"].extend({} for _ in range(1000000)), (js, d))[1], "any", 5),
        ("string-nesting", lambda js, d: glb(json.dumps(js)[:-1].encode() + b', "extras": ' + b"[" * 100000
                                             + b"]" * 100000 + b"}", d), "refuse-or-repair", None),
    ]


def structured_cases() -> list[Case]:
    groups = [("json-edit", structure_edits()), ("huge-count", huge_edits()), ("cycle", cycle_edits()),
              ("nan-inf", numeric_edits()), ("quaternion", quaternion_edits()), ("anim-time", time_edits()),
              ("extension", extension_edits()), ("component-type", component_edits()), ("scene", scene_edits()),
              ("name", name_edits()), ("size", size_edits())]
    out = []
    for category, edits in groups:
        for name, fn, expect, finding in edits:
            seeds = ("RiggedFigure", "Fox") if category in ("nan-inf", "quaternion", "component-type") else \
                ("RiggedFigure",)
            for seed in seeds:
                if seed == "Fox" and name == "indices-float":  # the Fox has no indices
                    continue
                out.append(_glb_case(f"{category}-{seed}-{name}", category, expect, name, fn, finding, seed))
    return out


# -- URIs, special files


def _external(seed: str, folder: Path, *, buffer_uri=None, image_uri=None, color_uri=None, bin_name=None,
              byte_length=None) -> Path:
    """``seed`` as a .gltf with an external ``.bin`` in ``folder``; then buffer 0's URI replaced by
    ``buffer_uri``, image 0's by ``image_uri`` (an image added when there is none), or a second
    buffer at ``color_uri`` read as the COLOR_0 of the skinned primitive."""
    js, data = seed_doc(seed)
    bin_name = bin_name or f"{seed}.bin"
    (folder / f"{seed}.bin").write_bytes(data)
    js["buffers"][0]["uri"] = bin_name
    if buffer_uri is not None:
        js["buffers"][0]["uri"] = buffer_uri
    if byte_length is not None:
        js["buffers"][0]["byteLength"] = byte_length
    if image_uri is not None:
        if js.get("images"):
            img = js["images"][0]
            img.pop("bufferView", None)
            img.pop("mimeType", None)
            img["uri"] = image_uri
        else:
            js["images"] = [{"uri": image_uri}]
            js["textures"] = [{"source": 0}]
            js["materials"] = js.get("materials") or [{}]
            js["materials"][0].setdefault("pbrMetallicRoughness", {})["baseColorTexture"] = {"index": 0}
            _prim(js)["material"] = 0
    if color_uri is not None:
        n = js["accessors"][_pos(js)]["count"]
        js["buffers"].append({"uri": color_uri, "byteLength": 16384})
        js["bufferViews"].append({"buffer": len(js["buffers"]) - 1, "byteOffset": 0, "byteLength": 16 * n})
        js["accessors"].append({"bufferView": len(js["bufferViews"]) - 1, "componentType": 5126, "count": n,
                                "type": "VEC4"})
        _prim(js)["attributes"]["COLOR_0"] = len(js["accessors"]) - 1
    path = folder / f"{seed}.gltf"
    path.write_text(json.dumps(js))
    return path


def uri_cases() -> list[Case]:
    """URIs that must resolve inside the asset folder only (finding 1)."""
    targets = {
        "dotdot": lambda ws, f, t: os.path.relpath(t, f),
        "dotdot-deep": lambda ws, f, t: "../" * 12 + str(t).lstrip("/"),
        "absolute": lambda ws, f, t: str(t),
        "pct-dotdot": lambda ws, f, t: os.path.relpath(t, f).replace("..", "%2e%2e"),
        "pct-slash": lambda ws, f, t: os.path.relpath(t, f).replace("/", "%2F"),
        "pct-abs": lambda ws, f, t: str(t).replace("/", "%2F"),
        "file-scheme": lambda ws, f, t: "file://" + str(t),
        "file-scheme-1slash": lambda ws, f, t: "file:" + str(t),
        "backslash": lambda ws, f, t: os.path.relpath(t, f).replace("/", "\\"),
        "inner-dotdot": lambda ws, f, t: "sub/../" + os.path.relpath(t, f),
    }
    out = []
    for tname, uri in targets.items():
        for role in ("buffer", "image", "color"):
            cid = f"uri-{role}-{tname}"

            def make(folder, ws, uri=uri, role=role):
                target = ws.sentinel_png if role == "image" else ws.sentinel_bin
                u = uri(ws, folder, target)
                if role == "buffer":
                    (folder / "RiggedFigure.bin").write_bytes(b"")  # the real one is not used
                    return _external("RiggedFigure", folder, buffer_uri=u, byte_length=16384)
                if role == "image":
                    return _external("Fox", folder, image_uri=u)
                return _external("RiggedFigure", folder, color_uri=u)
            out.append(Case(cid, "uri", "file", "refuse", f"{role} URI {tname} to a sentinel outside", 1, make))
    for role in ("buffer", "image"):
        out.append(Case(f"uri-{role}-etc-passwd", "uri", "file", "refuse", f"{role} URI ../../etc/passwd", 1,
                        lambda folder, ws, role=role: _external(
                            "RiggedFigure" if role == "buffer" else "Fox", folder,
                            **({"buffer_uri": "../" * 16 + "etc/passwd"} if role == "buffer"
                               else {"image_uri": "/etc/passwd"}))))
        # a missing buffer is refused; a missing image (inside the folder) drops its texture with a warning
        out.append(Case(f"uri-{role}-missing", "uri", "file", "refuse" if role == "buffer" else "refuse-or-repair",
                        f"{role} URI to a missing file", 1,
                        lambda folder, ws, role=role: _external(
                            "RiggedFigure" if role == "buffer" else "Fox", folder,
                            **({"buffer_uri": "nope.bin"} if role == "buffer" else {"image_uri": "nope.png"}))))
        out.append(Case(f"uri-{role}-http", "uri", "file", "refuse", f"{role} URI http://", 1,
                        lambda folder, ws, role=role: _external(
                            "RiggedFigure" if role == "buffer" else "Fox", folder,
                            **({"buffer_uri": "http://127.0.0.1:9/x.bin"} if role == "buffer"
                               else {"image_uri": "http://127.0.0.1:9/x.png"}))))
    # data: URIs
    def data_uri(payload: bytes, declared=None, mime="application/octet-stream", b64=True):
        def make(folder, ws):
            js, data = seed_doc("RiggedFigure")
            enc = base64.b64encode(payload).decode() if b64 else payload.decode("latin-1")
            js["buffers"][0]["uri"] = f"data:{mime};base64,{enc}" if b64 else f"data:{mime},{enc}"
            js["buffers"][0]["byteLength"] = len(payload) if declared is None else declared
            path = folder / "data.gltf"
            path.write_text(json.dumps(js))
            return path
        return make
    rf = seed_doc("RiggedFigure")[1] if (ASSETS / SEEDS["RiggedFigure"][0]).exists() else b""
    out += [
        Case("uri-data-ok", "uri", "file", "any", "the buffer as a valid data: URI", None, data_uri(rf)),
        Case("uri-data-bad-base64", "uri", "file", "refuse", "invalid base64", 1,
             lambda f, ws: _data_text(f, "data:application/octet-stream;base64,!!!not*base64")),
        Case("uri-data-short", "uri", "file", "refuse", "data shorter than byteLength", 1,
             data_uri(rf[: len(rf) // 2], declared=len(rf))),
        Case("uri-data-declared-huge", "uri", "file", "refuse", "byteLength 2**40 with a small data: URI", 1,
             data_uri(rf, declared=2**40)),
        Case("uri-data-oversized", "uri", "file", "refuse", "a 48 MB data: URI for a 1 kB buffer", 5,
             data_uri(b"\0" * (48 << 20), declared=1024)),
        Case("uri-data-no-base64", "uri", "file", "refuse-or-repair", "data: URI without ;base64", 1,
             data_uri(b"abcd", b64=False)),
    ]
    return out


def _data_text(folder: Path, uri: str) -> Path:
    js, _ = seed_doc("RiggedFigure")
    js["buffers"][0]["uri"] = uri
    path = folder / "data.gltf"
    path.write_text(json.dumps(js))
    return path


def special_cases() -> list[Case]:
    """Symlinks out, FIFOs, devices and folders as buffers, images and the file itself."""
    def link(target_of):
        def make(folder, ws, role):
            (folder / "link.bin").symlink_to(target_of(ws))
            if role == "buffer":
                return _external("RiggedFigure", folder, buffer_uri="link.bin", byte_length=16384)
            return _external("Fox", folder, image_uri="link.bin")
        return make

    def fifo(folder, ws, role):
        os.mkfifo(folder / "link.bin")
        if role == "buffer":
            return _external("RiggedFigure", folder, buffer_uri="link.bin")
        return _external("Fox", folder, image_uri="link.bin")

    def directory(folder, ws, role):
        (folder / "link.bin").mkdir()
        if role == "buffer":
            return _external("RiggedFigure", folder, buffer_uri="link.bin")
        return _external("Fox", folder, image_uri="link.bin")

    kinds = {
        "symlink-out": (link(lambda ws: ws.sentinel_bin), False),
        "symlink-dev-zero": (link(lambda ws: Path("/dev/zero")), True),
        "symlink-dev-urandom": (link(lambda ws: Path("/dev/urandom")), True),
        "fifo": (fifo, True),
        "directory": (directory, True),
        "symlink-proc": (link(lambda ws: Path("/proc/self/environ")), True),
    }
    out = []
    for kname, (make, special) in kinds.items():
        for role in ("buffer", "image"):
            out.append(Case(f"special-{role}-{kname}", "special-file", "file", "refuse", f"{role} URI to {kname}", 1,
                            lambda folder, ws, make=make, role=role: make(folder, ws, role), special=special))

    def self_link(target_of, name="model.glb"):
        def make(folder, ws):
            (folder / name).symlink_to(target_of(ws))
            return folder / name
        return make

    def self_fifo(folder, ws):
        os.mkfifo(folder / "model.glb")
        return folder / "model.glb"

    def self_dir(folder, ws):
        (folder / "model.glb").mkdir()
        return folder / "model.glb"
    out += [
        Case("special-file-dev-zero", "special-file", "file", "refuse", "the .glb is a symlink to /dev/zero", 1,
             self_link(lambda ws: Path("/dev/zero")), special=True),
        Case("special-file-gltf-dev-zero", "special-file", "file", "refuse", "the .gltf is a symlink to /dev/zero",
             1, self_link(lambda ws: Path("/dev/zero"), "model.gltf"), special=True),
        Case("special-file-fifo", "special-file", "file", "refuse", "the .glb is a FIFO", 1, self_fifo,
             special=True),
        Case("special-file-directory", "special-file", "file", "refuse", "the .glb is a folder", 1, self_dir,
             special=True),
        # the file named on the command line (or in the config) is the user's choice, trusted like
        # the command line (README, Security): a link to a GLB elsewhere is read; what the file names
        # (URIs) stays confined to the link's folder
        Case("special-file-symlink-out", "special-file", "file", "any",
             "the .glb is a symlink to a GLB outside the folder", 1,
             self_link(lambda ws: ws.sentinel_glb)),
        Case("special-file-empty", "special-file", "file", "refuse", "an empty .glb", None,
             lambda folder, ws: _file(folder, "model.glb", b"")),
        Case("special-file-gltf-is-glb", "special-file", "file", "any", "GLB bytes named .gltf", None,
             lambda folder, ws: _file(folder, "model.gltf", seed_bytes("RiggedFigure"))),
        Case("special-file-png", "special-file", "file", "refuse", "a PNG named .glb", None,
             lambda folder, ws: _file(folder, "model.glb", _png(b"x"))),
    ]
    return out


def file_cases() -> list[Case]:
    """Every hostile character file, in a fixed order."""
    return (truncation_cases() + header_cases() + flip_cases() + structured_cases() + uri_cases()
            + special_cases())


# --------------------------------------------------------------------------- configs


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(cfg: dict) -> str:
    """A small TOML writer for the config shapes used here (tables, arrays of tables)."""
    lines = []
    for k, v in cfg.items():
        if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
            lines.append(f"{json.dumps(k)} = {_toml_value(v)}")
    for k, v in cfg.items():
        if isinstance(v, dict):
            if k == "characters":
                for cid, ch in v.items():
                    lines.append(f"\n[characters.{json.dumps(cid)}]")
                    lines += [f"{json.dumps(a)} = {_toml_value(b)}" for a, b in ch.items()]
            else:
                lines.append(f"\n[{json.dumps(k)}]")
                lines += [f"{json.dumps(a)} = {_toml_value(b)}" for a, b in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                lines.append(f"\n[[{json.dumps(k)}]]")
                lines += [f"{json.dumps(a)} = {_toml_value(b)}" for a, b in item.items()]
    return "\n".join(lines) + "\n"


def base_config() -> dict:
    """A valid composition: RiggedFigure's left arm replaced by CesiumMan's (both ~1.5 m)."""
    return {
        "name": "fuzzbase",
        "characters": {
            "body": {"path": "${RIGMIX_ASSETS}/RiggedFigure/RiggedFigure.glb"},
            "donor": {"path": "${RIGMIX_ASSETS}/CesiumMan/CesiumMan.glb", "scale": 1.0},
        },
        "actions": [{"op": "replace", "source": "donor", "source_joint": "Skeleton_arm_joint_L__4_",
                     "target": "body", "target_joint": "arm_joint_L_1"}],
    }


COMPOSE_ARGV = ("compose", "{config}", "-o", "{out}/composed.glb", "--report", "{out}/report.json",
                "--no-feature-field")


def _config_case(cid, category, expect, note, edit, finding=None, argv=COMPOSE_ARGV, prepare=None,
                 text=None) -> Case:
    def make(folder, ws):
        if prepare is not None:
            prepare(folder, ws)
        path = folder / "config.toml"
        if text is not None:
            path.write_bytes(text(folder, ws) if callable(text) else text)
        else:
            cfg = base_config()
            res = edit(cfg, folder, ws)
            path.write_text(to_toml(res if res is not None else cfg))
        return path
    return Case(cid, category, "config", expect, note, finding, make, argv=tuple(argv))


def _cset(*path_and_value):
    """An edit setting ``cfg[path...] = value`` (intermediate dicts created)."""
    *path, value = path_and_value

    def edit(cfg, folder, ws):
        parent = cfg
        for k in path[:-1]:
            parent = parent.setdefault(k, {}) if isinstance(parent, dict) else parent[k]
        parent[path[-1]] = value
    return edit


def config_cases() -> list[Case]:
    out = []
    # unknown keys, in every section
    for where in (("bogus",), ("characters", "body", "bogus"), ("characters", "body", "placement", "bogus"),
                  ("characters", "body", "rotations", "arm_joint_L_1", "bogus"), ("actions", 0, "bogus"),
                  ("mapping", "bogus"), ("positioning", "bogus"), ("fusion", "bogus"), ("weights", "bogus"),
                  ("animation", "bogus")):
        def edit(cfg, folder, ws, where=where):
            if where[:3] == ("characters", "body", "rotations"):
                cfg["characters"]["body"]["rotations"] = {"arm_joint_L_1": {"euler": [0, 0, 10], "bogus": 1}}
                return
            if where[:3] == ("characters", "body", "placement"):
                cfg["characters"]["body"]["placement"] = {"translation": [0, 0, 0], "bogus": 1}
                return
            _cset(*where, 1)(cfg, folder, ws)
        out.append(_config_case("cfg-unknown-" + "-".join(map(str, where[:-1])) or "cfg-unknown-top",
                                "config-unknown-key", "refuse", f"unknown key at {where}", edit))
    out[0] = _config_case("cfg-unknown-top", "config-unknown-key", "refuse", "unknown top-level key",
                          _cset("bogus", 1))
    # wrong types
    wrong = [
        ("name-int", ("name", 5)), ("characters-list", ("characters", [1, 2])),
        ("path-int", ("characters", "body", "path", 3)), ("scale-str", ("characters", "donor", "scale", "big")),
        ("scale-bool", ("characters", "donor", "scale", True)),
        ("rotations-int", ("characters", "body", "rotations", 5)),
        ("rotation-5", ("characters", "body", "rotations", {"arm_joint_L_1": [1, 2, 3, 4, 5]})),
        ("translation-str", ("characters", "donor", "placement", {"translation": "x"})),
        ("translation-2", ("characters", "donor", "placement", {"translation": [1, 2]})),
        ("actions-dict", ("actions", {"op": "remove"})),
        ("op-int", ("actions", 0, "op", 3)), ("mode-mix", ("actions", 0, "mode", "mix")),
        ("mapping-score-int", ("mapping", "score", 1)), ("translate-str", ("positioning", "translate", "yes")),
        ("smooth-iterations-ten", ("fusion", "smooth_iterations", "ten")), ("snap-str", ("fusion", "snap", "0.5")),
        ("weights-method-int", ("weights", "method", 3)), ("fps-str", ("animation", "fps", "30")),
        ("backend-cuda", ("fusion", "backend", "cuda")), ("max-influences-float", ("weights", "max_influences", 1.5)),
        ("mirror-str", ("characters", "donor", "mirror", "w")),
    ]
    for name, pv in wrong:
        finding = 4 if name == "smooth-iterations-ten" else None
        out.append(_config_case(f"cfg-type-{name}", "config-type", "refuse", name, _cset(*pv), finding))
    # out-of-range numbers
    ranges = [
        ("placement-1e308", ("characters", "donor", "placement", {"translation": [1e308, 0, 0]}), 2),
        ("placement-neg1e308", ("characters", "donor", "placement", {"translation": [-1e308, 0, 0]}), 2),
        ("placement-1e30", ("characters", "donor", "placement", {"translation": [1e30, 0, 0]}), 2),
        ("placement-nan", ("characters", "donor", "placement", {"translation": [math.nan, 0, 0]}), 2),
        ("placement-inf", ("characters", "donor", "placement", {"translation": [math.inf, 0, 0]}), 2),
        ("scale-1e9", ("characters", "donor", "scale", 1e9), 4),
        ("scale-1e-9", ("characters", "donor", "scale", 1e-9), 4),
        ("scale-0", ("characters", "donor", "scale", 0), 4),
        ("scale-neg", ("characters", "donor", "scale", -1), 4),
        ("scale-1e308", ("characters", "donor", "scale", 1e308), 4),
        ("scale-inf", ("characters", "donor", "scale", math.inf), 4),
        ("voxel-factor-neg", ("fusion", "voxel_factor", -1), 4),
        ("voxel-factor-0", ("fusion", "voxel_factor", 0), 4),
        ("voxel-factor-1e-9", ("fusion", "voxel_factor", 1e-9), 5),
        ("max-voxels-1e12", ("fusion", "max_voxels", 10**12), 5),
        ("min-voxels-across-1e6", ("fusion", "min_voxels_across", 10**6), 5),
        ("smooth-iterations-1e9", ("fusion", "smooth_iterations", 10**9), 5),
        ("band-voxels-1e9", ("fusion", "band_voxels", 1e9), 5),
        ("margin-voxels-1e9", ("fusion", "margin_voxels", 10**9), 5),
        ("fps-1e9", ("animation", "fps", 1e9), 5),
        ("fps-1e-9", ("animation", "fps", 1e-9), 5),
        ("match-angle-1000", ("weights", "match_angle", 1000), None),
        ("max-influences-1e6", ("weights", "max_influences", 10**6), 5),
        ("euler-1e308", ("characters", "body", "rotations", {"arm_joint_L_1": [1e308, 0, 0]}), 2),
        ("quat-1e300", ("characters", "body", "rotations", {"arm_joint_L_1": [1e300, 0, 0, 1e300]}), 10),
        ("quat-zero", ("characters", "body", "rotations", {"arm_joint_L_1": [0, 0, 0, 0]}), None),
        ("quat-nan", ("characters", "body", "rotations", {"arm_joint_L_1": [math.nan, 0, 0, 1]}), None),
        ("injectivity-inf", ("mapping", "injectivity_bonus", [math.inf, 0.1]), None),
        ("snap-2", ("fusion", "snap", 2.0), None),
        ("smooth-iterations-neg", ("fusion", "smooth_iterations", -1), None),
    ]
    for name, pv, finding in ranges:
        out.append(_config_case(f"cfg-range-{name}", "config-range", "refuse", name, _cset(*pv), finding))
    # actions that make no sense
    def act(*actions):
        def edit(cfg, folder, ws):
            cfg["actions"] = [dict(a) for a in actions]
        return edit
    rep = {"op": "replace", "source": "donor", "source_joint": "Skeleton_arm_joint_L__4_", "target": "body",
           "target_joint": "arm_joint_L_1"}
    out += [
        _config_case("cfg-act-remove-root", "config-action", "refuse", "remove the root joint",
                     act({"op": "remove", "target": "body", "target_joint": "torso_joint_1"}), 4),
        _config_case("cfg-act-replace-root", "config-action", "any", "replace the root joint",
                     act(dict(rep, target_joint="torso_joint_1")), None),
        _config_case("cfg-act-replace-twice", "config-action", "refuse", "the same target joint replaced twice",
                     act(rep, rep), 10),
        _config_case("cfg-act-replace-twice-sources", "config-action", "refuse",
                     "one target joint replaced by two different source joints",
                     act(rep, dict(rep, source_joint="Skeleton_arm_joint_R__2_")), 10),
        _config_case("cfg-act-attach-removed", "config-action", "refuse", "attach to a removed joint",
                     act({"op": "remove", "target": "body", "target_joint": "arm_joint_L_1"},
                         dict(rep, op="attach", target_joint="arm_joint_L_2")), None),
        # a joint replaced by itself is the identity (rigmix.operations.plan; PIPELINE.md section 7)
        _config_case("cfg-act-self", "config-action", "any", "a joint replaced by itself",
                     act(dict(rep, source="body", source_joint="arm_joint_L_1")), None),
        _config_case("cfg-act-unknown-character", "config-action", "refuse", "unknown character id",
                     act(dict(rep, source="ghost")), None),
        _config_case("cfg-act-unknown-joint", "config-action", "refuse", "unknown joint",
                     act(dict(rep, source_joint="NoSuchJoint")), None),
        # actions are optional (Config.actions): each character is then a body, composed unfused
        _config_case("cfg-act-none", "config-action", "any", "no actions", act(), None),
        _config_case("cfg-act-2000", "config-action", "refuse", "2000 identical actions",
                     act(*([rep] * 2000)), 10),
        _config_case("cfg-act-empty-joint", "config-action", "refuse", "empty joint name",
                     act(dict(rep, target_joint="")), None),
    ]
    # character paths
    def path_to(fn, prepare=None):
        def edit(cfg, folder, ws):
            if prepare:
                prepare(folder, ws)
            cfg["characters"]["donor"]["path"] = fn(folder, ws)
        return edit

    def fifo(folder, ws):
        os.mkfifo(folder / "fifo.glb")

    out += [
        _config_case("cfg-path-missing", "config-path", "refuse", "missing file", path_to(lambda f, ws: "nope.glb")),
        _config_case("cfg-path-etc-passwd", "config-path", "refuse", "/etc/passwd as a character",
                     path_to(lambda f, ws: "../" * 16 + "etc/passwd")),
        _config_case("cfg-path-dev-zero", "config-path", "refuse", "/dev/zero as a character", path_to(
            lambda f, ws: "/dev/zero"), 1),
        _config_case("cfg-path-directory", "config-path", "refuse", "a folder as a character", path_to(
            lambda f, ws: "."), None),
        _config_case("cfg-path-fifo", "config-path", "refuse", "a FIFO as a character",
                     path_to(lambda f, ws: "fifo.glb", fifo), 1),
        _config_case("cfg-path-undefined-var", "config-path", "refuse", "${UNDEFINED} in a path",
                     path_to(lambda f, ws: "${RIGMIX_FUZZ_UNDEFINED}/x.glb")),
        _config_case("cfg-path-config-itself", "config-path", "refuse", "the config as a character",
                     path_to(lambda f, ws: "config.toml")),
        _config_case("cfg-path-text", "config-path", "refuse", "a text file named .glb",
                     path_to(lambda f, ws: "notes.glb",
                             lambda f, ws: (f / "notes.glb").write_text("hello\n"))),
        _config_case("cfg-path-builtin-nope", "config-path", "refuse", "unknown builtin",
                     path_to(lambda f, ws: "builtin:nope")),
        _config_case("cfg-path-empty", "config-path", "refuse", "empty path", path_to(lambda f, ws: "")),
        _config_case("cfg-path-hostile-gltf", "config-path", "refuse", "a .gltf whose buffer URI escapes",
                     path_to(lambda f, ws: "evil.gltf", lambda f, ws: _external(
                         "CesiumMan", f, color_uri=os.path.relpath(ws.sentinel_bin, f)).rename(f / "evil.gltf")),
                     1),
        _config_case("cfg-path-url", "config-path", "refuse", "an http URL as a path",
                     path_to(lambda f, ws: "http://127.0.0.1:9/x.glb")),
    ]
    # TOML itself
    out += [
        _config_case("cfg-toml-syntax", "config-toml", "refuse", "invalid TOML", None, text=b"name = \n[[["),
        _config_case("cfg-toml-binary", "config-toml", "refuse", "binary garbage", None,
                     text=bytes(random.Random("bin").randrange(256) for _ in range(4096))),
        _config_case("cfg-toml-bom", "config-toml", "refuse-or-repair", "UTF-8 BOM", None,
                     text=lambda f, ws: b"\xef\xbb\xbf" + to_toml(base_config()).encode()),
        _config_case("cfg-toml-dup-key", "config-toml", "refuse", "duplicate key", None,
                     text=b'name = "a"\nname = "b"\n'),
        _config_case("cfg-toml-huge-string", "config-toml", "refuse", "a 20 MB name and no characters", None,
                     text=b'name = "' + b"x" * (20 << 20) + b'"\n'),
        _config_case("cfg-toml-deep-arrays", "config-toml", "refuse", "arrays nested 100000 deep", None,
                     text=b"name = " + b"[" * 100000 + b"]" * 100000 + b"\n"),
        _config_case("cfg-toml-empty", "config-toml", "refuse", "empty file", None, text=b""),
    ]
    # outputs that are inputs (finding 6)
    def copy_body(folder, ws):
        (folder / "body.glb").write_bytes(seed_bytes("RiggedFigure"))

    def local_body(cfg, folder, ws):
        copy_body(folder, ws)
        cfg["characters"]["body"]["path"] = "body.glb"
    out += [
        _config_case("cfg-out-is-input", "config-output", "refuse", "-o names the input character", local_body, 6,
                     argv=("compose", "{config}", "-o", "{case}/body.glb")),
        _config_case("cfg-report-is-input", "config-output", "refuse", "--report names the input character",
                     local_body, 6, argv=("compose", "{config}", "-o", "{out}/x.glb", "--report", "{case}/body.glb")),
        _config_case("cfg-report-is-config", "config-output", "refuse", "--report names the config", local_body, 6,
                     argv=("compose", "{config}", "-o", "{out}/x.glb", "--report", "{config}")),
        _config_case("cfg-report-is-output", "config-output", "refuse", "--report and -o name one file",
                     local_body, 6, argv=("compose", "{config}", "-o", "{out}/x.glb", "--report", "{out}/x.glb")),
        _config_case("cfg-out-is-config", "config-output", "refuse", "-o names the config", local_body, 6,
                     argv=("compose", "{config}", "-o", "{config}")),
    ]
    return out


def all_cases() -> list[Case]:
    """The whole corpus: files, then configs; ids are unique."""
    cases = file_cases() + config_cases()
    ids = [c.id for c in cases]
    assert len(ids) == len(set(ids)), sorted({i for i in ids if ids.count(i) > 1})
    return cases


# --------------------------------------------------------------------------- running one case


@dataclass
class Run:
    """One subprocess: its command, exit status, output and resources."""

    argv: list
    rc: int | None
    stdout: bytes
    stderr: bytes
    seconds: float
    peak_rss_mb: float
    timed_out: bool
    opens: list  # (path, mode) of every `open` audit event


def _limit():
    os.setsid()
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def run_rigmix(args, ws: Workspace, *, timeout: float = TIMEOUT, name: str = "run") -> Run:
    """``python -m rigmix.cli ARGS`` with the audit hook, a memory limit and a timeout (the process
    group is killed on timeout). Peak RSS from ``wait4`` of that child."""
    log = ws.root / "logs" / f"{name}.opens"
    log.parent.mkdir(exist_ok=True)
    log.unlink(missing_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ws.hook), str(ROOT)] + (
        [env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env["RIGMIX_FUZZ_OPEN_LOG"] = str(log)
    env.setdefault("RIGMIX_ASSETS", str(ASSETS))
    env["TQDM_DISABLE"] = "1"
    argv = [sys.executable, "-m", "rigmix.cli", *map(str, args)]
    out_f, err_f = ws.root / "logs" / f"{name}.out", ws.root / "logs" / f"{name}.err"
    t0 = time.monotonic()
    with open(out_f, "wb") as out, open(err_f, "wb") as err:
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=out, stderr=err, cwd=ROOT, env=env,
                                preexec_fn=_limit)
        timed_out = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() - t0 > timeout:
                timed_out = True
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.02)
    rc = os.waitstatus_to_exitcode(status)
    proc.returncode = rc
    opens = []
    if log.exists():
        for line in log.read_text(errors="replace").splitlines():
            if not line.startswith("#"):
                parts = line.split("\t")
                opens.append((parts[0], parts[1] if len(parts) > 1 else ""))
    return Run(argv, None if timed_out else rc, out_f.read_bytes(), err_f.read_bytes(),
               time.monotonic() - t0, usage.ru_maxrss / 1024.0, timed_out, opens)


#: Opens anywhere are fine under these (code, interpreter, pseudo-files).
_SYSTEM = ("/proc/", "/sys/", "/dev/null", "/dev/urandom", "/etc/localtime", "/usr/share/zoneinfo/",
           "/etc/ld.so", "/usr/lib/", "/usr/share/", "/usr/local/lib/")


def code_roots() -> list[str]:
    """Folders whose files any run may open: the repository, the interpreter and its packages."""
    import site
    roots = {ROOT, Path(sys.prefix), Path(sys.base_prefix), *map(Path, site.getsitepackages())}
    roots |= {Path(p) for p in sys.path if p and Path(p).is_dir() and Path(p).resolve() != Path("/")}
    return sorted({str(p.resolve()) for p in roots})


_CODE_ROOTS: list[str] = []


def outside_opens(run: Run, allowed: list[Path]) -> list[str]:
    """Files opened by ``run`` that are neither code nor under an ``allowed`` folder (symlinks
    resolved: a link out of the folder counts as outside)."""
    if not _CODE_ROOTS:
        _CODE_ROOTS.extend(code_roots())
    ok = [str(Path(a).resolve()) for a in allowed] + _CODE_ROOTS
    bad = []
    for path, mode in run.opens:
        real = os.path.realpath(path)
        if real.startswith(_SYSTEM) and not real.startswith(("/proc/self/environ",)):
            continue
        if any(real == r or real.startswith(r.rstrip("/") + "/") for r in ok):
            continue
        bad.append(f"{path} -> {real} ({mode})" if real != path else f"{path} ({mode})")
    return sorted(set(bad))


def _tree_digest(folder: Path) -> dict:
    """name -> sha256 of each regular file under ``folder`` (symlinks and special files by kind)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[rel] = "dir" if p.is_dir() else "special"
    return out


def _echoes_outside(run: Run, path: Path, ws: Workspace) -> bool:
    """The outside folder's path printed, where the case itself did not spell it out."""
    if str(ws.outside).encode() not in run.stdout + run.stderr:
        return False
    files = [p for p in path.parent.rglob("*") if p.is_file() and not p.is_symlink() and p.stat().st_size < 1 << 26]
    return not any(str(ws.outside).encode() in p.read_bytes() for p in files)


def _warned(run: Run) -> bool:
    err = run.stderr.decode("utf-8", "replace")
    out = run.stdout.decode("utf-8", "replace")
    if "rigmix: WARNING:" in err or "rigmix: warning:" in err.lower():
        return True
    for line in out.splitlines():
        if line.startswith("repaired defects:") and line.split(":", 1)[1].strip() not in ("", "none"):
            return True
    return False


_CONTROL = set(range(0, 32)) - {9, 10} | {127}


def _raw_controls(run: Run) -> bool:
    """Control characters (ESC, CR, NUL, ...) or unicode bidi overrides printed raw (CR allowed on
    stderr: the progress bar)."""
    if any(b in _CONTROL for b in run.stdout) or any(b in _CONTROL - {13} for b in run.stderr):
        return True
    text = (run.stdout + run.stderr).decode("utf-8", "replace")
    return any(ch in text for ch in "\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


_VALIDATED: dict[tuple, tuple] = {}


def validator_errors(path: Path, special: bool) -> int | None:
    """The Khronos validator's error count on ``path`` (None: not run or could not run)."""
    return validator_report(path, special)[0]


def validator_report(path: Path, special: bool) -> tuple[int | None, list]:
    """(error count or None, the distinct error codes) of the Khronos validator on ``path``;
    cached by the file's digest."""
    if special:
        return None, []
    key = (str(path), hashlib.sha256(path.read_bytes()).hexdigest())
    if key not in _VALIDATED:
        _VALIDATED[key] = _validate(path)
    return _VALIDATED[key]


def _validate(path: Path) -> tuple[int | None, list]:
    try:
        from rigmix.io.validator import validate_gltf, validator_available
    except ImportError:
        return None
    if not validator_available():
        return None, []
    try:
        report = validate_gltf(path, timeout=60)
    except Exception:  # the validator itself failed on a hostile file: unknown
        return None, []
    codes = sorted({m["code"] for m in report["issues"]["messages"] if m.get("severity") == 0})
    return int(report["issues"]["numErrors"]), codes


@dataclass
class Outcome:
    """What one command did to one case, judged."""

    case: str
    category: str
    command: str
    rc: int | None
    seconds: float
    peak_rss_mb: float
    clean_error: bool = False
    internal_error: bool = False
    traceback: bool = False
    hang: bool = False
    crash: bool = False
    silently_accepted: bool = False
    partial_files: list = field(default_factory=list)
    inputs_modified: list = field(default_factory=list)
    outside_opens: list = field(default_factory=list)
    leaked: bool = False
    raw_controls: bool = False
    invalid_output: bool = False
    unexpected: bool = False
    warned: bool = False
    validator_errors: int | None = None
    validator_codes: list = field(default_factory=list)
    stderr_tail: str = ""

    def failures(self) -> list[str]:
        """The acceptance failures of this run (empty: fine)."""
        f = []
        if self.traceback:
            f.append("traceback")
        if self.crash:
            f.append(f"crash (signal {-self.rc})")
        if self.hang:
            f.append("hang")
        if self.internal_error:
            f.append("internal error (exit 1)")
        if self.rc == 2 and not self.clean_error:
            f.append("exit 2 without one clean error line")
        if self.outside_opens:
            f.append(f"opened outside the asset folder: {self.outside_opens[:3]}")
        if self.leaked:
            f.append("sentinel bytes or outside paths in the output")
        if self.partial_files:
            f.append(f"partial files: {self.partial_files}")
        if self.inputs_modified:
            f.append(f"inputs modified: {self.inputs_modified}")
        if self.silently_accepted:
            f.append(f"silently accepted (validator: {self.validator_errors} errors {self.validator_codes[:4]}, "
                     "no warning)" if self.validator_errors else "silently accepted (exit 0, no warning)")
        if self.invalid_output:
            f.append("exit 0 with an output the validator rejects")
        if self.raw_controls:
            f.append("control characters printed raw")
        if self.peak_rss_mb > 2048:
            f.append(f"peak RSS {self.peak_rss_mb:.0f} MB")
        if self.unexpected:
            f.append("outcome differs from the expectation")
        return f


def _compose_config(folder: Path, path: Path, seed: str) -> Path:
    """A self-composition config using the hostile file ``path`` as body and donor."""
    joint = SEEDS[seed][1]
    cfg = {"name": "hostile", "characters": {"body": {"path": path.name}, "donor": {"path": path.name}},
           "actions": [{"op": "replace", "source": "donor", "source_joint": joint, "target": "body",
                        "target_joint": joint}]}
    cfg_path = folder.parent / f"{folder.name}.compose.toml"
    cfg_path.write_text(to_toml(cfg).replace(f'"{path.name}"', json.dumps(str(path))))
    return cfg_path


def seed_of(case: Case) -> str:
    """The seed character a file case was built from (by its id)."""
    return next((s for s in SEEDS if f"-{s}-" in f"-{case.id}-"), "RiggedFigure")


def execute(case: Case, ws: Workspace, command: str = "inspect", *, timeout: float = TIMEOUT,
            validate: bool = True) -> Outcome:
    """Build ``case`` and run one command on it: ``inspect`` (file cases), ``convert`` (to GLB),
    ``compose`` (a self-composition of a file case; a config case's own command)."""
    path = ws.materialize(case)
    folder = path.parent
    out = ws.out / f"{case.id}.{command}"
    if out.exists():
        _rmtree(out)
    out.mkdir(parents=True)
    allowed = [folder, out]
    if path.is_file():  # the named file itself, wherever a link leads: trusted like the command line
        allowed.append(path.resolve())
    config_path = None
    if case.kind == "config":
        config_path = path
        args = [a.format(config=path, out=out, case=folder) for a in case.argv]
        allowed.append(ASSETS)
    elif command == "inspect":
        args = ["inspect", path]
    elif command == "convert":
        args = ["convert", path, out / "converted.glb"]
    elif command == "compose":
        config_path = _compose_config(folder, path, seed_of(case))
        args = ["compose", config_path, "-o", out / "composed.glb", "--report", out / "report.json",
                "--no-feature-field"]
        allowed.append(config_path)
    else:
        raise ValueError(command)
    before = _tree_digest(folder)
    before_outside = _tree_digest(ws.outside)
    run = run_rigmix(args, ws, timeout=timeout, name=f"{case.id}.{command}")
    err = run.stderr.decode("utf-8", "replace")
    o = Outcome(case.id, case.category, command, run.rc, round(run.seconds, 2), round(run.peak_rss_mb, 1))
    o.stderr_tail = err.strip()[-400:]
    o.hang = run.timed_out
    o.crash = run.rc is not None and run.rc < 0
    o.traceback = "Traceback" in err
    o.internal_error = run.rc == 1
    error_lines = [ln for ln in err.splitlines() if ln.startswith("rigmix: error:")]
    o.clean_error = run.rc == 2 and len(error_lines) == 1 and not o.traceback and len(error_lines[0]) < 2000
    o.warned = _warned(run)
    o.outside_opens = outside_opens(run, allowed)
    outputs = list(out.rglob("*"))
    blobs = [run.stdout, run.stderr] + [p.read_bytes() for p in outputs if p.is_file() and not p.is_symlink()]
    o.leaked = any(ws.leaked(b) for b in blobs) or _echoes_outside(run, path, ws)
    if run.rc != 0:
        o.partial_files = sorted(str(p.relative_to(out)) for p in outputs)
    after = _tree_digest(folder)
    o.inputs_modified = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    if _tree_digest(ws.outside) != before_outside:
        o.inputs_modified.append("outside sentinels")
    o.raw_controls = _raw_controls(run)
    if run.rc == 0 and validate:
        if case.kind == "file" and command == "inspect" and not o.warned:
            o.validator_errors, o.validator_codes = validator_report(path, case.special)
            unknown_but_refusable = o.validator_errors is None and case.expect == "refuse"
            o.silently_accepted = bool(o.validator_errors) or unknown_but_refusable
        elif case.kind == "config" and not o.warned and case.expect == "refuse":
            o.silently_accepted = True
        for p in outputs:
            if p.suffix in (".glb", ".gltf") and p.is_file():
                n = validator_errors(p, False)
                o.invalid_output = o.invalid_output or bool(n)
    if command != "inspect" and case.kind == "file":
        pass  # the expectation is judged on inspect; compose and convert of files that read
    elif run.rc == 0 and case.expect == "refuse":
        o.unexpected = True
    elif run.rc == 0 and case.expect == "refuse-or-repair" and not o.warned:
        o.unexpected = True
    return o


#: Categories that the property tests (tests/test_fuzz.py) and tests/test_bad_inputs.py already cover
#: well in-process: one case each in the slice.
_COVERED = {"truncation", "header", "json-flip", "bin-flip", "json-edit", "config-toml", "config-type",
            "config-unknown-key"}


def slice_cases(cases=None, per_category: int = 2) -> list[Case]:
    """The fast deterministic slice (about 40 cases): the first ``per_category`` cases of each
    category (one of those in ``_COVERED``)."""
    cases = all_cases() if cases is None else cases
    seen: dict[str, int] = {}
    out = []
    for c in cases:
        if seen.get(c.category, 0) < (1 if c.category in _COVERED else per_category):
            seen[c.category] = seen.get(c.category, 0) + 1
            out.append(c)
    return out
