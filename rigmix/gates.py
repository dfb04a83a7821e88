"""Hard gates: what every composition must meet, checked on the files it writes.

:func:`evaluate_gates` is called by :func:`rigmix.export.write_outputs` (behind ``rigmix
compose`` and ``rigmix batch``) once the glTF file is written and before the report is: the
report's ``gates`` is its list, and ``rigmix compose --strict`` exits with status 3 when a gate
has failed (the outputs are written all the same).

A gate is a dict ``{"name", "value", "op", "bound", "pass"}``, plus ``"note"`` where something
needs saying: it passes when ``value op bound`` (``op`` is ``"<="`` or ``">="``). ``pass`` is
``null`` when the gate could not be evaluated (the Khronos validator is not installed, no glTF
file was written), which is not a failure. A gate that does not apply to the composition (the
identity gates of a composition of two characters) has ``value`` null, ``pass`` true and a note
saying why; every gate is always listed, in this order (:data:`GATE_NAMES`):

``wall_seconds`` <= :data:`MAX_SECONDS` (``[gates] max_seconds``)
    Seconds of the composition and of writing its outputs, up to the gates (the interpreter's
    start-up and the gates themselves not counted), on the machine that ran it.
``validator_errors`` <= 0
    Errors of the Khronos glTF-Validator (:func:`rigmix.io.validator.validate_gltf`) on the
    written file; the note names the first error codes.
``junction_boundary_edges``, ``open_seam_edges``, ``new_non_manifold_edges``, ``junction_self_intersections`` <= 0
    The fusion's counts (report ``mesh``): holes along the junction, open seam chains, edges
    shared by more than two faces that no input had, pairs of crossing faces at the junction
    that the inputs did not already have (:func:`crossing_gate`: a kept part of a modular
    character that, in its own input, passed through what the junction replaced, passes through
    the junction too; those pairs are ``junction_crossings_inherited``, named in the note).
``junction_min_angle_p05`` >= :data:`MIN_ANGLE_P05` degrees
    The 5th percentile of the smallest angle of the generated junction triangles; null (pass)
    when no junction triangle was generated (the junction faces were copied from the inputs).
``grafted_visible`` >= :data:`MIN_GRAFTED_VISIBLE`
    Report ``mesh.grafted_visible_min`` (:func:`rigmix.quality.grafted_visibility`): of each
    grafted part, the share of its output area outside the other inputs' kept surfaces, over the
    share of the same faces outside the rest of its own character (at most 1), the smallest over
    the parts; null (pass) without a grafted part (one character, or only bodies).
``junction_dihedral_ratio`` <= :data:`MAX_DIHEDRAL_RATIO`
    Report ``mesh.junction_dihedral_ratio`` (:func:`rigmix.quality.junction_dihedral`): the 95th
    percentile of the angle between neighbouring junction faces (those ``junction_min_angle_p05``
    measures) over the same figure on the inputs near the fused joints; null (pass) when there
    are none (the junction copied, or none) or nothing is fused between the fusion's inputs (a
    capped removal).
``junction_stretch_ratio`` <= :data:`MAX_STRETCH_RATIO`
    Report ``quality`` (:func:`rigmix.quality.junction_stretch_ratio`); null (pass) when no input
    has a clip, no clip was completed, or no joint is fused; null otherwise fails (not measured).
``clip_fidelity_max`` <= :data:`MAX_CLIP_FIDELITY`
    Report ``animation.fidelity_max``, the largest over the sources
    (:func:`rigmix.animation.fidelity.clip_fidelity`); null (pass) without a measured source.
``weights_min`` >= 0, ``weights_unnormalized_vertices`` <= 0, ``weights_max_influences`` <= :data:`MAX_INFLUENCES`
    On the ``WEIGHTS_n`` accessors as written (:func:`rigmix.io.accessors.load_document`, no
    repair): the smallest weight; the vertices whose weights, summed in float32 slot by slot,
    are farther from 1 than :data:`WEIGHT_SUM_TOLERANCE` per non-zero weight (the validator's
    rule); the most non-zero weights of a vertex.
``clips_missing`` <= 0, ``clips_non_increasing_times`` <= 0
    Distinct input clips (by content: a file listed under two ids gives its clips once) among
    those the completion was asked for (``[animation] clips``, else all) with no written
    animation completing them (named as the report's ``animation`` says) over the same time
    span (within half a frame at :data:`GATE_FPS`); written animations having a sampler whose
    key times (float32, as stored) are not strictly increasing.
``joint_world_scale_error`` <= :data:`MAX_WORLD_SCALE_ERROR`
    The written skeleton read back: the largest ``|s - 1|`` of the axis scales of every joint's
    world rest matrix (Blender bones hold no rest scale).
``identity_surface_error``, ``identity_skinned_error`` <= :data:`IDENTITY_TOLERANCE`
    Only for an identity composition (:func:`identity_mismatch`): the output, read back by
    :func:`rigmix.io.gltf.read_gltf`, against its input (:func:`rigmix.quality.identity_errors`):
    rest surfaces both ways, and
    every vertex at every frame (:data:`GATE_FPS`) of every clip, relative to the bounding-box
    diagonal. Otherwise value null, pass true, the note saying what makes it no identity.
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
from dataclasses import dataclass

import numpy as np

from .errors import RigmixError

__all__ = ["MAX_SECONDS", "MIN_ANGLE_P05", "MIN_GRAFTED_VISIBLE", "MAX_DIHEDRAL_RATIO", "MAX_STRETCH_RATIO",
           "MAX_INFLUENCES", "IDENTITY_TOLERANCE", "GATE_FPS", "WEIGHT_SUM_TOLERANCE", "VALIDATOR_TIMEOUT",
           "GATE_NAMES", "GateBounds", "Gate", "evaluate_gates", "wall_time_gate", "validator_gate", "mesh_gates",
           "crossing_gate", "failed_mesh_gates", "fails_less", "visibility_gate", "dihedral_gate", "stretch_gate",
           "weight_gates", "clip_gates", "identity_gates", "identity_mismatch", "clip_fingerprint",
           "character_fingerprint", "failed_gates", "failure_items", "failure_text", "gate_summary"]

logger = logging.getLogger(__name__)

#: Most wall seconds of one composition with its outputs (issue 24: on 2 CPU cores).
MAX_SECONDS = 60.0
#: Least 5th percentile of the junction triangles' smallest angle, degrees.
MIN_ANGLE_P05 = 20.0
#: Least share of each grafted part's output area outside the other inputs (issue 25).
MIN_GRAFTED_VISIBLE = 0.9
#: Most junction dihedral p95 over the sources' (1: the seam creases as the inputs' surface does there).
MAX_DIHEDRAL_RATIO = 1.5
#: Most junction stretch ratio (1: the seam deforms as the inputs deform near the same joints).
MAX_STRETCH_RATIO = 1.5
#: Most influences per vertex (glTF's one ``JOINTS_0``/``WEIGHTS_0`` set, what engines read).
MAX_INFLUENCES = 4
#: Most error of an identity composition, relative to the bounding-box diagonal.
IDENTITY_TOLERANCE = 0.005
#: Frames per second at which clips are compared, and half a frame the time-span tolerance.
GATE_FPS = 30.0
#: Allowed distance of a weight sum from 1, per non-zero weight, the sum accumulated in float32
#: (the Khronos validator's ``ACCESSOR_WEIGHTS_NON_NORMALIZED`` rule).
WEIGHT_SUM_TOLERANCE = 2e-7
#: Seconds the validator may run before its gate is left unevaluated.
VALIDATOR_TIMEOUT = 60.0
#: Scales this close to 1 are unit scales (identity compositions).
SCALE_TOLERANCE = 1e-9
#: Largest distance between a joint kept from a source in an output clip and in the source's own
#: clip, relative to the output's bounding-box diagonal (``animation.fidelity_max``).
MAX_CLIP_FIDELITY = 1e-4
#: Largest departure from 1 of a joint's world rest scale in the written skeleton: Blender bones
#: cannot hold a rest scale, and its importer bakes one into the mesh.
MAX_WORLD_SCALE_ERROR = 1e-6

#: Every gate, in report order.
GATE_NAMES = ("wall_seconds", "validator_errors", "junction_boundary_edges", "open_seam_edges",
              "new_non_manifold_edges", "junction_self_intersections", "junction_min_angle_p05", "grafted_visible",
              "junction_dihedral_ratio", "junction_stretch_ratio", "clip_fidelity_max", "weights_min",
              "weights_unnormalized_vertices", "weights_max_influences", "clips_missing",
              "clips_non_increasing_times", "joint_world_scale_error", "identity_surface_error",
              "identity_skinned_error")


@dataclass(frozen=True)
class GateBounds:
    """The gate bounds a config may set (its ``[gates]`` section); the others are fixed.

    Attributes
    ----------
    max_seconds : float
        Most wall seconds of the composition and of writing its outputs (``wall_seconds``);
        raise it on a slower machine than 2 cores of a current server.
    """

    max_seconds: float = MAX_SECONDS


@dataclass(frozen=True)
class Gate:
    """One gate: ``value op bound``.

    Attributes
    ----------
    name : str
    value : int, float or None
    op : {"<=", ">="}
    bound : float
    passed : bool or None
        None: not evaluated.
    note : str or None
    """

    name: str
    value: float | int | None
    op: str
    bound: float
    passed: bool | None
    note: str | None = None

    @classmethod
    def measure(cls, name: str, value, op: str, bound: float, note: str | None = None) -> "Gate":
        """The gate of a measured ``value`` (finite; a NaN fails)."""
        ok = value <= bound if op == "<=" else value >= bound
        return cls(name, value, op, bound, bool(ok), note)

    def as_dict(self) -> dict:
        """The report's form: ``{"name", "value", "op", "bound", "pass"}`` and ``"note"`` if any."""
        out = {"name": self.name, "value": self.value, "op": self.op, "bound": self.bound, "pass": self.passed}
        if self.note:
            out["note"] = self.note
        return out


