"""The Khronos glTF-Validator (npm ``gltf-validator``), run through Node.

The set-up (``make env``: ``npm ci``) installs the package in ``node_modules/`` at the
repository root; ``RIGMIX_NODE_MODULES`` can point elsewhere. Used by the tests to check that
every file :func:`rigmix.io.gltf.write_gltf` writes has 0 errors.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

from ..errors import RigmixError

__all__ = ["validate_gltf", "validator_available", "ValidatorUnavailable"]

SCRIPT = Path(__file__).with_name("validate_gltf.mjs")


class ValidatorUnavailable(RigmixError):
    """Node or the ``gltf-validator`` package is missing."""


def _node_modules() -> Path:
    env = os.environ.get("RIGMIX_NODE_MODULES")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "node_modules"


def validator_available() -> bool:
    """Whether :func:`validate_gltf` can run (node on PATH and the package installed)."""
    return shutil.which("node") is not None and (_node_modules() / "gltf-validator").is_dir()


def validate_gltf(path, *, timeout: float = 120.0) -> dict:
    """Validate a ``.glb`` or ``.gltf`` (external resources resolved next to it).

    Parameters
    ----------
    path : str or Path
    timeout : float
        Seconds before giving up.

    Returns
    -------
    dict
        The validator's report; ``report["issues"]["numErrors"]`` is the error count and
        ``report["issues"]["messages"]`` the list of ``{code, message, severity, pointer}``
        (severity 0 error, 1 warning, 2 info, 3 hint).

    Raises
    ------
    ValidatorUnavailable
        Node or the npm package is missing (with the command that installs them).
    RigmixError
        The validator could not run on the file.
    """
    path = Path(path)
    node = shutil.which("node")
    modules = _node_modules()
    if node is None:
        raise ValidatorUnavailable("validate_gltf: 'node' is not on PATH: install Node.js 18+ and run `npm ci`")
    if not (modules / "gltf-validator").is_dir():
        raise ValidatorUnavailable(
            f"validate_gltf: the npm package gltf-validator is not in {modules}: run `npm ci` at the "
            "repository root (or set RIGMIX_NODE_MODULES)"
        )
    try:
        res = subprocess.run(
            [node, str(SCRIPT), str(path), str(modules)], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        raise RigmixError(f"validate_gltf: {path.name}: the validator took longer than {timeout} s") from None
    if res.returncode != 0:
        raise RigmixError(f"validate_gltf: {path.name}: the validator failed: {_failure_line(res.stderr)}")
    return json.loads(res.stdout)


def _failure_line(stderr: str) -> str:
    """The line of Node's stderr that says what failed: its first ``...Error: ...`` line (Node
    ends with a stack and its own version, e.g. ``RangeError: Maximum call stack size exceeded``
    on a node hierarchy about 7,000 deep), else the last line."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if re.match(r"[A-Za-z]*Error\b", ln)]
    if errors:
        return errors[0]
    return lines[-1] if lines else "(no output)"
