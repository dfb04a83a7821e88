"""glTF containers and accessors: bytes in, bounds-checked numpy arrays out.

This module knows the glTF *binary layout* and nothing of characters:

* :func:`load_document` splits a ``.glb`` (header, JSON chunk, BIN chunk) or parses a ``.gltf``
  JSON file, and resolves every buffer (GLB BIN chunk, ``data:`` URI with either
  ``application/octet-stream`` or ``application/gltf-buffer``, or an external file next to the
  glTF).
* :class:`Document.accessor` reads one accessor into numpy with one strided view per accessor
  (no Python loop over elements): byte strides, matrix column padding, sparse substitution and
  normalized integer types are handled.

The JSON is parsed with :mod:`json` into plain dicts rather than pygltflib's dataclasses:
decoding the shared Horse's JSON with ``pygltflib.GLTF2.from_dict`` alone takes about 0.5 s,
some 20 times this whole reader, and reports malformed values as Python warnings instead of
errors. Every field is checked where it is used instead.

Reads are bounded: a declared ``byteLength`` is checked against the bytes that really exist
before anything is allocated; buffer view and accessor ranges are checked before numpy sees
them. Every failure is an :class:`rigmix.errors.InputError` naming the file and the object.

Reads are confined (:meth:`Document.resolve_uri`, :func:`read_regular_file`): the file given and
every file a URI names must be a *regular* file (never a device, FIFO or folder: ``/dev/zero``
would be read until memory runs out), no larger than :data:`MAX_FILE_BYTES` (images:
:data:`MAX_IMAGE_BYTES`), its size checked before it is read. A URI names a file inside the
glTF's own folder only: it is percent-decoded and its symlinks resolved, and an absolute path, a
scheme other than ``data:``, or a path that ends up outside the folder (``../``, ``%2e%2e/``, a
symlink pointing out) is refused without being opened, with a message that echoes neither the
URI nor the outside path and does not tell whether that file exists. ``data:`` URIs are capped
before decoding by what their declared ``byteLength`` (or the image limit) can need.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import os
import re
import stat
import struct
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..errors import InputError

__all__ = [
    "Document", "load_document", "COMPONENT_DTYPES", "TYPE_SHAPES", "decode_data_uri", "read_regular_file",
    "MAX_FILE_BYTES", "MAX_IMAGE_BYTES",
]

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

#: glTF componentType -> little-endian numpy dtype.
COMPONENT_DTYPES = {
    5120: np.dtype("<i1"),
    5121: np.dtype("<u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
#: glTF accessor type -> (columns, rows); vectors are one column.
TYPE_SHAPES = {
    "SCALAR": (1, 1),
    "VEC2": (1, 2),
    "VEC3": (1, 3),
    "VEC4": (1, 4),
    "MAT2": (2, 2),
    "MAT3": (3, 3),
    "MAT4": (4, 4),
}
#: An accessor without a buffer view is all zeros; refuse to allocate more elements than this.
MAX_ZERO_ELEMENTS = 1 << 24
#: Largest input file, external buffer or ``data:`` buffer read (1 GiB): the largest shared
#: character is some 30 MB, and reading the whole of anything larger would not fit the 2 GB of
#: memory a composition is allowed.
MAX_FILE_BYTES = 1 << 30
#: Largest image read for a base colour texture (256 MiB: a 8k x 8k RGBA PNG is at most 256 MiB
#: uncompressed); a larger image is refused before it is read.
MAX_IMAGE_BYTES = 1 << 28
#: A URI scheme (``file:``, ``http:``, ...): only ``data:`` is read, by :func:`decode_data_uri`.
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


@dataclass
class Document:
    """A parsed glTF: its JSON, its resolved buffers, and where it came from.

    Attributes
    ----------
    json : dict
        The glTF JSON.
    buffers : list of memoryview
        Buffer ``i`` cut to its declared ``byteLength`` (never longer than the bytes that exist).
    path : Path
        The file read (external URIs resolve relative to its folder).
    bounds_mismatch : list of str
        Labels of the float accessors read so far whose declared ``min``/``max`` differ from
        their data (the glTF validator's error; the writer recomputes bounds, so the reader
        reports it as a repair).
    """

    json: dict
    buffers: list
    path: Path
    bounds_mismatch: list = field(default_factory=list)
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def name(self) -> str:
        return self.path.name

    def error(self, message: str) -> InputError:
        """An :class:`InputError` prefixed with the file name."""
        return InputError(f"{self.name}: {message}")

    def items(self, key: str) -> list:
        """The top-level array ``key`` (``[]`` when absent); an InputError if not a list."""
        value = self.json.get(key, [])
        if not isinstance(value, list):
            raise self.error(f"'{key}' must be a JSON array, got {type(value).__name__}")
        return value

    def get(self, key: str, index, what: str = "") -> dict:
        """Object ``index`` of the top-level array ``key``, with a clear error if out of range."""
        arr = self.items(key)
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(arr):
            ref = f" (referenced by {what})" if what else ""
            raise self.error(f"{key}[{index!r}] does not exist{ref}: the file has {len(arr)} {key}")
        obj = arr[index]
        if not isinstance(obj, dict):
            raise self.error(f"{key}[{index}] must be a JSON object")
        return obj

    def buffer_view(self, index: int, what: str = "") -> memoryview:
        """The bytes of buffer view ``index``, range-checked against its buffer."""
        bv = self.get("bufferViews", index, what)
        buf = _int(self, bv, "buffer", f"bufferViews[{index}]")
        if not 0 <= buf < len(self.buffers):
            raise self.error(f"bufferViews[{index}] refers to buffer {buf}, the file has {len(self.buffers)}")
        offset = _int(self, bv, "byteOffset", f"bufferViews[{index}]", 0)
        length = _int(self, bv, "byteLength", f"bufferViews[{index}]")
        data = self.buffers[buf]
        if offset < 0 or length < 0 or offset + length > len(data):
            raise self.error(
                f"bufferViews[{index}] spans bytes {offset}..{offset + length} but buffer {buf} has "
                f"{len(data)} bytes (truncated or corrupt file)"
            )
        return data[offset : offset + length]

    def accessor(self, index: int, what: str = "") -> np.ndarray:
        """Read accessor ``index``.

        Parameters
        ----------
        index : int
        what : str
            Who references it, for messages (e.g. ``"mesh 'Wasp' POSITION"``).

        Returns
        -------
        (count, n) array, ``n`` the number of components (16 for MAT4, column-major as in the
        file). Floats and normalized integers are float64 (normalized mapped to [0, 1] or
        [-1, 1]); other integers keep an integer dtype. A cached read-only array.
        """
        if index in self._cache:
            return self._cache[index]
        acc = self.get("accessors", index, what)
        label = f"accessors[{index}]" + (f" ({what})" if what else "")
        ctype = acc.get("componentType")
        if ctype not in COMPONENT_DTYPES:
            raise self.error(f"{label} has unknown componentType {ctype!r}")
        dtype = COMPONENT_DTYPES[ctype]
        if acc.get("type") not in TYPE_SHAPES:
            raise self.error(f"{label} has unknown type {acc.get('type')!r}")
        cols, rows = TYPE_SHAPES[acc["type"]]
        count = _int(self, acc, "count", label)
        if count < 1:
            raise self.error(f"{label} has count {count}, expected at least 1")
        ncomp = cols * rows
        # Matrix columns start on 4-byte boundaries (glTF 3.6.2.4); vectors are one column.
        col_bytes = rows * dtype.itemsize
        col_stride = -(-col_bytes // 4) * 4 if cols > 1 else col_bytes
        elem_bytes = col_stride * (cols - 1) + col_bytes

        if "bufferView" in acc:
            view = self.buffer_view(acc["bufferView"], label)
            bv = self.get("bufferViews", acc["bufferView"])
            stride = _int(self, bv, "byteStride", f"bufferViews[{acc['bufferView']}]", 0) or elem_bytes
            if stride < elem_bytes:
                raise self.error(f"{label}: byteStride {stride} is smaller than one element ({elem_bytes} bytes)")
            offset = _int(self, acc, "byteOffset", label, 0)
            end = offset + stride * (count - 1) + elem_bytes
            if offset < 0 or end > len(view):
                raise self.error(
                    f"{label} reads bytes {offset}..{end} of bufferViews[{acc['bufferView']}] which has "
                    f"{len(view)} bytes (count {count}, stride {stride}): out of range"
                )
            raw = np.ndarray(
                (count, cols, rows), dtype=dtype, buffer=view, offset=offset,
                strides=(stride, col_stride, dtype.itemsize),
            )
            out = raw.copy().reshape(count, ncomp)  # one contiguous copy we own
        else:
            if count * ncomp > MAX_ZERO_ELEMENTS:
                raise self.error(f"{label} has no bufferView and a count of {count}: too large to allocate")
            out = np.zeros((count, ncomp), dtype=dtype)

        if "sparse" in acc:
            self._apply_sparse(acc["sparse"], out, label, dtype, elem_bytes, cols, rows, col_stride)
        if dtype.kind == "f":
            if not _bounds_match(acc, out, ncomp):
                self.bounds_mismatch.append(label)
            out = out.astype(np.float64)
        elif acc.get("normalized", False):
            out = _normalize_ints(out)
        out.setflags(write=False)
        self._cache[index] = out
        return out

    def _apply_sparse(self, sparse, out, label, dtype, elem_bytes, cols, rows, col_stride):
        """Substitute the sparse values into ``out`` in place (indices and ranges checked)."""
        if not isinstance(sparse, dict):
            raise self.error(f"{label}: 'sparse' must be an object")
        n = _int(self, sparse, "count", f"{label} sparse")
        if not 1 <= n <= len(out):
            raise self.error(f"{label}: sparse count {n} must be between 1 and the accessor count {len(out)}")
        ind, val = sparse.get("indices"), sparse.get("values")
        if not isinstance(ind, dict) or not isinstance(val, dict):
            raise self.error(f"{label}: sparse 'indices' and 'values' are required")
        itype = ind.get("componentType")
        if itype not in (5121, 5123, 5125):
            raise self.error(f"{label}: sparse indices componentType {itype!r} must be an unsigned integer type")
        idtype = COMPONENT_DTYPES[itype]
        ibytes = self._sparse_bytes(ind, n * idtype.itemsize, f"{label} sparse indices")
        idx = np.frombuffer(ibytes, dtype=idtype, count=n).astype(np.int64)
        if idx.max() >= len(out):
            raise self.error(f"{label}: sparse index {int(idx.max())} is past the accessor count {len(out)}")
        if np.any(np.diff(idx) <= 0):
            raise self.error(f"{label}: sparse indices must be strictly increasing")
        vbytes = self._sparse_bytes(val, n * elem_bytes, f"{label} sparse values")
        vals = np.ndarray((n, cols, rows), dtype=dtype, buffer=vbytes,
                          strides=(elem_bytes, col_stride, dtype.itemsize))
        out[idx] = vals.reshape(n, cols * rows)

    def _sparse_bytes(self, ref, nbytes, label):
        view = self.buffer_view(ref.get("bufferView"), label)
        offset = _int(self, ref, "byteOffset", label, 0)
        if offset < 0 or offset + nbytes > len(view):
            raise self.error(f"{label} reads bytes {offset}..{offset + nbytes} of a bufferView of {len(view)} bytes")
        return view[offset : offset + nbytes]

    def resolve_uri(self, uri: str, what: str, *, must_exist: bool = True) -> Path | None:
        """The regular file inside the glTF's folder that a relative ``uri`` names.

        Parameters
        ----------
        uri : str
            Percent-encoded relative URI (not a ``data:`` URI).
        what : str
            Who refers to it, for messages (e.g. ``"buffers[1]"``).
        must_exist : bool
            ``False``: a URI naming no file inside the folder gives ``None`` (a missing texture
            is dropped with a warning); anything that is not confined is refused all the same.

        Returns
        -------
        Path
            The real path (symlinks resolved), a regular file within the folder's real path.

        Raises
        ------
        InputError
            A scheme, an absolute path, a path leading outside the folder (``..``, a symlink), a
            NUL byte, or something that is not a regular file. Outside paths are never opened
            nor echoed, and whether they exist is never told.
        """
        fix = "only files inside the glTF's own folder are read: embed the data or copy the file next to it"
        decoded = unquote(uri)
        if _SCHEME.match(uri) or _SCHEME.match(decoded):  # file:, http:, a drive letter
            raise self.error(f"{what} has a URI with a scheme or drive letter: {fix}")
        if "\0" in decoded or os.path.isabs(decoded) or decoded.startswith(("\\", "/")):
            raise self.error(f"{what} has an absolute or malformed file URI: {fix}")
        folder = os.path.realpath(self.path.parent)
        target = os.path.realpath(os.path.join(folder, decoded.replace("\\", "/")))
        if os.path.commonpath([folder, target]) != folder:
            raise self.error(f"{what} has a URI that leads outside the glTF's folder: {fix}")
        try:
            st = os.stat(target)
        except OSError:
            if not must_exist:
                return None
            raise self.error(f"{what} refers to {uri!r} which was not found next to the file") from None
        if not stat.S_ISREG(st.st_mode):
            raise self.error(f"{what} refers to {uri!r} which is not a regular file: {fix}")
        return Path(target)


def _int(doc: Document, obj: dict, key: str, label: str, default=None) -> int:
    """``obj[key]`` as an int (``default`` when absent); an InputError if missing or not integral."""
    if key not in obj:
        if default is None:
            raise doc.error(f"{label} has no '{key}'")
        return default
    v = obj[key]
    # json reads NaN and Infinity as floats: int() of them would raise ValueError/OverflowError
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v):
        raise doc.error(f"{label}: '{key}' must be an integer, got {v!r}")
    return int(v)


def _bounds_match(acc: dict, data: np.ndarray, ncomp: int) -> bool:
    """Whether a float accessor's declared ``min``/``max`` (when given) equal its data's, per
    component, compared in float32 as stored; NaN data never matches."""
    for key, reduce in (("min", np.min), ("max", np.max)):
        declared = acc.get(key)
        if declared is None:
            continue
        if (not isinstance(declared, list) or len(declared) != ncomp
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in declared)):
            return False
        with np.errstate(over="ignore", invalid="ignore"):
            want = np.asarray(declared, np.float64).astype(np.float32)
            if not np.array_equal(reduce(data, axis=0).astype(np.float32), want):
                return False
    return True


def _normalize_ints(a: np.ndarray) -> np.ndarray:
    """glTF normalized integers to float64: unsigned to [0, 1], signed to [-1, 1]."""
    info = np.iinfo(a.dtype)
    f = a.astype(np.float64) / info.max
    return np.maximum(f, -1.0) if info.min < 0 else f


def decode_data_uri(uri: str, doc: Document, what: str, max_bytes: int = MAX_FILE_BYTES) -> tuple[bytes, str]:
    """Decode a ``data:[mime][;base64],payload`` URI into ``(bytes, mime)``.

    Parameters
    ----------
    uri : str
    doc : Document
        For messages.
    what : str
        Who holds the URI (e.g. ``"buffers[0]"``).
    max_bytes : int
        The most bytes the caller needs (a buffer's ``byteLength``, the image limit): a payload
        whose encoded length could only decode to more (beyond 3 bytes of padding) is refused
        before anything is decoded.

    Raises
    ------
    InputError
        A malformed URI, a payload that cannot be decoded, or one longer than ``max_bytes`` allows.
    """
    head, sep, payload = uri.partition(",")
    if not sep:
        raise doc.error(f"{what}: malformed data URI (no comma)")
    mime = head[5:].split(";")[0]
    base64_encoded = head.endswith(";base64")
    # base64: 4 characters per 3 bytes; percent-encoding: up to 3 characters per byte
    limit = 4 * (-(-(max_bytes + 3) // 3)) if base64_encoded else 3 * (max_bytes + 3)
    if len(payload) > limit:
        raise doc.error(
            f"{what}: data URI of {len(payload)} characters is longer than its {max_bytes} bytes can need "
            "(declared byteLength, or the size limit): corrupt or hostile file"
        )
    try:
        if base64_encoded:
            data = base64.b64decode(payload, validate=False)
        else:
            data = unquote(payload).encode("latin-1")
    except (binascii.Error, ValueError, UnicodeEncodeError) as exc:
        raise doc.error(f"{what}: data URI cannot be decoded ({exc})") from None
    return data, mime


def read_regular_file(path, *, limit: int | None, name: str, label: str = "the file",
                      at_most: int | None = None) -> bytes:
    """The bytes of a regular file, refused before reading when it is not one or is too large.

    Parameters
    ----------
    path : str or Path
        Followed if a symlink (the caller confines it first when it comes from a URI).
    limit : int or None
        Largest file size accepted, in bytes (:data:`MAX_FILE_BYTES`, :data:`MAX_IMAGE_BYTES`);
        ``None`` when ``at_most`` bounds the read instead.
    name : str
        The file name messages start with.
    label : str
        What is read, for messages (``"buffers[1]"``).
    at_most : int, optional
        Read only this many bytes (a buffer's ``byteLength``; the file may be longer).

    Raises
    ------
    InputError
        Missing or unreadable, a device, FIFO, socket or folder, or larger than ``limit``.
    """
    try:
        st = os.stat(path)  # before opening: a FIFO would block, /dev/zero never end
    except OSError as exc:
        raise InputError(f"{name}: cannot read {label} ({exc.strerror or type(exc).__name__})") from None
    _check_regular(st, limit, name, label)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise InputError(f"{name}: cannot read {label} ({exc.strerror or type(exc).__name__})") from None
    with os.fdopen(fd, "rb") as fh:
        _check_regular(os.fstat(fh.fileno()), limit, name, label)  # the file opened, not a swapped one
        try:
            return fh.read(at_most) if at_most is not None else fh.read()
        except OSError as exc:
            raise InputError(f"{name}: cannot read {label} ({exc.strerror or type(exc).__name__})") from None


def _check_regular(st: os.stat_result, limit: int | None, name: str, label: str) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "a device, FIFO or socket"
        raise InputError(f"{name}: {label} is {kind}, not a regular file")
    if limit is not None and st.st_size > limit:
        raise InputError(f"{name}: {label} has {st.st_size} bytes, more than the {limit}-byte limit")


def _split_glb(raw: bytes, name: str) -> tuple[bytes, bytes | None]:
    """GLB header and chunks -> (JSON bytes, BIN bytes or None), with bounds checks."""
    if len(raw) < 20:
        raise InputError(f"{name}: truncated GLB ({len(raw)} bytes, a GLB header and JSON chunk need at least 20)")
    _, version, length = struct.unpack_from("<4sII", raw, 0)
    if version != 2:
        raise InputError(f"{name}: GLB version {version} is not supported (glTF 2.0 expected)")
    if length > len(raw):
        raise InputError(f"{name}: truncated GLB: the header declares {length} bytes but the file has {len(raw)}")
    pos, chunks = 12, []
    while pos + 8 <= length:
        clen, ctype = struct.unpack_from("<II", raw, pos)
        if pos + 8 + clen > length:
            raise InputError(
                f"{name}: truncated GLB: chunk {len(chunks)} declares {clen} bytes at offset {pos + 8} "
                f"but the file ends at {length}"
            )
        chunks.append((ctype, raw[pos + 8 : pos + 8 + clen]))
        pos += 8 + clen
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise InputError(f"{name}: corrupt GLB: the first chunk is not a JSON chunk")
    bin_chunk = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN else None
    return chunks[0][1], bin_chunk


def _parse_json(text: bytes, name: str, where: str) -> dict:
    try:
        doc = json.loads(text.decode("utf-8-sig"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{name}: corrupted {where}: not valid UTF-8 JSON ({exc})") from None
    except RecursionError:  # arrays or objects nested thousands deep
        raise InputError(f"{name}: corrupted {where}: JSON nested too deeply to be glTF") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
        raise InputError(f"{name}: {where} is not a glTF document (no 'asset' object)")
    version = str(doc["asset"].get("version", ""))
    if not version.startswith("2."):
        raise InputError(f"{name}: glTF version {version!r} is not supported (2.0 expected)")
    return doc


def load_document(path) -> Document:
    """Read a ``.glb`` or ``.gltf`` file and resolve its buffers.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Document

    Raises
    ------
    InputError
        Missing file, not glTF, truncated GLB, corrupted JSON, a buffer shorter than its
        declared ``byteLength``, or a missing external buffer.
    """
    path = Path(path)
    name = path.name
    raw = read_regular_file(path, limit=MAX_FILE_BYTES, name=name)
    bin_chunk = None
    if raw[:4] == GLB_MAGIC:
        text, bin_chunk = _split_glb(raw, name)
        js = _parse_json(text, name, "GLB JSON chunk")
    elif raw.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{":
        js = _parse_json(raw, name, "glTF JSON")
    else:
        raise InputError(f"{name}: not a glTF file (neither the GLB magic 'glTF' nor a JSON document)")
    doc = Document(js, [], path)
    budget = MAX_FILE_BYTES  # all buffers read from URIs together
    for i, buf in enumerate(doc.items("buffers")):
        if not isinstance(buf, dict):
            raise doc.error(f"buffers[{i}] must be a JSON object")
        declared = _int(doc, buf, "byteLength", f"buffers[{i}]")
        uri = buf.get("uri")
        if uri is None:
            if i != 0 or bin_chunk is None:
                raise doc.error(f"buffers[{i}] has no uri and there is no GLB BIN chunk for it")
            data = bin_chunk
            where = "the GLB BIN chunk"
        elif not isinstance(uri, str):
            raise doc.error(f"buffers[{i}].uri must be a string")
        elif uri.startswith("data:"):
            data, _ = decode_data_uri(uri, doc, f"buffers[{i}]", max_bytes=max(0, min(declared, budget)))
            where = "its data URI"
            budget -= len(data)
        else:
            ext = doc.resolve_uri(uri, f"buffers[{i}]")
            size = ext.stat().st_size
            if declared > size:  # checked before reading: never allocate a declared size
                raise doc.error(f"buffers[{i}] declares {declared} bytes but {uri!r} has {size}")
            if declared > budget:
                raise doc.error(f"buffers[{i}] declares {declared} bytes: the buffers of one file may hold "
                                f"{MAX_FILE_BYTES} bytes in all")
            data = read_regular_file(ext, limit=None, name=name, label=f"buffers[{i}] ({uri!r})", at_most=declared)
            where = repr(uri)
            budget -= declared
        if declared < 0 or declared > len(data):
            raise doc.error(
                f"buffers[{i}] declares byteLength {declared} but {where} holds {len(data)} bytes "
                "(truncated or corrupt file)"
            )
        doc.buffers.append(memoryview(data)[:declared])
    return doc