def _not_evaluated(name: str, op: str, bound: float, note: str) -> Gate:
    return Gate(name, None, op, bound, None, note)


def _not_applicable(name: str, op: str, bound: float, note: str) -> Gate:
    return Gate(name, None, op, bound, True, note)


# --------------------------------------------------------------------------------------------
# the gate families


def wall_time_gate(seconds: float, max_seconds: float = MAX_SECONDS) -> Gate:
    """``wall_seconds``: the composition's wall time, seconds."""
    return Gate.measure("wall_seconds", round(float(seconds), 3), "<=", float(max_seconds))


def validator_gate(path) -> Gate:
    """``validator_errors``: Khronos glTF-Validator errors on the file at ``path``.

    Not evaluated (``pass`` None, the note says why) when Node or the validator package is
    missing, or the validator cannot run; ``path`` None: no file written.
    """
    from .io.validator import ValidatorUnavailable, validate_gltf

    name = "validator_errors"
    if path is None:
        return _not_evaluated(name, "<=", 0, "no glTF file written")
    try:
        report = validate_gltf(path, timeout=VALIDATOR_TIMEOUT)
    except ValidatorUnavailable as exc:
        return _not_evaluated(name, "<=", 0, f"validator unavailable: {exc}")
    except RigmixError as exc:
        logger.info("gates: %s", exc)
        return _not_evaluated(name, "<=", 0, str(exc))
    issues = report.get("issues", {})
    count = int(issues.get("numErrors", 0))
    codes = list(dict.fromkeys(m.get("code") for m in issues.get("messages", []) if m.get("severity") == 0))
    return Gate.measure(name, count, "<=", 0, ", ".join(map(str, codes[:3])) or None)


