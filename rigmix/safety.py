"""Safe file output shared by the writers, the CLI and the batch runner.

Every file rigmix writes goes through :func:`atomic_output`: the data are written to a
temporary file in the target's folder, which is renamed over the target only when the writer
succeeded. A failure (an exception, a bad value found half way) never leaves a partial or
empty output file, and an existing file at the target is untouched until the rename.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError

__all__ = ["atomic_output", "atomic_write_bytes", "atomic_write_text", "make_readable", "file_digest"]


def make_readable(path) -> None:
    """Give a ``mkstemp`` file (mode 0600) the permissions of an ordinary new file (``0666 & ~umask``)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextmanager
def atomic_output(path, *, suffix: str | None = None):
    """Write ``path`` atomically: yield a temporary path beside it, rename it over ``path`` on success.

    Parameters
    ----------
    path : str or Path
        The final file. Its folder must exist.
    suffix : str, optional
        Suffix of the temporary file (default ``".tmp"``); writers that choose the format by
        suffix (USD's ``Export``) need the target's.

    Yields
    ------
    Path
        The temporary file (already created, empty) to write to.

    Raises
    ------
    InputError
        The folder of ``path`` does not exist or is not writable, or ``path`` cannot be replaced
        (e.g. it is a folder).

    Notes
    -----
    On any exception inside the ``with`` block (``KeyboardInterrupt`` included) the temporary
    file is removed and the exception propagates; ``path`` is then as it was before.

    Examples
    --------
    >>> with atomic_output(out) as tmp:       # doctest: +SKIP
    ...     tmp.write_bytes(payload)
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" if suffix is None else suffix,
                                   dir=path.parent)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc} (does the folder exist and is it "
                         "writable?)") from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        make_readable(tmp)
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise InputError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_output`; returns ``Path(path)``."""
    path = Path(path)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return path


def atomic_write_text(path, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` through :func:`atomic_output`; returns ``Path(path)``."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def file_digest(path) -> str:
    """SHA-256 hex digest of a file's bytes (to check that inputs are left unchanged)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
