"""A time bound of issue 26, in this machine's seconds: ``python -m benchmarks.calibrate SECONDS``.

Issue 26's bounds (no test over 60 s, a composition within 60 s, ...) were set on a machine where
the reference operation (:func:`benchmarks.common.reference_operation`) takes
:data:`TARGET_REFERENCE_SECONDS`. On a slower machine, or a loaded one, the same work takes longer
in proportion: :func:`scaled_bound` multiplies a bound by the reference's seconds here over that
figure (never below 1). ``make test`` gives pytest's per-test ``--timeout`` this way, so that the
suite guards against a hang on any machine while the bound itself stays what the benchmarks
measure (as multiples of the reference).

Prints the scaled bound (whole seconds) on stdout and how it was found on stderr; without the
Horse to time the reference on (``RIGMIX_ASSETS``), the bound unscaled.
"""

from __future__ import annotations

import math
import sys

#: The reference operation's seconds on the machine issue 26's bounds were set on (2 cores, idle;
#: ``benchmarks/results/compose_bench.json`` measured 1.16 to 1.20 s there).
TARGET_REFERENCE_SECONDS = 1.2


def scaled_bound(seconds: float, reference_seconds: float) -> float:
    """``seconds`` times ``reference_seconds / TARGET_REFERENCE_SECONDS``, at least ``seconds``."""
    return float(seconds) * max(1.0, float(reference_seconds) / TARGET_REFERENCE_SECONDS)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if len(args) != 1:
        print("usage: python -m benchmarks.calibrate SECONDS", file=sys.stderr)
        return 2
    try:
        bound = float(args[0])
    except ValueError:
        print(f"calibrate: {args[0]!r} is not a number of seconds", file=sys.stderr)
        return 2
    from benchmarks.common import reference_operation

    try:
        ref = reference_operation(repeats=1)["seconds"]
    except FileNotFoundError as exc:
        print(f"calibrate: {exc}; the bound is left at {bound:g} s", file=sys.stderr)
        print(math.ceil(bound))
        return 0
    scaled = scaled_bound(bound, ref)
    print(f"calibrate: reference operation {ref:.2f} s here, {TARGET_REFERENCE_SECONDS:g} s where the bounds were "
          f"set: {bound:g} s -> {math.ceil(scaled)} s", file=sys.stderr)
    print(math.ceil(scaled))
    return 0


if __name__ == "__main__":
    sys.exit(main())