def mesh_gates(mesh: dict, *, min_angle: float = MIN_ANGLE_P05, min_visible: float = MIN_GRAFTED_VISIBLE,
               max_dihedral: float = MAX_DIHEDRAL_RATIO) -> list[Gate]:
    """The fusion's gates from the report's ``mesh``: the four counts, the junction angle, the
    grafted parts' visibility and the junction dihedral ratio."""
    gates = []
    for name in ("junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges"):
        value = mesh.get(name)
        gates.append(_not_evaluated(name, "<=", 0, "not in the report") if value is None
                     else Gate.measure(name, int(value), "<=", 0))
    gates.append(crossing_gate(mesh))
    angle = mesh.get("junction_min_angle_p05")
    name = "junction_min_angle_p05"
    if angle is None:
        gates.append(_not_applicable(name, ">=", min_angle, f"no junction triangle generated "
                                                            f"({mesh.get('copied_faces', 0)} junction faces copied)"))
    else:
        gates.append(Gate.measure(name, float(angle), ">=", min_angle))
    gates.append(visibility_gate(mesh, bound=min_visible))
    gates.append(dihedral_gate(mesh, bound=max_dihedral))
    return gates


def crossing_gate(mesh: dict) -> Gate:
    """``junction_self_intersections``: the crossing pairs at the junction that the composition
    made, those the inputs already had (``junction_crossings_inherited``: a kept part of a modular
    character through what the junction replaced) left out and named in the note."""
    name = "junction_self_intersections"
    total = mesh.get(name)
    if total is None:
        return _not_evaluated(name, "<=", 0, "not in the report")
    inherited = int(mesh.get("junction_crossings_inherited") or 0)
    note = (f"{total} crossing pairs, {inherited} of them inherited from overlapping input parts"
            if inherited else None)
    return Gate.measure(name, int(total) - inherited, "<=", 0, note)


