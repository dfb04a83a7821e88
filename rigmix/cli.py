"""The ``rigmix`` command line; the only place that configures logging.

Usage::

    rigmix [-v] [--debug] <command> ...
    rigmix inspect FILE [--json]
    rigmix convert IN OUT
    rigmix render FILE [--clip NAME] [--gif OUT.gif] [--mp4 OUT.mp4] [--sheet OUT.png]
    rigmix preview FILE.glb [--out DIR] [--port N] [--no-serve] [--force]
    rigmix map CONFIG [--json]
    rigmix schema

Adding a command
----------------
Write ``_add_<name>(parser)`` (declares the arguments of its ``argparse`` sub-parser) and
``_run_<name>(args) -> int`` (does the work, returns the exit status), then append one
:class:`Command` to :data:`COMMANDS`. Heavy imports go inside ``_run_<name>``, so that
``rigmix --help`` stays fast.

Errors
------
A :class:`rigmix.errors.RigmixError` (or an ``OSError`` such as a missing file) is printed as
one line ``rigmix: error: <message>`` on stderr, exit status 2, no traceback; any other
exception is reported the same way as an internal error, exit status 1. ``--debug`` re-raises
instead (full traceback). Error lines are cut at :data:`MAX_ERROR_CHARS` characters, and control
and bidirectional-override characters in them (from names and paths) are shown escaped
(:func:`rigmix.describe.printable`), as in every logged line.

``compose --strict`` exits with status 3 when a hard gate of the report failed
(:mod:`rigmix.gates`), after writing every output, with one line ``rigmix: gate failed: <name> =
<value> (bound <op> <bound>)[; ...]`` on stderr; ``batch --strict`` exits with 3 when every job
succeeded but some failed a gate (a failed job's status, 2 or 1, comes first).

Outputs that are inputs or each other (``compose -o IN.glb``, ``--report CONFIG.toml``, ``-o X
--report X``, a ``batch --out`` folder where an output would land on an input) are refused with
exit status 2 before anything is composed. ``batch`` exits 0 when every job succeeded (or was
done before), 2 when every failure is a bad input (a :class:`RigmixError`), 1 when any failure
is internal (a bug, or a worker process that died).

Signals: SIGTERM and SIGINT raise :class:`rigmix.safety.Interrupted` in the running command, so
temporary files and folders are removed and ``batch`` stops its workers; the exit status is then
``128 + signal`` (143 for SIGTERM, 130 for SIGINT). Library code never prints: it logs through
``logging.getLogger(__name__)``; warnings go to stderr, ``-v`` adds info, ``-vv`` debug.

The keys of ``rigmix inspect --json`` are those of :func:`rigmix.describe.describe`; the
outputs of ``compose`` and ``batch`` are written by :func:`rigmix.export.write_outputs`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from . import __version__
from .errors import RigmixError
from .safety import received_signal, signals_raise

__all__ = ["main", "build_parser", "Command", "COMMANDS", "MAX_ERROR_CHARS"]

logger = logging.getLogger(__name__)

#: Longest error line printed (an ellipsis marks the cut): a message quoting a huge value must
#: not flood the terminal.
MAX_ERROR_CHARS = 500
#: Longest warning (or error) line logged; info and debug lines are not cut.
MAX_LOG_CHARS = 2000


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """One sub-command: its name, one-line help, argument declaration and runner."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _add_inspect(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("--json", action="store_true", help="print a JSON object instead of text")


def _run_inspect(args) -> int:
    from .describe import describe, format_description
    from .io import load_character
    from .pipeline import check_input

    path = args.file
    try:
        character = load_character(path)
        check_input(character)  # what compose refuses in a file, inspect refuses with the same line
    except RigmixError as exc:
        if path.name not in str(exc):  # every message must name the file
            raise type(exc)(f"inspect: {path}: {exc}") from exc
        raise
    d = describe(character, path)
    print(json.dumps(d, indent=2) if args.json else format_description(d))
    return 0


