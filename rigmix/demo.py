"""`make demo`: the main job on the built-in example characters (no third-party assets)."""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rigmix.demo")
    parser.add_argument("--out", default="out/demo")
    args = parser.parse_args(argv)
    print(f"demo: nothing to do yet (out={args.out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