def visibility_gate(mesh: dict, *, bound: float = MIN_GRAFTED_VISIBLE) -> Gate:
    """``grafted_visible``: the least visible grafted part's relative share
    (``mesh.grafted_visible_relative``), the note naming that part with its share in the output
    and in its own character; not applicable without a grafted part."""
    name = "grafted_visible"
    if "grafted_visible_relative" not in mesh:
        return _not_evaluated(name, ">=", bound, "not in the report")
    shares = mesh["grafted_visible_relative"] or {}
    if not shares:
        return _not_applicable(name, ">=", bound, "no grafted part")
    worst = min(shares, key=shares.get)
    own = (mesh.get("grafted_visible_source") or {}).get(worst)
    shown = (mesh.get("grafted_visible") or {}).get(worst)
    note = f"least visible part: {worst}"
    if shown is not None:
        note += f" ({shown:.3g} of its output area shows" + (f", {own:.3g} in its own character)" if own is not None
                                                             else ")")
    return Gate.measure(name, float(shares[worst]), ">=", bound, note)


def dihedral_gate(mesh: dict, *, bound: float = MAX_DIHEDRAL_RATIO) -> Gate:
    """``junction_dihedral_ratio`` from the report's ``mesh`` (see the module docstring for null)."""
    name = "junction_dihedral_ratio"
    if "junction_dihedral_ratio" not in mesh:
        return _not_evaluated(name, "<=", bound, "not in the report")
    ratio = mesh["junction_dihedral_ratio"]
    junction, source = mesh.get("junction_dihedral_p95"), mesh.get("source_dihedral_p95")
    if ratio is not None:
        return Gate.measure(name, float(ratio), "<=", bound, f"junction p95 {junction:.3g} degrees, "
                                                             f"sources' {source:.3g}")
    if junction is None:
        return _not_applicable(name, "<=", bound, f"no neighbouring junction faces that are not copied "
                                                  f"({mesh.get('copied_faces', 0)} junction faces copied)")
    return _not_applicable(name, "<=", bound, "no source band: no joint fused between the fusion's inputs")


def stretch_gate(composition, *, max_ratio: float = MAX_STRETCH_RATIO) -> Gate:
    """``junction_stretch_ratio`` from the report's ``quality`` (see the module docstring for null)."""
    name = "junction_stretch_ratio"
    ratio = composition.report.get("quality", {}).get(name)
    if ratio is not None:
        return Gate.measure(name, float(ratio), "<=", max_ratio)
    character = composition.character
    if not any(ch.clips for ch in composition.inputs.values()):
        return _not_applicable(name, "<=", max_ratio, "no input has a clip")
    if character is not None and not character.clips:
        return _not_applicable(name, "<=", max_ratio, "no clip completed")
    if not composition.plan.junction_pairs:
        return _not_applicable(name, "<=", max_ratio, "no joint fused")
    return Gate(name, None, "<=", max_ratio, False, "not measured: no junction band with a clip")