def _add_map(parser):
    parser.add_argument("config", type=Path, help="a composition config (.toml)")
    parser.add_argument("--json", action="store_true",
                        help="print a JSON object: output_joints, mapping rows (character, input_joint, "
                             "output_joint, confidence) and the operations report (scales, fused pairs)")


def _run_map(args) -> int:
    from .pipeline import compose, mapping_table

    comp = compose(args.config, until="mapping")
    rows = mapping_table(comp)
    if args.json:
        print(json.dumps({"config": str(args.config), "output_joints": list(comp.skeleton.names),
                          "mapping": rows, "operations": comp.report["operations"]}, indent=2))
        return 0
    heads = ("character", "input joint", "output joint", "confidence")
    cells = [(r["character"], r["input_joint"], r["output_joint"] or "-", f"{r['confidence']:.3f}") for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(heads, widths)).rstrip()]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in cells]
    for cid, info in comp.report["operations"]["characters"].items():
        lines.append(f"# {cid}: scale {info['scale']:.6g} ({info['scale_method']})")
    print("\n".join(lines))
    return 0


def _add_schema(parser):
    pass


def _run_schema(args) -> int:
    from .config import config_schema

    print(json.dumps(config_schema(), indent=2))
    return 0


def _add_convert(parser):
    parser.add_argument("input", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("output", type=Path,
                        help="the file to write: .usda, .usdc, .usd (crate), .usdz, .glb or .gltf; USD keeps "
                             "every clip (an 'animation' variant set), materials and textures (textures/ beside it)")


def _run_convert(args) -> int:
    from .io.convert import convert

    character = convert(args.input, args.output)
    print(f"{args.output}: {character.skeleton.num_joints} joints, {len(character.meshes)} meshes, "
          f"{len(character.props)} props, {len(character.clips)} clips, {len(character.materials)} materials")
    return 0


def _add_render(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, .gltf, .usd, .usda, .usdc, .usdz)")
    parser.add_argument("--clip", help="the clip to render (default: the first; the rest pose if there is none)")
    parser.add_argument("--gif", type=Path, help="write an animated GIF")
    parser.add_argument("--mp4", type=Path, help="write an MP4 video (needs imageio-ffmpeg)")
    parser.add_argument("--sheet", type=Path, help="write a contact sheet PNG of frames over the clip")
    parser.add_argument("--size", type=int, nargs=2, default=(480, 480), metavar=("W", "H"), help="pixels")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    parser.add_argument("--azimuth", type=float, default=30.0, help="camera degrees around +Y from the front")
    parser.add_argument("--elevation", type=float, default=15.0, help="camera degrees above the horizon")
    parser.add_argument("--backend", choices=("auto", "gl", "pil"), default="auto",
                        help="gl: OpenGL on EGL (Mesa, CPU); pil: Pillow fallback; auto: gl if it works")
    parser.add_argument("--bones", action="store_true", help="draw the skeleton over the character")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_render(args) -> int:
    from tqdm import tqdm

    from .errors import InputError
    from .io import load_character
    from .preview.render import render_clip

    outputs = [p for p in (args.gif, args.mp4, args.sheet) if p is not None]
    if not outputs:
        raise InputError("render: nothing to write; give --gif OUT.gif, --mp4 OUT.mp4 or --sheet OUT.png")
    character = load_character(args.file)
    with tqdm(desc="render", unit="frame", disable=args.no_progress, file=sys.stderr, leave=False) as bar:
        def progress(done, total):
            bar.total = total
            bar.update(done - bar.n)

        frames = render_clip(character, args.clip, gif=args.gif, mp4=args.mp4, sheet=args.sheet, fps=args.fps,
                             width=args.size[0], height=args.size[1], azimuth=args.azimuth,
                             elevation=args.elevation, backend=args.backend, bones=args.bones,
                             progress=progress)
    print(f"{', '.join(map(str, outputs))}: {len(frames)} frames of {args.size[0]}x{args.size[1]}")
    return 0


def _add_preview(parser):
    parser.add_argument("file", type=Path, help="a character file (.glb, or a .gltf with embedded buffers)")
    parser.add_argument("--out", type=Path, help="the viewer folder (default: <name>_preview beside the file)")
    parser.add_argument("--port", type=int, help="port on 127.0.0.1, 1-65535 (default: a free one)")
    parser.add_argument("--no-serve", action="store_true", help="only write the viewer folder")
    parser.add_argument("--force", action="store_true",
                        help="write into an --out folder that holds other files (only the viewer's are served)")


def _run_preview(args) -> int:
    import threading

    from .errors import InputError
    from .preview.viewer import serve, write_viewer

    if args.port is not None and not 1 <= args.port <= 65535:
        raise InputError(f"preview: --port {args.port} is not a TCP port; give 1-65535, or leave it out for a free one")
    out = args.out or args.file.with_name(args.file.stem + "_preview")
    index = write_viewer(args.file, out, force=args.force)
    if args.no_serve:
        print(f"{index}: open it through a web server (ES modules do not load from file://)")
        return 0
    server, url = serve(out, port=args.port or 0)
    print(f"rigmix preview: {url} (serving {out}; Ctrl+C to stop)", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
    return 0


def _add_compose(parser):
    parser.add_argument("config", type=Path, help="a composition config (.toml)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the composed character (.glb or .gltf)")
    parser.add_argument("--report", type=Path, help="write the JSON report (timings, mesh, fields, weights, "
                                                    "quality, animation, scales, warnings)")
    parser.add_argument("--usd", type=Path, help="also write the character as USD (.usda, .usdc, .usd, .usdz)")
    parser.add_argument("--dump-fields", type=Path, metavar="DIR",
                        help="write the blended signed distance fields (.vdb with OpenVDB, else .npz) to DIR")
    parser.add_argument("--weights", choices=("nearest", "inpaint", "dfd"),
                        help="junction weight method (default: the config's [weights] method, else dfd)")
    field = parser.add_mutually_exclusive_group()
    field.add_argument("--feature-field", action="store_true",
                       help="dfd with the distilled DFD feature field of the fused surface judging the mirror "
                            "prior (a few seconds more; same as [weights] feature_field = true)")
    field.add_argument("--no-feature-field", action="store_true",
                       help="dfd without the feature field (the default; same as [weights] feature_field = false)")
    parser.add_argument("--strict", action="store_true",
                        help="exit with status 3 when a hard gate of the report fails (the outputs are still "
                             "written); one stderr line names the failed gates")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_compose(args) -> int:
    from tqdm import tqdm

    from .config import load_config
    from .describe import format_composition
    from .errors import InputError
    from .export import check_targets, config_inputs, write_outputs
    from .gates import failure_text
    from .pipeline import STAGE_NAMES, compose

    if args.output.suffix.lower() not in (".glb", ".gltf"):
        raise InputError(f"compose: output {args.output} must end in .glb or .gltf")
    if args.usd is not None and args.usd.suffix.lower() not in (".usda", ".usdc", ".usd", ".usdz"):
        raise InputError(f"compose: --usd {args.usd} must end in .usda, .usdc, .usd or .usdz")
    for p in (args.output, args.report, args.usd):
        if p is not None and not p.parent.is_dir():
            raise InputError(f"compose: the folder of {p} does not exist")
    outputs = dict(glb=args.output, usd=args.usd, report=args.report, fields_dir=args.dump_fields)
    check_targets([("the config", args.config)], stage="compose", **outputs)  # before reading it
    config = load_config(args.config)
    check_targets(config_inputs(config), stage="compose", **outputs)
    weights, fusion = {}, {}
    if args.weights:
        weights["method"] = args.weights
    if args.feature_field or args.no_feature_field:
        weights["feature_field"] = bool(args.feature_field)
    if args.dump_fields:
        fusion["keep_fields"] = True
    config = config.with_options(weights=weights, fusion=fusion)
    with tqdm(total=len(STAGE_NAMES), desc="compose", unit="stage", disable=args.no_progress, file=sys.stderr,
              leave=False) as bar:
        def progress(stage, done, total):  # stage: "fusion", or with its sub-step "fusion: junction 1 of 2"
            if isinstance(done, int) and (stage.split(":")[0] in STAGE_NAMES or stage == "done"):
                bar.total = total
                bar.set_postfix_str(stage)
                bar.update(done - bar.n)

        comp = compose(config, progress=progress)
    result = write_outputs(comp, glb=args.output, usd=args.usd, report=args.report, fields_dir=args.dump_fields,
                           report_extra={"output": str(args.output)})
    if args.dump_fields and not result.fields:
        print(f"rigmix compose: --dump-fields {args.dump_fields}: no junction field was computed (every "
              "junction was copied from faces the inputs share); nothing written", file=sys.stderr)
    print(format_composition(comp, args.output, gates=result.gates))
    failures = failure_text(list(result.gates))
    if args.strict and failures:
        _gate_failed(failures)
        return 3
    return 0


def _gate_failed(text: str) -> None:
    """The one stderr line of a failed gate (``--strict``)."""
    print("rigmix: " + _one_line("gate failed: " + text, MAX_ERROR_CHARS - len("rigmix: ")), file=sys.stderr)


def _add_batch(parser):
    parser.add_argument("configs", type=Path, nargs="+", metavar="CONFIG", help="composition configs (.toml)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder: <config name>.glb, <config name>.report.json, manifest.jsonl")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes (default: the CPU count; 0: in this process; with "
                             "--scheduler local-dask: Dask workers, default 2)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on a Dask cluster: a scheduler address (tcp://host:8786) or 'local-dask' "
                             "(needs rigmix[dask]; the output folder must be shared with the workers)")
    parser.add_argument("--strict", action="store_true",
                        help="exit with status 3 when every job succeeded but some failed a hard gate of its report "
                             "(one stderr line per such job)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_batch(args) -> int:
    from tqdm import tqdm

    from .batch import run_batch

    if args.workers is not None and args.workers < 0:
        from .errors import InputError

        raise InputError(f"batch: --workers must be 0 or more, got {args.workers}")
    with tqdm(total=len(args.configs), desc="batch", unit="config", disable=args.no_progress,
              file=sys.stderr) as bar:
        def progress(done, total, entry):
            bar.set_postfix_str(f"{entry['stem']} {'skipped' if entry.get('skipped') else entry['status']}")
            bar.update(done - bar.n)

        entries = run_batch(args.configs, args.out, workers=args.workers, scheduler=args.scheduler,
                            progress=progress)
    from .batch import exit_status
    from .describe import printable

    failed = [e for e in entries if e["status"] != "ok"]
    skipped = sum(bool(e.get("skipped")) for e in entries)
    gated = [e for e in entries if e["status"] == "ok" and e.get("gates_failed")]
    for e in failed:
        _error(f"{Path(e['config']).name}: {e['error']}")
    if args.strict:
        for e in gated:
            _gate_failed(f"{Path(e['config']).name}: {'; '.join(e['gates_failed'])}")
    print(f"{printable(args.out)}: {len(entries) - len(failed) - skipped} composed, {skipped} skipped "
          f"(done before), {len(failed)} failed, {len(gated)} with a failed gate; manifest "
          f"{printable(args.out / 'manifest.jsonl')}")
    return exit_status(entries, strict=args.strict)


#: The sub-commands, in the order ``rigmix --help`` lists them. Append here.
COMMANDS: list[Command] = [
    Command("inspect", "print a character's joints, meshes, clips, counts and repaired defects",
            _add_inspect, _run_inspect),
    Command("convert", "convert a character file: glTF/GLB <-> USD (.usda, .usdc, .usd, .usdz)",
            _add_convert, _run_convert),
    Command("render", "render a clip offscreen on the CPU to a GIF, an MP4 or a contact sheet PNG",
            _add_render, _run_render),
    Command("preview", "write a web viewer for a .glb (clips, timeline, skeleton) and serve it on 127.0.0.1",
            _add_preview, _run_preview),
    Command("map", "print the bone-to-bone mapping of a composition config (input joint -> output "
                   "joint, confidence)", _add_map, _run_map),
    Command("schema", "print the JSON schema of composition configs", _add_schema, _run_schema),
    Command("compose", "compose a new character from a config: GLB (and USD), JSON report", _add_compose,
            _run_compose),
    Command("batch", "compose many configs in parallel (process pool or Dask), resumable, with a JSONL manifest",
            _add_batch, _run_batch),
]


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The ``rigmix`` parser with one sub-parser per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="rigmix",
        description="Compose new rigged, skinned and animated characters from pieces of existing ones.",
    )
    parser.add_argument("--version", action="version", version=f"rigmix {__version__}")
    # the common options are accepted before or after the command name; in the sub-parsers
    # they default to SUPPRESS so that they never overwrite a value given before the command
    _add_common_options(parser, default=True)
    parser.set_defaults(command=None)
    common = argparse.ArgumentParser(add_help=False)
    _add_common_options(common, default=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for cmd in COMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help, parents=[common])
        cmd.add_arguments(p)
        p.set_defaults(run=cmd.run)
    return parser


def _add_common_options(parser, *, default: bool) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=0 if default else argparse.SUPPRESS,
                        help="log info (-v) or debug (-vv) messages on stderr")
    parser.add_argument("--debug", action="store_true", default=False if default else argparse.SUPPRESS,
                        help="show the full traceback of an error")


class _OneLine(logging.Formatter):
    def format(self, record):
        return _one_line(super().format(record), MAX_LOG_CHARS if record.levelno >= logging.WARNING else None)


def _one_line(text: str, limit: int | None) -> str:
    """``text`` on one line, control characters escaped, cut at ``limit`` characters."""
    from .describe import printable

    text = " ".join(str(text).split())
    if limit is not None and len(text) > limit:
        text = text[: limit - 1] + "\u2026"
    return printable(text)


@contextlib.contextmanager
def _cli_logging(verbosity: int):
    """Warnings (or info/debug with -v/-vv) of rigmix and dfd on stderr, one line each, for the
    duration of one command. The loggers' handlers, levels and propagation and the capture of
    Python warnings are put back afterwards: ``main()`` called in-process (tests, notebooks)
    must not leave the library's loggers detached from the root logger."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLine("rigmix: %(levelname)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in ("rigmix", "dfd")]
    saved = [(log, list(log.handlers), log.level, log.propagate) for log in loggers]
    warnings_captured = getattr(logging, "_warnings_showwarning", None) is not None
    for log in loggers:
        log.addHandler(handler)
        log.setLevel(level)
        log.propagate = False
    logging.captureWarnings(True)
    try:
        yield
    finally:
        for log, handlers, old_level, propagate in saved:
            log.handlers[:] = handlers
            log.setLevel(old_level)
            log.propagate = propagate
        logging.captureWarnings(warnings_captured)


def _error(message: str) -> None:
    print("rigmix: error: " + _one_line(message, MAX_ERROR_CHARS - len("rigmix: error: ")), file=sys.stderr)


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 user error, 1 internal error,
    3 a failed gate with ``--strict``, 128 + signal after SIGTERM or SIGINT)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    with _cli_logging(args.verbose), signals_raise():
        try:
            status = _run(args)
        except KeyboardInterrupt:  # a signal in the instant after the command returned
            status = 130
        signum = received_signal()
    # a signal caught by a command that then returned normally (preview) still ends as a signal
    return 128 + signum if signum is not None else status


def _run(args) -> int:
    try:
        return int(args.run(args) or 0)
    except RigmixError as exc:
        if args.debug:
            raise
        _error(str(exc))
        return 2
    except BrokenPipeError:  # e.g. `rigmix inspect X | head`: stop quietly
        sys.stdout = open(os.devnull, "w")
        return 0
    except OSError as exc:
        if args.debug:
            raise
        _error(f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc))
        return 2
    except KeyboardInterrupt:
        signum = received_signal()
        _error("interrupted" + (f" ({signal.Signals(signum).name})" if signum is not None else ""))
        return 128 + (signum or signal.SIGINT)
    except Exception as exc:  # a bug: still one line, the traceback with --debug
        if args.debug:
            raise
        _error(f"internal error ({type(exc).__name__}: {exc}); run again with --debug for the traceback")
        return 1


if __name__ == "__main__":
    sys.exit(main())
