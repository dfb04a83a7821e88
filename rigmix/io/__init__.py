"""File formats: files <-> :class:`rigmix.character.Character`.

The only place where conventions change (e.g. USD's row-vector matrices).
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path

from ..errors import InputError

__all__ = ["load_character", "READERS"]

#: File suffix -> ``"module:function"`` reading it into a Character (imported on first use).
READERS = {
    ".glb": "rigmix.io.gltf:read_gltf",
    ".gltf": "rigmix.io.gltf:read_gltf",
    ".usda": "rigmix.io.usd_read:read_usd",
    ".usdc": "rigmix.io.usd_read:read_usd",
    ".usd": "rigmix.io.usd_read:read_usd",
    ".usdz": "rigmix.io.usd_read:read_usd",
}


def load_character(path):
    """Read a character file, choosing the reader by suffix.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Character

    Raises
    ------
    InputError
        An unsupported suffix (the message lists the supported ones), or a file the reader
        cannot read.
    """
    path = Path(path)
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        supported = ", ".join(sorted(READERS))
        raise InputError(f"load_character: {path.name}: unsupported format {path.suffix or '(no suffix)'!r}; "
                         f"supported: {supported}")
    module, func = reader.split(":")
    return getattr(import_module(module), func)(path)
