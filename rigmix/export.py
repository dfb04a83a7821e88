"""Export: the files of a composition, written all or none.

:func:`write_outputs` is the one writer behind ``rigmix compose`` and ``rigmix batch``: the
composed character as glTF (``.glb`` or ``.gltf``) and as USD (with its ``textures/``), the JSON
report, and the blended signed distance fields (``.vdb`` with OpenVDB, else ``.npz``). Between the
files and the report it evaluates the hard gates (:func:`rigmix.gates.evaluate_gates`) on the
glTF file as written: the report's ``gates``, and the writer's result for ``--strict``. The
report's ``timings`` gain ``write`` (seconds writing the files before the gates) and ``gates``.

Every output is first written into a temporary folder beside the first target; only when all
of them are written is each one renamed into place through
:func:`rigmix.safety.atomic_output`. A failure while writing (an unwritable folder, a value
the JSON encoder refuses, an exception in a writer) leaves every target as it was and no
temporary file behind; a failure while renaming removes the outputs this call already put in
place, so a run never leaves a partial set of files. A signal turned into an exception
(:func:`rigmix.safety.signals_raise`) takes the same way out.

No output may be one of the composition's inputs (:func:`config_inputs`: the config, the
character files and the files a ``.gltf`` refers to) or another output: :func:`check_targets`
refuses it before anything is written (the command line calls it before composing, and
:func:`write_outputs` again on every file it is about to put in place). An ``OSError`` while
writing (a full disk, no permission) becomes an :class:`rigmix.errors.InputError` naming the
output and the fix.

:func:`json_default` is the one JSON encoder of rigmix's reports and manifests.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import NamedTuple
from urllib.parse import unquote

from .errors import InputError
from .safety import atomic_output, check_outputs, write_error_hint

__all__ = ["ExportResult", "write_outputs", "report_json", "json_default", "config_inputs", "check_targets"]

logger = logging.getLogger(__name__)


def json_default(obj):
    """JSON value of what :func:`json.dumps` does not encode itself (its ``default=`` hook).

    numpy scalars and arrays (anything with ``tolist``) become numbers and nested lists, paths
    strings, sets and frozensets lists.

    Raises
    ------
    TypeError
        Any other object (as :func:`json.dumps` expects of its hook).
    """
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, (set, frozenset)):
        return list(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def report_json(report: dict, *, sort_keys: bool = False) -> str:
    """The text of a JSON report: indented by 2, ending in a newline.

    Parameters
    ----------
    report : dict
        JSON-ready values, plus what :func:`json_default` converts.
    sort_keys : bool
        Keys sorted at every level (``rigmix batch``) rather than in insertion order
        (``rigmix compose``, whose report reads in stage order).
    """
    return json.dumps(report, indent=2, sort_keys=sort_keys, default=json_default) + "\n"


@dataclass(frozen=True)
class ExportResult:
    """What :func:`write_outputs` wrote.

    Attributes
    ----------
    files : tuple of Path
        Every file put in place, in the order written: the glTF file, the USD file and its
        textures, the fields, the report.
    fields : tuple of Path
        The field files among them; empty when no junction field was computed (every junction
        copied from faces the inputs share) or none was asked for.
    gates : tuple of dict
        The hard gates (:func:`rigmix.gates.evaluate_gates`), as in the report.
    """

    files: tuple = ()
    fields: tuple = ()
    gates: tuple = ()


def write_outputs(composition, *, glb=None, usd=None, report=None, fields_dir=None, report_extra=None,
                  sort_keys: bool = False) -> ExportResult:
    """Write a composition's files, all or none (see the module docstring).

    Parameters
    ----------
    composition : rigmix.pipeline.Composition
        A full composition: ``character`` is set (and ``surface.fields`` holds the blended
        fields when ``fields_dir`` is given, i.e. the fusion ran with ``keep_fields``).
    glb : str or Path, optional
        The character as glTF; ``.glb`` or ``.gltf`` (embedded buffers).
    usd : str or Path, optional
        The character as USD (``.usda``, ``.usdc``, ``.usd`` or ``.usdz``); textures go to
        ``textures/`` beside it.
    report : str or Path, optional
        ``composition.report`` as JSON (:func:`report_json`).
    fields_dir : str or Path, optional
        Folder (created if missing, even when no field was computed) receiving the blended
        fields, one file per junction.
    report_extra : dict, optional
        Entries appended to the written report (``composition.report`` is not modified).
    sort_keys : bool
        Sort the report's keys (see :func:`report_json`).

    Returns
    -------
    ExportResult

    Raises
    ------
    rigmix.errors.InputError
        A target that cannot be written (a missing or read-only folder, a folder in the way) or
        an unknown suffix.
    TypeError
        A report value that is not JSON serializable.
    """
    started = time.perf_counter()
    config = getattr(composition, "config", None)
    inputs = config_inputs(config) if config is not None else []
    check_targets(inputs, glb=glb, usd=usd, report=report, fields_dir=fields_dir, stage="export")
    targets = [Path(p) for p in (glb, usd, report) if p is not None]
    staging = next((p.parent for p in targets), None)
    with _writing(staging, "a temporary folder in"):
        tmp_dir = tempfile.TemporaryDirectory(dir=staging, prefix=".rigmix-export-")
    with tmp_dir as tmp:
        staged, gates = _stage(composition, Path(tmp), glb=glb, usd=usd, report=report, fields_dir=fields_dir,
                               report_extra=report_extra, sort_keys=sort_keys, started=started)
        # USD textures and field files are only known now: none may land on an input either
        check_outputs([("the output", s.dest) for s in staged], inputs, stage="export")
        files = _commit(staged, fields_dir)
    return ExportResult(files=files, fields=tuple(s.dest for s in staged if s.is_field), gates=tuple(gates))


def config_inputs(config) -> list:
    """The files a composition reads, as ``(what, path)`` for :func:`rigmix.safety.check_outputs`.

    Parameters
    ----------
    config : rigmix.config.Config

    Returns
    -------
    list of (str, Path)
        The config file (when it was read from one), each character file (built-in characters
        have none) and, for a ``.gltf``, the buffer and image files its JSON names (best
        effort: a file that cannot be read here is reported by the loader).
    """
    out = []
    source = Path(config.source)
    if source.is_file():
        out.append(("the config", source))
    for cid in config.characters:
        try:
            path = config.character_path(cid)
        except InputError:
            continue  # reported when the characters are loaded
        if not isinstance(path, Path):
            continue
        what = f"the input character '{cid}'"
        out.append((what, path))
        if path.suffix.lower() == ".gltf":
            out += [(f"a file of {what}", f) for f in _gltf_resources(path)]
    return out


def _gltf_resources(path: Path) -> list:
    """The external buffer and image files of a ``.gltf`` (relative URIs, percent-decoded)."""
    try:
        if path.stat().st_size > 64 << 20:  # not a JSON document rigmix would read anyway
            return []
        doc = json.loads(path.read_bytes())
        uris = [item.get("uri") for key in ("buffers", "images") for item in doc.get(key) or []
                if isinstance(item, dict)]
    except (OSError, ValueError, AttributeError, TypeError):
        return []
    return [path.parent / unquote(u) for u in uris
            if isinstance(u, str) and u and not u.startswith("data:") and "://" not in u]


def check_targets(inputs, *, glb=None, usd=None, report=None, fields_dir=None, stage="export") -> None:
    """Refuse outputs that are inputs or each other (see :func:`rigmix.safety.check_outputs`).

    Parameters
    ----------
    inputs : list of (str, path)
        From :func:`config_inputs`.
    glb, usd, report, fields_dir : str or Path, optional
        The outputs, as given to :func:`write_outputs`.
    stage : str
        Prefix of the message.
    """
    outputs = [("-o", glb), ("--usd", usd), ("--report", report), ("--dump-fields", fields_dir)]
    check_outputs([(w, p) for w, p in outputs if p is not None], inputs, stage=stage)


@contextmanager
def _writing(dest, what: str = ""):
    """Turn an ``OSError`` (or the safety helpers' ``InputError`` caused by one) into one line
    naming ``dest`` and the fix."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"export: cannot write {what + ' ' if what else ''}{dest}: "
                         f"{exc.strerror or type(exc).__name__} ({write_error_hint(exc)})") from None
    except InputError as exc:
        cause = exc.__cause__
        if not isinstance(cause, OSError):
            raise
        raise InputError(f"export: cannot write {what + ' ' if what else ''}{dest}: "
                         f"{cause.strerror or type(cause).__name__} ({write_error_hint(cause)})") from None


