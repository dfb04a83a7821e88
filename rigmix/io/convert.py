"""Writing a character by file suffix, and converting between formats (``rigmix convert``).

Reading goes through :func:`rigmix.io.load_character` (the reader is chosen by suffix);
:func:`save_character` is its counterpart for writing. USD targets take every clip (one
``SkelAnimation`` each, behind the ``animation`` variant set), materials with their textures
(``textures/`` next to the file) and props; see :mod:`rigmix.io.usd`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..errors import InputError
from . import format_handler

__all__ = ["WRITERS", "convert", "save_character"]

logger = logging.getLogger(__name__)

#: File suffix -> ``"module:function"`` writing a Character (imported on first use).
WRITERS = {
    ".glb": "rigmix.io.gltf:write_gltf",
    ".gltf": "rigmix.io.gltf:write_gltf",
    ".usda": "rigmix.io.usd:write_usd",
    ".usdc": "rigmix.io.usd:write_usd",
    ".usd": "rigmix.io.usd:write_usd",
    ".usdz": "rigmix.io.usd:write_usd",
}


def save_character(character, path):
    """Write a character, choosing the writer by suffix (``.glb``, ``.gltf``, ``.usd[a|c|z]``).

    Parameters
    ----------
    character : rigmix.character.Character
    path : str or Path

    Returns
    -------
    pathlib.Path
        The written file (written atomically by every writer: no partial file on error).

    Raises
    ------
    InputError
        An unsupported suffix (the message lists the supported ones) or a write failure.
    """
    path = Path(path)
    format_handler(WRITERS, path, stage="save_character", problem="cannot write format")(character, path)
    return path


def convert(source, target):
    """Read any character file and write it in the format of ``target``'s suffix.

    Parameters
    ----------
    source : str or Path
        Any file :func:`rigmix.io.load_character` reads (``.glb``, ``.gltf``, and the UsdSkel
        files :mod:`rigmix.io.usd_read` reads: ``.usda``, ``.usdc``, ``.usd``, ``.usdz``).
    target : str or Path
        ``.usda``, ``.usdc``, ``.usd`` (crate), ``.usdz``, ``.glb`` or ``.gltf``.

    Returns
    -------
    rigmix.character.Character
        The character read (its ``warnings`` list the repairs made on load).
    """
    from . import load_character

    source, target = Path(source), Path(target)
    # fail before the (possibly slow) read
    format_handler(WRITERS, target, stage="convert", problem="cannot write format", load=False)
    if source.resolve() == target.resolve():
        raise InputError(f"convert: {source} is both the input and the output; choose another output path")
    character = load_character(source)
    save_character(character, target)
    logger.info("convert: %s -> %s (%d joints, %d meshes, %d clips)", source, target,
                character.skeleton.num_joints, len(character.meshes), len(character.clips))
    return character