def weight_gates(document) -> list[Gate]:
    """``weights_min``, ``weights_unnormalized_vertices``, ``weights_max_influences`` of a written file.

    Parameters
    ----------
    document : rigmix.io.accessors.Document
        The file as written (:func:`rigmix.io.accessors.load_document`): the weights are read as
        stored (floats exactly, normalized integers mapped to [0, 1]), nothing repaired.
    """
    W = _written_weights(document)
    names = ("weights_min", "weights_unnormalized_vertices", "weights_max_influences")
    ops = ((">=", 0), ("<=", 0), ("<=", MAX_INFLUENCES))
    if W is None:
        return [_not_applicable(n, op, b, "no skinned mesh written") for n, (op, b) in zip(names, ops)]
    W32 = W.astype(np.float32)
    total = np.zeros(len(W32), np.float32)
    for k in range(W32.shape[1]):  # slot by slot in float32, as the validator adds them
        total = (total + np.maximum(W32[:, k], 0)).astype(np.float32)
    nonzero = np.count_nonzero(W32, axis=1)
    off = np.abs(total.astype(np.float64) - 1.0)
    bad = off > WEIGHT_SUM_TOLERANCE * np.maximum(nonzero, 1)
    worst = float(off.max()) if len(off) else 0.0
    return [Gate.measure(names[0], float(W.min()) if W.size else 0.0, *ops[0]),
            Gate.measure(names[1], int(bad.sum()), *ops[1], f"largest |sum - 1| {worst:.3g}" if bad.any() else None),
            Gate.measure(names[2], int(nonzero.max()) if len(nonzero) else 0, *ops[2])]


def _written_weights(document):
    """Every skinned vertex's written weights ``(n, 4 s)`` (``s`` weight sets; padded with 0), or
    None without a skinned primitive. A primitive sharing its accessors with another counts once."""
    rows, seen = [], set()
    for i, mesh in enumerate(document.items("meshes")):
        for p, prim in enumerate(mesh.get("primitives") or []):
            attrs = prim.get("attributes") or {}
            sets = sorted((k for k in attrs if k.startswith("WEIGHTS_") and k[8:].isdigit()), key=lambda k: int(k[8:]))
            key = tuple(attrs[k] for k in sets)
            if not key or key in seen:
                continue
            seen.add(key)
            parts = [document.accessor(a, f"meshes[{i}].primitives[{p}] {k}") for a, k in zip(key, sets)]
            n = max(len(x) for x in parts)
            rows.append(np.concatenate([np.pad(np.asarray(x, np.float64), ((0, n - len(x)), (0, 0))) for x in parts],
                                       axis=1))
    if not rows:
        return None
    width = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]))) for r in rows])


def clip_gates(document, composition) -> list[Gate]:
    """``clips_missing`` and ``clips_non_increasing_times`` (see the module docstring).

    Parameters
    ----------
    document : rigmix.io.accessors.Document
        The file as written: its animations' names and key times as stored.
    composition : rigmix.pipeline.Composition
        Its ``inputs``, ``config`` (``[animation] clips``) and ``report["animation"]`` (the
        source of each output clip).
    """
    spans, bad = _written_clips(document)
    missing = _missing_clips(spans, composition)
    return [Gate.measure("clips_missing", len(missing), "<=", 0, ", ".join(missing[:5]) or None),
            Gate.measure("clips_non_increasing_times", len(bad), "<=", 0, ", ".join(bad[:5]) or None)]