class _Staged(NamedTuple):
    """One output written under the temporary folder, and where it goes."""

    src: Path
    dest: Path
    is_field: bool = False


def _stage(composition, tmp: Path, *, glb, usd, report, fields_dir, report_extra, sort_keys, started) -> tuple:
    """Write every output under ``tmp``, evaluating the gates before the report; returns the
    :class:`_Staged` files in commit order and the gates."""
    from .gates import evaluate_gates

    staged = []
    written = None
    if glb is not None:
        from .io.gltf import write_gltf

        glb = Path(glb)
        written = tmp / ("character" + glb.suffix.lower())
        with _writing(glb):
            write_gltf(composition.character, written)
        staged.append(_Staged(written, glb))
    if usd is not None:
        from .io.usd import write_usd

        usd = Path(usd)
        usd_dir = tmp / "usd"
        with _writing(usd):
            usd_dir.mkdir()
            write_usd(composition.character, usd_dir / usd.name)
        staged += [_Staged(f, usd.parent / f.relative_to(usd_dir))
                   for f in sorted(usd_dir.rglob("*")) if f.is_file()]
    if fields_dir is not None:
        from .fusion import dump_fields

        fdir = tmp / "fields"
        with _writing(fields_dir):
            fdir.mkdir()
            dump_fields(fdir, composition.surface.fields)
        staged += [_Staged(f, Path(fields_dir) / f.name, is_field=True) for f in sorted(fdir.iterdir())]
    timings = dict(composition.report.get("timings", {}))
    t0 = time.perf_counter()
    timings["write"] = round(t0 - started, 4)
    gates = evaluate_gates(composition, written, seconds=float(timings.get("total", 0.0)) + t0 - started)
    timings["gates"] = round(time.perf_counter() - t0, 4)
    if report is not None:
        data = dict(composition.report)
        data.update(timings=timings, gates=gates)
        data.update(report_extra or {})
        path = tmp / "report.json"
        text = report_json(data, sort_keys=sort_keys).encode("utf-8")
        with _writing(report):
            path.write_bytes(text)
        staged.append(_Staged(path, Path(report)))
    return staged, gates


def _commit(staged: list, fields_dir) -> tuple:
    """Rename the staged files into place; on a failure, remove those already placed and re-raise."""
    placed = []
    try:
        if fields_dir is not None:
            with _writing(fields_dir, "the folder"):
                Path(fields_dir).mkdir(parents=True, exist_ok=True)
        for src, dest, _ in staged:
            with _writing(dest):
                dest.parent.mkdir(parents=True, exist_ok=True)
                with atomic_output(dest, suffix=dest.suffix) as out:
                    out.write_bytes(src.read_bytes())
            placed.append(dest)
    except BaseException:
        for dest in placed:
            dest.unlink(missing_ok=True)
        raise
    logger.debug("export: wrote %s", ", ".join(map(str, placed)))
    return tuple(placed)
