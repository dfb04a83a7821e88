"""Export: the files of a composition, written all or none.

:func:`write_outputs` is the one writer behind ``rigmix compose`` and ``rigmix batch``: the
composed character as glTF (``.glb`` or ``.gltf``) and as USD (with its ``textures/``), the JSON
report, and the blended signed distance fields (``.vdb`` with OpenVDB, else ``.npz``).

Every output is first written into a temporary folder beside the first target; only when all
of them are written is each one renamed into place through
:func:`rigmix.safety.atomic_output`. A failure while writing (an unwritable folder, a value
the JSON encoder refuses, an exception in a writer) leaves every target as it was and no
temporary file behind; a failure while renaming removes the outputs this call already put in
place, so a run never leaves a partial set of files.

:func:`json_default` is the one JSON encoder of rigmix's reports and manifests.
"""

from __future__ import annotations

import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import NamedTuple

from .safety import atomic_output

__all__ = ["ExportResult", "write_outputs", "report_json", "json_default"]

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
    """

    files: tuple = ()
    fields: tuple = ()


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
    targets = [Path(p) for p in (glb, usd, report) if p is not None]
    staging = next((p.parent for p in targets), None)
    with tempfile.TemporaryDirectory(dir=staging, prefix=".rigmix-export-") as tmp:
        staged = _stage(composition, Path(tmp), glb=glb, usd=usd, report=report, fields_dir=fields_dir,
                        report_extra=report_extra, sort_keys=sort_keys)
        files = _commit(staged, fields_dir)
    return ExportResult(files=files, fields=tuple(s.dest for s in staged if s.is_field))


class _Staged(NamedTuple):
    """One output written under the temporary folder, and where it goes."""

    src: Path
    dest: Path
    is_field: bool = False


def _stage(composition, tmp: Path, *, glb, usd, report, fields_dir, report_extra, sort_keys) -> list:
    """Write every output under ``tmp``; returns the :class:`_Staged` files in commit order."""
    staged = []
    if glb is not None:
        from .io.gltf import write_gltf

        glb = Path(glb)
        path = tmp / ("character" + glb.suffix.lower())
        write_gltf(composition.character, path)
        staged.append(_Staged(path, glb))
    if usd is not None:
        from .io.usd import write_usd

        usd = Path(usd)
        usd_dir = tmp / "usd"
        usd_dir.mkdir()
        write_usd(composition.character, usd_dir / usd.name)
        staged += [_Staged(f, usd.parent / f.relative_to(usd_dir))
                   for f in sorted(usd_dir.rglob("*")) if f.is_file()]
    if fields_dir is not None:
        from .fusion import dump_fields

        fdir = tmp / "fields"
        fdir.mkdir()
        dump_fields(fdir, composition.surface.fields)
        staged += [_Staged(f, Path(fields_dir) / f.name, is_field=True) for f in sorted(fdir.iterdir())]
    if report is not None:
        data = dict(composition.report)
        data.update(report_extra or {})
        path = tmp / "report.json"
        path.write_bytes(report_json(data, sort_keys=sort_keys).encode("utf-8"))
        staged.append(_Staged(path, Path(report)))
    return staged


def _commit(staged: list, fields_dir) -> tuple:
    """Rename the staged files into place; on a failure, remove those already placed and re-raise."""
    placed = []
    try:
        if fields_dir is not None:
            Path(fields_dir).mkdir(parents=True, exist_ok=True)
        for src, dest, _ in staged:
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
