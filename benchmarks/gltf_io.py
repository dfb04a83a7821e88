"""glTF I/O speed: read and write time of every shared character, and the validator's verdict.

For each character in ``../shared/data/characters`` (or ``$RIGMIX_ASSETS``): the median of 5
``read_gltf`` and 5 ``write_gltf`` (GLB) calls, the time of ``pygltflib.GLTF2().load`` on the
same file for comparison (rigmix parses the JSON itself, see the report), and the Khronos
validator's error count on the input and on the written file. Writes
``benchmarks/results/gltf_io.json`` and ``gltf_io.md``.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from conftest import ASSETS, CHARACTERS  # noqa: E402

from benchmarks.common import median_seconds  # noqa: E402
from rigmix.io.gltf import read_gltf, write_gltf  # noqa: E402
from rigmix.io.validator import validate_gltf, validator_available  # noqa: E402

REPEATS = 5


def main():
    import pygltflib

    rows = []
    read_gltf(ASSETS / CHARACTERS["SimpleSkin"])  # warm the imports
    with tempfile.TemporaryDirectory() as tmp:
        for name, rel in sorted(CHARACTERS.items()):
            path = ASSETS / rel
            if not path.exists():
                continue
            character = read_gltf(path)
            out = Path(tmp) / f"{name}.glb"
            row = {
                "name": name,
                "bytes": path.stat().st_size,
                "read_ms": 1e3 * median_seconds(lambda: read_gltf(path), REPEATS),
                "write_ms": 1e3 * median_seconds(lambda: write_gltf(character, out), REPEATS),
                "pygltflib_load_ms": 1e3 * median_seconds(lambda: pygltflib.GLTF2().load(str(path)), 1),
                "written_bytes": out.stat().st_size,
            }
            if validator_available():
                row["validator_errors_in"] = validate_gltf(path)["issues"]["numErrors"]
                row["validator_errors_out"] = validate_gltf(out)["issues"]["numErrors"]
            rows.append(row)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"python": platform.python_version(), "machine": platform.machine(), "repeats": REPEATS}
    (RESULTS / "gltf_io.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    lines = [
        "| character | bytes | read ms | write ms | pygltflib load ms | validator errors in -> out |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        v = f"{r.get('validator_errors_in', '-')} -> {r.get('validator_errors_out', '-')}"
        lines.append(f"| {r['name']} | {r['bytes']:,} | {r['read_ms']:.1f} | {r['write_ms']:.1f} | "
                     f"{r['pygltflib_load_ms']:.1f} | {v} |")
    (RESULTS / "gltf_io.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
