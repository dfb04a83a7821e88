"""The Blender round trip: a written glTF imported by Blender deforms as rigmix skins it.

Blender's glTF importer is the strictest consumer of a skeleton: bones cannot hold a rest scale,
so it bakes joint scales into the mesh, and a skeleton that mixes world scales (1 and 100 after
a cross-rig graft) imports with vertices blended across the two scale groups thrown far away.
:func:`blender_roundtrip` imports a file in Blender (``blender -b``, the Debian package;
:mod:`rigmix.io.blender_script` runs inside it), evaluates the deformed skinned meshes at rest
and at sampled frames of every clip, and compares them with rigmix's own linear blend skinning
of the same file read back (:func:`rigmix.io.load_character`).

Vertex correspondence: Blender's importer keeps, per primitive, the vertices its indices use in
ascending order and concatenates the primitives of a mesh (no merging: its ``merge_vertices``
option is off by default); the same order is built here from the file's index accessors.

Blender needs a plain system ``PATH`` (a pyenv shim first on the ``PATH`` breaks its Python):
it runs with ``PATH`` set to the folder of the ``blender`` executable and ``/usr/bin:/bin``.
``RIGMIX_BLENDER`` names another executable.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import RigmixError

__all__ = ["BlenderUnavailable", "RoundTrip", "blender_executable", "blender_available", "blender_roundtrip",
           "sample_times"]

SCRIPT = Path(__file__).with_name("blender_script.py")
#: Where Debian's ``blender`` lives, searched after ``RIGMIX_BLENDER`` and the ``PATH``.
SYSTEM_PATH = "/usr/bin:/bin"


class BlenderUnavailable(RigmixError):
    """No ``blender`` executable (Debian: ``apt-get install --no-install-recommends blender``)."""


@dataclass(frozen=True)
class RoundTrip:
    """Blender's deformed meshes against rigmix's skinning of one file.

    Attributes
    ----------
    error : float
        Largest vertex distance over the rest pose and every sampled frame, divided by the
        bounding-box diagonal of the rest mesh.
    rest_error : float
        The same at rest only.
    clip_errors : dict of str -> float
        Per clip, over its sampled frames.
    frames : int
        Frames compared (rest included).
    vertices : int
    """

    error: float
    rest_error: float
    clip_errors: dict
    frames: int
    vertices: int


def blender_executable() -> str | None:
    """Path of the ``blender`` executable, or None."""
    env = os.environ.get("RIGMIX_BLENDER")
    if env:
        return env if Path(env).is_file() else None
    return shutil.which("blender") or shutil.which("blender", path=SYSTEM_PATH)


def blender_available() -> bool:
    """Whether :func:`blender_roundtrip` can run."""
    return blender_executable() is not None


def sample_times(clip, frames: int | None, fps: float = 30.0) -> np.ndarray:
    """Times at which a clip is compared: its keys at ``fps`` (:func:`rigmix.animation.clip_times`),
    at most ``frames`` of them evenly spread, first and last included (all when None)."""
    from ..animation import clip_times

    t = clip_times(clip, fps)
    if frames is None or len(t) <= frames:
        return t
    return t[np.unique(np.round(np.linspace(0, len(t) - 1, max(frames, 2))).astype(np.int64))]


def _skinned_nodes(doc):
    """``(node index, name, [(rigmix mesh index, used vertex indices)])`` of every mesh node with
    a skin, in the reader's order (:func:`rigmix.io.gltf_read.read_gltf`: nodes, then primitives)."""
    out, k = [], 0
    for i, node in enumerate(doc.items("nodes")):
        if "mesh" not in node:
            continue
        prims = doc.get("meshes", node["mesh"], f"nodes[{i}]").get("primitives", [])
        parts = []
        for prim in prims:
            attrs = prim.get("attributes", {})
            if "skin" not in node or "JOINTS_0" not in attrs:
                continue
            n = doc.get("accessors", attrs["POSITION"], "POSITION")["count"]
            used = (np.unique(np.asarray(doc.accessor(prim["indices"], "indices")).ravel())
                    if "indices" in prim else np.arange(n))
            parts.append((k, used.astype(np.int64)))
            k += 1
        if parts:
            out.append((i, node.get("name"), parts))
    return out


