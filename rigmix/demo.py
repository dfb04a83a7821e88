"""`make demo`: the main job on the built-in example characters (no third-party assets).

``python -m rigmix.demo --out DIR``

1. builds the procedural example characters (:mod:`rigmix.examples`),
2. writes each as GLB to ``DIR`` (:func:`rigmix.io.gltf.write_gltf`),
3. reads each file back and prints its ``rigmix inspect`` summary (:mod:`rigmix.describe`),
4. composes the built-in centaur and writes its GLB, USD and JSON report as ``rigmix compose``
   does (:func:`compose_examples`, through :func:`rigmix.export.write_outputs`),
5. renders a contact sheet of the centaur's first clip (``centaur.sheet.png``, as
   ``rigmix render --sheet`` does), the first thing to look at,
6. lists what was written.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["main", "write_examples", "compose_examples", "render_sheet"]


def write_examples(out: Path) -> list[Path]:
    """Build the example characters and write them as GLB files to ``out``.

    Returns
    -------
    list of Path
        The files written, in order (humanoid, quadruped).
    """
    from . import examples
    from .io.gltf import write_gltf

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for build in (examples.humanoid, examples.quadruped):
        character = build()
        path = out / f"{character.name}.glb"
        write_gltf(character, path)
        written.append(path)
    return written


def compose_examples(inputs: list[Path], out: Path) -> list[Path]:
    """Compose the built-in centaur (``examples/centaur.toml``: the humanoid's torso, arms and
    head on the quadruped's body) and write it as ``rigmix compose`` does.

    Writes ``centaur.glb``, ``centaur.usda`` and ``centaur.report.json`` to ``out`` (all or
    none) and prints ``rigmix compose``'s summary line. The config names the built-in
    characters, so ``inputs`` (the files written before) are not read again.

    Returns
    -------
    list of Path
        The character files written (GLB, USD).

    Raises
    ------
    rigmix.errors.RigmixError
        The composition failed (nothing is written then).
    """
    from .describe import format_composition
    from .export import write_outputs
    from .pipeline import compose

    config = Path(__file__).resolve().parent.parent / "examples" / "centaur.toml"
    glb, usd, report = out / "centaur.glb", out / "centaur.usda", out / "centaur.report.json"
    composition = compose(config)
    write_outputs(composition, glb=glb, usd=usd, report=report, report_extra={"output": str(glb)})
    print(format_composition(composition, glb))
    print(f"demo: composition report {report}")
    return [glb, usd]


def render_sheet(path: Path, out: Path, frames: int = 12) -> Path:
    """Render a contact sheet of the first clip of the character file ``path`` to ``out``
    (``frames`` evenly spaced frames, as ``rigmix render --sheet``); returns ``out``."""
    from .io import load_character
    from .preview.render import render_clip

    character = load_character(path)
    duration = character.clips[0].duration if character.clips else 0.0
    # only the sheet's frames are needed: sample the clip at about twice their rate
    render_clip(character, sheet=out, fps=max(1.0, 2 * frames / max(duration, 1e-3)), sheet_frames=frames)
    return out


def main(argv=None) -> int:
    """Run the demo; returns the exit status."""
    from .describe import describe, format_description
    from .errors import RigmixError
    from .io import load_character

    parser = argparse.ArgumentParser(prog="python -m rigmix.demo",
                                     description="Build, write and inspect the built-in example characters.")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    args = parser.parse_args(argv)

    try:
        t0 = time.perf_counter()
        written = write_examples(args.out)
        print(f"demo: built and wrote {len(written)} example characters in {time.perf_counter() - t0:.1f} s\n")
        for path in written:
            print(format_description(describe(load_character(path), path)))
            print()
        composed = compose_examples(written, args.out)
        for path in composed:
            print(format_description(describe(load_character(path), path)))
            print()
        sheet = render_sheet(composed[0], args.out / "centaur.sheet.png")
        print(f"demo: contact sheet {sheet}")
    except RigmixError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2

    print("demo: wrote")
    for path in written + composed + [sheet]:
        print(f"  {path}  ({path.stat().st_size:,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