def _written_clips(document) -> tuple[dict, list]:
    """The written animations: ``{name: (start, end)}`` over their samplers' key times, and the
    names of those with a sampler whose key times do not strictly increase (unnamed ones are
    ``clip_<index>``, as :func:`rigmix.io.gltf.read_gltf` names them)."""
    spans, bad = {}, []
    for i, anim in enumerate(document.items("animations")):
        name = str(anim.get("name") or f"clip_{i}")
        lo, hi, increasing = math.inf, -math.inf, True
        for s, sampler in enumerate(anim.get("samplers") or []):
            times = document.accessor(sampler.get("input"), f"animations[{i}].samplers[{s}] input").ravel()
            lo, hi = min(lo, float(times.min())), max(hi, float(times.max()))
            increasing &= not np.any(np.diff(times) <= 0)
        if lo <= hi:
            spans[name] = (lo, hi)
        if not increasing:
            bad.append(name)
    return spans, bad


def _missing_clips(spans: dict, composition) -> list[str]:
    """``"<id>:<clip>"`` of each distinct asked-for input clip that no written clip (``spans``:
    name -> (start, end)) completes over the same time span."""
    from .animation.completion import selected_clips

    inputs = composition.inputs
    asked = selected_clips(inputs, composition.config.animation.to_params())
    animation = composition.report.get("animation", {})
    output_name = {tuple(src): name for src, name in zip(animation.get("sources", []), animation.get("clips", []))}
    groups: dict[str, list] = {}
    for cid, name in asked:
        groups.setdefault(clip_fingerprint(inputs[cid].skeleton, inputs[cid].clip(name)), []).append((cid, name))
    half_frame = 0.5 / GATE_FPS
    missing = []
    for keys in groups.values():
        source = inputs[keys[0][0]].clip(keys[0][1])
        found = [spans.get(output_name.get(k)) for k in keys]
        if not any(span is not None and abs(span[0] - source.start) <= half_frame
                   and abs(span[1] - source.end) <= half_frame for span in found):
            missing.append(f"{keys[0][0]}:{keys[0][1]}")
    return missing


def identity_gates(composition, written, *, tolerance: float = IDENTITY_TOLERANCE) -> list[Gate]:
    """``identity_surface_error`` and ``identity_skinned_error`` (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
    written : rigmix.character.Character
        The written file, read back by :func:`rigmix.io.gltf.read_gltf`; used only when the
        composition is an identity composition.
    """
    from .quality import identity_errors

    names = ("identity_surface_error", "identity_skinned_error")
    why = identity_mismatch(composition)
    if why is not None:
        return [_not_applicable(n, "<=", tolerance, f"not an identity composition: {why}") for n in names]
    inputs = composition.inputs
    original = next(iter(inputs.values()))
    animation = composition.report.get("animation", {})
    by_name = {c.name: c for c in written.clips}
    clips = [(by_name[name], inputs[cid].clip(clip)) for (cid, clip), name
             in zip(animation.get("sources", []), animation.get("clips", [])) if name in by_name]
    errors = identity_errors(original, written, clips, fps=GATE_FPS)
    out = []
    for name, key in zip(names, ("surface_error", "skinned_error")):
        value = errors[key]
        out.append(_not_evaluated(name, "<=", tolerance, "no skinned face to compare") if value is None
                   else Gate.measure(name, float(value), "<=", tolerance,
                                     f"{errors['frames']} frames" if key == "skinned_error" else None))
    return out


def identity_mismatch(composition) -> str | None:
    """What keeps a composition from being an identity composition; None when it is one.

    An identity composition has inputs of one and the same content (:func:`character_fingerprint`:
    one file listed under several ids), each at unit scale, unmirrored, unplaced, with no
    rest-pose rotation, and only ``replace`` actions whose source joint has the target joint's
    name: its output must be its input.
    """
    config = composition.config
    for i, action in enumerate(config.actions):
        if action.op != "replace":
            return f"action {i} is {action.op!r}"
        if action.source_joint != action.target_joint:
            return f"action {i} replaces {action.target_joint!r} by {action.source_joint!r}"
    characters = list(composition.inputs.values())
    first = characters[0]
    if any(ch is not first for ch in characters[1:]):
        digest = character_fingerprint(first)
        if any(ch is not first and character_fingerprint(ch) != digest for ch in characters[1:]):
            return "the characters differ"
    for cid, cc in config.characters.items():
        if cc.mirror is not False:
            return f"character {cid!r} is mirrored"
        if cc.placement is not None:
            return f"character {cid!r} is placed"
        if cc.rotations:
            return f"character {cid!r} has rest-pose rotations"
    for cid, scale in composition.plan.scales.items():
        if abs(float(scale) - 1.0) > SCALE_TOLERANCE:
            return f"character {cid!r} has scale {float(scale):.6g}"
    return None


