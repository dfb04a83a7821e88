"""File formats: files <-> :class:`rigmix.character.Character`.

The only place where conventions change (e.g. USD's row-vector matrices).
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path

from ..errors import InputError

__all__ = ["READERS", "format_handler", "load_character"]

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
    return format_handler(READERS, path, stage="load_character", problem="unsupported format")(path)


def format_handler(table, path, *, stage, problem, load=True):
    """The function a suffix table names for ``path`` (the reader or writer of its format).

    Parameters
    ----------
    table : dict of str -> str
        Lower-case suffix -> ``"module:function"`` (:data:`READERS`,
        :data:`rigmix.io.convert.WRITERS`).
    path : Path
    stage, problem : str
        Named in the error: ``"<stage>: <file name>: <problem> '<suffix>'; supported: ..."``.
    load : bool
        Import the module and return the function; ``False`` only checks the suffix.

    Returns
    -------
    callable or None
        ``None`` with ``load=False``.

    Raises
    ------
    InputError
        A suffix the table does not list (the message lists the ones it does).
    """
    entry = table.get(path.suffix.lower())
    if entry is None:
        supported = ", ".join(sorted(table))
        raise InputError(f"{stage}: {path.name}: {problem} {path.suffix or '(no suffix)'!r}; "
                         f"supported: {supported}")
    if not load:
        return None
    module, func = entry.split(":")
    return getattr(import_module(module), func)