def _run_blender(path: Path, request: dict, timeout: float) -> dict:
    exe = blender_executable()
    if exe is None:
        raise BlenderUnavailable("blender_roundtrip: no blender executable; install Debian's blender "
                                 "(apt-get install --no-install-recommends blender) or set RIGMIX_BLENDER")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env["PATH"] = f"{Path(exe).parent}:{SYSTEM_PATH}"
    with tempfile.TemporaryDirectory(prefix="rigmix-blender-") as tmp:
        req, out = Path(tmp) / "request.json", Path(tmp) / "out.npz"
        req.write_text(json.dumps(request))
        cmd = [exe, "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(SCRIPT), "--",
               str(path), str(req), str(out)]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=tmp)
        except subprocess.TimeoutExpired:
            raise RigmixError(f"blender_roundtrip: {path.name}: Blender ran longer than {timeout:g} s") from None
        if res.returncode != 0 or not out.is_file():
            tail = (res.stdout + res.stderr)[-3000:]
            raise RigmixError(f"blender_roundtrip: {path.name}: Blender exited {res.returncode}: {tail}")
        with np.load(out) as z:
            return {k: z[k] for k in z.files}


def blender_roundtrip(path, *, frames: int | None = 12, fps: float = 30.0, timeout: float = 600.0) -> RoundTrip:
    """Import ``path`` in Blender and compare its deformed meshes with rigmix's skinning.

    Parameters
    ----------
    path : str or Path
        A ``.glb`` or ``.gltf`` with a skin.
    frames : int or None
        Frames compared per clip (:func:`sample_times`; None: every key at ``fps``).
    fps : float
    timeout : float
        Seconds Blender may run.

    Returns
    -------
    RoundTrip

    Raises
    ------
    BlenderUnavailable
        No Blender.
    RigmixError
        Blender failed, or its meshes do not have the file's vertex counts.
    """
    from ..animation import sample_clip
    from ..geometry import bounding_box_diagonal
    from ..skinning import skin_character
    from . import load_character
    from .accessors import load_document

    path = Path(path)
    character = load_character(path)
    nodes = _skinned_nodes(load_document(path))
    if not nodes:
        raise RigmixError(f"blender_roundtrip: {path.name} has no skinned mesh")
    sk = character.skeleton
    times = [sample_times(c, frames, fps) for c in character.clips]
    request = {"nodes": [i for i, _, _ in nodes],
               "animations": [{"index": i, "times": t.tolist()} for i, t in enumerate(times)]}
    got = _run_blender(path, request, timeout)

    def ours(T, R, S):
        """rigmix's skinned positions ``(..., n, 3)`` of each requested node, in Blender's order."""
        V = skin_character(character, T, R, S)
        return [np.concatenate([V[m][..., used, :] for m, used in parts], axis=-2) for _, _, parts in nodes]

    rest = ours(sk.translations, sk.rotations, sk.scales)
    diag = bounding_box_diagonal(np.concatenate(rest)) or 1.0
    for k, (_, name, _) in enumerate(nodes):
        if got[f"rest/{k}"].shape != rest[k].shape:
            raise RigmixError(f"blender_roundtrip: {path.name}: Blender's mesh {name!r} has "
                              f"{len(got[f'rest/{k}'])} vertices, the file {len(rest[k])}")
    clip_errors = {}
    for i, (clip, t) in enumerate(zip(character.clips, times)):
        posed = ours(*sample_clip(sk, clip, t))
        clip_errors[clip.name] = max(float(np.linalg.norm(got[f"anim{i}/{k}"] - posed[k], axis=-1).max())
                                     for k in range(len(nodes))) / diag
    rest_error = max(float(np.linalg.norm(got[f"rest/{k}"] - rest[k], axis=-1).max())
                     for k in range(len(nodes))) / diag
    return RoundTrip(error=max([rest_error, *clip_errors.values()]), rest_error=rest_error, clip_errors=clip_errors,
                     frames=1 + sum(len(t) for t in times), vertices=sum(len(r) for r in rest))