def character_fingerprint(character) -> str:
    """SHA-256 of what a composition reads of a character: skeleton, skinned meshes and clips."""
    sk = character.skeleton
    h = hashlib.sha256()
    h.update("\0".join(sk.names).encode("utf-8"))
    for a in (sk.parents, sk.translations, sk.rotations, sk.scales, sk.inverse_binds, sk.anchor_worlds()):
        _update(h, a)
    for m in character.meshes:
        h.update(m.name.encode("utf-8"))
        for a in (m.positions, m.faces, m.joints, m.weights):
            _update(h, a)
    for c in character.clips:
        h.update(c.name.encode("utf-8"))
        h.update(clip_fingerprint(sk, c).encode("ascii"))
    return h.hexdigest()


def clip_fingerprint(skeleton, clip) -> str:
    """SHA-256 of a clip's content (not its name): each track's joint name, path, interpolation,
    times and values; equal for the same clip of one file loaded under two ids."""
    h = hashlib.sha256()
    for t in clip.tracks:
        h.update(f"{skeleton.names[t.joint]}\0{t.path}\0{t.interpolation}\0".encode("utf-8"))
        _update(h, t.times)
        _update(h, t.values)
    return h.hexdigest()


def _update(h, a) -> None:
    if a is None:
        h.update(b"-")
        return
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode("ascii"))
    h.update(a.tobytes())


# --------------------------------------------------------------------------------------------
# all of them


def evaluate_gates(composition, path, *, seconds: float) -> list[dict]:
    """Every gate of a composition whose glTF file has been written (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        A full composition (``character`` set, ``report`` with ``mesh``, ``quality`` and
        ``animation``); its config's ``[gates]`` section gives ``max_seconds``.
    path : str or Path or None
        The written ``.glb`` or ``.gltf`` (with its resources beside it); None: the gates that
        need the file are not evaluated.
    seconds : float
        Wall seconds of the composition and its writing so far.

    Returns
    -------
    list of dict
        One per :data:`GATE_NAMES`, in that order (:meth:`Gate.as_dict`).
    """
    bounds = composition.config.gates
    report = composition.report
    validation = _in_background(validator_gate, path)  # Node on another core while the rest is measured
    gates = [wall_time_gate(seconds, bounds.max_seconds)]
    gates += mesh_gates(report.get("mesh", {}))
    gates.append(stretch_gate(composition))
    gates.append(fidelity_gate(report.get("animation", {})))
    if path is None:
        gates += [_not_evaluated(name, ">=" if name == "weights_min" else "<=", _bound(name), "no glTF file written")
                  for name in GATE_NAMES[len(gates) + 1:]]
    else:
        gates += _file_gates(composition, path)
    gates.insert(1, validation())
    assert tuple(g.name for g in gates) == GATE_NAMES, [g.name for g in gates]
    return [g.as_dict() for g in gates]


