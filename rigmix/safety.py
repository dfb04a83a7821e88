"""Safe file output shared by the writers, the CLI and the batch runner.

Every file rigmix writes goes through :func:`atomic_output`: the data are written to a
temporary file in the target's folder, which is renamed over the target only when the writer
succeeded. A failure (an exception, a bad value found half way) never leaves a partial or
empty output file, and an existing file at the target is untouched until the rename.

:func:`same_file` and :func:`check_outputs` refuse an output path that is one of the run's
inputs or another of its outputs (symlinks, ``./x`` and ``x``, hard links all compared).

Signals: :func:`signals_raise` makes SIGTERM and SIGINT raise :class:`Interrupted` in the main
thread (the command line and the batch workers install it), so that the ``finally`` blocks and
context managers of the writers remove their temporary files and folders before the process
exits; the default SIGTERM action would kill the process with them left behind.
"""

from __future__ import annotations

import errno
import hashlib
import os
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError

__all__ = ["atomic_output", "atomic_write_bytes", "atomic_write_text", "make_readable", "file_digest",
           "write_error_hint", "same_file", "check_outputs", "Interrupted", "signals_raise",
           "received_signal"]


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
    tmp = None
    try:
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" if suffix is None else suffix,
                                       dir=path.parent)
        except OSError as exc:
            raise InputError(f"cannot write {path}: {exc.strerror or exc} ({write_error_hint(exc)})") from exc
        tmp = Path(tmp)
        os.close(fd)
        yield tmp
        make_readable(tmp)
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc
    except BaseException:
        if tmp is not None:
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


def write_error_hint(exc: OSError) -> str:
    """What to do about an ``OSError`` met while writing an output (for one-line messages)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return "the disk is full or the file too large: free some space or write to another disk"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return "choose a folder you can write to"
    return "does the folder exist and is it writable?"


# --------------------------------------------------------------------------------------------
# Output paths
# --------------------------------------------------------------------------------------------


def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name the same file: equal real paths (symlinks resolved,
    ``./x`` and ``x``), or the same inode when both exist (hard links). Missing files compare by
    real path only."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        sa, sb = os.stat(a), os.stat(b)
    except (OSError, ValueError):
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def check_outputs(outputs, inputs, *, stage: str) -> None:
    """Refuse an output that is an input or another output of the same run.

    Parameters
    ----------
    outputs : iterable of (str, path)
        ``(what, path)`` of each file (or folder) the run will write, e.g. ``("-o", "x.glb")``.
    inputs : iterable of (str, path)
        ``(what, path)`` of each file the run reads, e.g. ``("the config", "c.toml")``.
    stage : str
        Prefix of the message (``"compose"``, ``"batch"``).

    Raises
    ------
    InputError
        One line naming both paths and the fix; nothing has been written.
    """
    outputs = [(what, Path(p)) for what, p in outputs if p is not None]
    inputs = [(what, Path(p)) for what, p in inputs if p is not None]
    for i, (what, p) in enumerate(outputs):
        for src, q in inputs:
            if same_file(p, q):
                raise InputError(f"{stage}: {what} {p} is {src}: writing it would destroy an input; "
                                 "choose another output path")
        for other, q in outputs[:i]:
            if same_file(p, q):
                raise InputError(f"{stage}: {what} {p} and {other} {q} are the same file; give each output "
                                 "its own path")


# --------------------------------------------------------------------------------------------
# Signals
# --------------------------------------------------------------------------------------------


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM or SIGINT inside :func:`signals_raise`.

    A ``KeyboardInterrupt`` (not an ``Exception``): ``except Exception`` handlers let it through
    to the command line, while ``finally`` blocks and context managers run on the way.

    Attributes
    ----------
    signum : int
        The signal received; the command line exits with ``128 + signum``.
    """

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: list[int] = []


def _raise_interrupted(signum, frame):
    if _received:  # the first signal's clean-up is running: a second one must not cut it short
        return
    _received.append(signum)
    raise Interrupted(signum)


def received_signal() -> int | None:
    """The signal received inside the current :func:`signals_raise` block, or None."""
    return _received[0] if _received else None


@contextmanager
def signals_raise(signums=(signal.SIGTERM, signal.SIGINT)):
    """Within the block, each of ``signums`` raises :class:`Interrupted` in the main thread.

    Only the first signal raises; later ones are ignored until the block ends, so that the
    clean-up they started finishes. Outside the main thread this does nothing (Python runs
    signal handlers in the main thread only). The previous handlers are restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    previous = {s: signal.signal(s, _raise_interrupted) for s in signums}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