def _in_background(fn, *args):
    """Start ``fn(*args)`` in a daemon thread; returns the function that waits for its result
    (re-raising its exception). A daemon: an interrupted composition never waits for it."""
    box = {}

    def run():
        try:
            box["value"] = fn(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
            box["error"] = exc

    thread = threading.Thread(target=run, name="rigmix-gates", daemon=True)
    thread.start()

    def wait():
        thread.join()
        if "error" in box:
            raise box["error"]
        return box["value"]

    return wait


def _file_gates(composition, path) -> list[Gate]:
    """The weight, clip and identity gates of the written file; all failed, with the reason,
    when rigmix cannot read that file back."""
    from .io.accessors import load_document

    try:
        document = load_document(path)
        from .io.gltf import read_gltf

        written = read_gltf(path)  # once, for the skeleton's scales and the identity comparison
        return (weight_gates(document) + clip_gates(document, composition) + [world_scale_gate(written)]
                + identity_gates(composition, written))
    except RigmixError as exc:
        start = GATE_NAMES.index("weights_min")
        return [Gate(name, None, ">=" if name == "weights_min" else "<=", _bound(name), False,
                     f"the written file cannot be read back: {exc}") for name in GATE_NAMES[start:]]


def _bound(name: str) -> float:
    """The fixed bound of a gate read from the written file."""
    return {"weights_max_influences": MAX_INFLUENCES, "identity_surface_error": IDENTITY_TOLERANCE,
            "identity_skinned_error": IDENTITY_TOLERANCE,
            "joint_world_scale_error": MAX_WORLD_SCALE_ERROR}.get(name, 0)


def fidelity_gate(animation: dict, *, bound: float = MAX_CLIP_FIDELITY) -> Gate:
    """``clip_fidelity_max``: the largest ``animation.fidelity_max`` over the sources (each the
    farthest a kept joint strays from its source clip, over the output's diagonal); not
    applicable without a measured source."""
    figures = {cid: v for cid, v in (animation.get("fidelity_max") or {}).items() if v is not None}
    if not figures:
        return _not_applicable("clip_fidelity_max", "<=", bound, "no source clip to compare with")
    worst = max(figures, key=figures.get)
    return Gate.measure("clip_fidelity_max", float(figures[worst]), "<=", bound, f"worst source: {worst}")


def world_scale_gate(written, *, bound: float = MAX_WORLD_SCALE_ERROR) -> Gate:
    """``joint_world_scale_error``: the largest ``|s - 1|`` over the axis scales ``s`` of every
    joint's world rest matrix of ``written`` (the written file read back, a Character)."""
    worlds = written.skeleton.rest_worlds()
    if not len(worlds):
        return _not_applicable("joint_world_scale_error", "<=", bound, "no joint")
    scales = np.linalg.norm(worlds[:, :3, :3], axis=1)
    return Gate.measure("joint_world_scale_error", float(np.abs(scales - 1.0).max()), "<=", bound)


def failed_mesh_gates(mesh: dict) -> dict:
    """The fusion's gates (:func:`mesh_gates`) that fail on the report's ``mesh``, by name."""
    return {g.name: g for g in mesh_gates(mesh) if g.passed is False}


def fails_less(alt: dict, first: dict) -> bool:
    """Whether the failed gates ``alt`` (name -> :class:`Gate`) are better than
    ``first``: some of them only, or the same ones, each as near its bound or nearer and one of
    them nearer."""
    if set(alt) != set(first):
        return set(alt) < set(first)

    def nearer(a, b):  # a's value on the passing side of b's
        return a.value < b.value if a.op == "<=" else a.value > b.value

    return all(not nearer(first[k], alt[k]) for k in alt) and any(nearer(alt[k], first[k]) for k in alt)


def failed_gates(gates: list[dict]) -> list[dict]:
    """The gates with ``pass`` false (not those left unevaluated)."""
    return [g for g in gates if g.get("pass") is False]


def _number(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, float) and math.isfinite(value) and value != int(value):
        return f"{value:.4g}"
    return str(int(value)) if isinstance(value, float) and math.isfinite(value) else str(value)


def failure_items(gates: list[dict]) -> list[str]:
    """``"<name> = <value> (bound <op> <bound>)"`` per failed gate."""
    return [f"{g['name']} = {_number(g['value'])} (bound {g['op']} {_number(g['bound'])})" for g in failed_gates(gates)]


def failure_text(gates: list[dict]) -> str | None:
    """The :func:`failure_items` joined by ``"; "``, None if no gate failed."""
    return "; ".join(failure_items(gates)) or None


def gate_summary(gates: list[dict]) -> str:
    """``"gates: N/M passed"``, with the failed gates' names and the count left unevaluated."""
    passed = sum(g.get("pass") is True for g in gates)
    failed = [g["name"] for g in failed_gates(gates)]
    unevaluated = sum(g.get("pass") is None for g in gates)
    text = f"gates: {passed}/{len(gates)} passed"
    if failed:
        text += f" (failed: {', '.join(failed)})"
    if unevaluated:
        text += f" ({unevaluated} not evaluated)"
    return text
