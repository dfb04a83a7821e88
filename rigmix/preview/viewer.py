"""The web viewer behind ``rigmix preview OUT.glb`` (:mod:`rigmix.cli`).

:func:`write_viewer` writes a self-contained folder: ``index.html`` (clip selector, play/pause,
timeline, skeleton overlay), ``viewer.js``, the character as ``model.glb`` and the parts of
three.js it imports (copied from the npm package ``three`` in ``node_modules``, resolved from
the import statements, so the page needs no network), and a marker file, ``.rigmix-preview.json``,
listing those files. :func:`serve` serves such a folder on 127.0.0.1 (ES modules do not load
from ``file://``); :func:`preview` does both.

What is served, and to whom
---------------------------
Only the files the marker lists, by exact name (``/`` is ``index.html``): no directory listing,
no symbolic link is followed, nothing else in the folder is reachable (404). The server listens
on 127.0.0.1 only and answers 403 to a ``Host`` header other than ``127.0.0.1``, ``localhost``
or ``[::1]`` with its port, so that a web page cannot reach it through DNS rebinding. A request
path that is not valid percent-encoded UTF-8, or holds a control character, is a 400. The
character is read with rigmix's glTF reader before anything is written: an invalid file is an
:class:`~rigmix.errors.InputError`, as is an output folder that holds other files (unless
``force``) or a port outside 0-65535.

The page exposes its state as ``window.rigmixViewer`` (``ready``, ``clips``, ``current``,
``time``, ``duration``, ``select(name)``, ``setTime(t)``, ``play()``, ``pause()``) and mirrors
the current clip and time in ``document.body.dataset`` for scripts and tests.
"""

from __future__ import annotations

import html
import json
import logging
import os
import posixpath
import re
import shutil
import stat
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

from ..errors import InputError

__all__ = ["MARKER", "find_three", "relative_imports", "write_viewer", "serve", "preview"]

logger = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
#: three.js addons the viewer imports (their own relative imports are followed).
ADDONS = ("loaders/GLTFLoader.js", "controls/OrbitControls.js")
#: The file that makes a folder a rigmix preview: JSON ``{"rigmix_preview": 1, "files": [...]}``,
#: the files :func:`serve` may send (POSIX paths relative to the folder).
MARKER = ".rigmix-preview.json"
#: The names under which the server answers; each with its port (bare when the port is 80).
LOCAL_HOSTS = ("127.0.0.1", "localhost", "[::1]")
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".glb": "model/gltf-binary"}
_BAD_ESCAPE = re.compile(r"%(?![0-9A-Fa-f]{2})")
_RELATIVE_IMPORT = re.compile(r"""(?:import|export)\s[^;]*?from\s*['"](\.{1,2}/[^'"]+)['"]""", re.S)


def relative_imports(source: str) -> list[str]:
    """The relative module paths (``./x.js``, ``../y/z.js``) that an ES module's source imports
    or re-exports from, in order of appearance; bare names (``"three"``) and URLs are left out."""
    return _RELATIVE_IMPORT.findall(source)


def find_three(start=None) -> Path:
    """The ``node_modules/three`` package directory.

    Looks in ``$RIGMIX_NODE_MODULES``, then in ``node_modules`` of ``start`` (default: the
    current directory), of the repository holding this package, and of their parents.

    Raises
    ------
    InputError
        three.js is not installed (the message says how to install it).
    """
    candidates = []
    if os.environ.get("RIGMIX_NODE_MODULES"):
        candidates.append(Path(os.environ["RIGMIX_NODE_MODULES"]))
    for base in (Path(start) if start else Path.cwd(), HERE):
        for d in (base, *base.parents):
            candidates.append(d / "node_modules")
    for nm in candidates:
        three = nm / "three"
        if (three / "build" / "three.module.js").is_file():
            return three
    raise InputError("preview: three.js not found (node_modules/three); install the npm tools "
                     "with `npm ci` in the repository (or set RIGMIX_NODE_MODULES)")


def _module_closure(src_root: Path, rel: str, seen: dict) -> None:
    """``src_root/rel`` and, recursively, the files it imports by relative path, added to ``seen``
    (normalized relative POSIX path -> source file), in the order they are found."""
    rel = posixpath.normpath(rel)
    if rel in seen:
        return
    if rel.startswith("/") or rel.split("/")[0] == "..":
        raise InputError(f"preview: three.js imports {rel!r}, outside its package (reinstall with `npm ci`)")
    src = src_root.joinpath(*rel.split("/"))
    if not src.is_file():
        raise InputError(f"preview: three.js file {src} is missing (reinstall with `npm ci`)")
    seen[rel] = src
    for dep in relative_imports(src.read_text(encoding="utf-8")):
        _module_closure(src_root, posixpath.join(posixpath.dirname(rel), dep), seen)


def _check_model(glb: Path) -> bytes:
    """The bytes of ``glb`` once rigmix's glTF reader has read it (skeleton, meshes, clips).

    The page loads only ``model.glb``, so a buffer or image in another file could not load:
    every ``uri`` must be a ``data:`` URI.
    """
    from ..io.accessors import load_document
    from ..io.gltf import read_gltf

    if not glb.is_file():  # a missing file, a folder, a device or a FIFO
        what = "not a regular file" if glb.exists() else "no such file"
        raise InputError(f"preview: {glb.name}: {what}; give a .glb, or a .gltf with embedded buffers")
    if glb.suffix.lower() not in (".glb", ".gltf"):
        raise InputError(f"preview: {glb.name}: expected a .glb (or self-contained .gltf) file")
    doc = load_document(glb)
    for kind in ("buffers", "images"):
        for i, item in enumerate(doc.items(kind)):
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                raise InputError(f"preview: {glb.name}: {kind}[{i}] is in a separate file, which the viewer "
                                 f"cannot load; convert it first: rigmix convert {glb.name} {glb.stem}.glb")
    read_gltf(glb)
    return glb.read_bytes()


def _prepare_folder(out: Path, force: bool) -> None:
    """Create ``out``, or check that it may be written: empty, a previous preview, or ``force``."""
    if out.exists() and not out.is_dir():
        raise InputError(f"preview: --out {out.name} is a file, not a folder; give a new or empty folder")
    if out.is_dir() and not force and not (out / MARKER).is_file() and any(out.iterdir()):
        raise InputError(f"preview: --out {out.name} is a folder that holds other files and is not a rigmix "
                         "preview; give a new or empty folder, or --force to write the viewer into it")
    out.mkdir(parents=True, exist_ok=True)


def _put(out: Path, name: str, data) -> None:
    """Write ``data`` (bytes, or a file to copy) as ``out/name`` (a relative POSIX path), never
    through a symbolic link: a link left in the folder in place of a file is replaced, one in
    place of a folder is refused."""
    folder = out
    for part in name.split("/")[:-1]:
        folder = folder / part
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            raise InputError(f"preview: {out.name}/{name.rsplit('/', 1)[0]} is not a folder (a link or a file); "
                             "remove it, or give a new --out folder")
        folder.mkdir(exist_ok=True)
    dst = out.joinpath(*name.split("/"))
    if dst.is_symlink():
        dst.unlink()
    if isinstance(data, Path):
        shutil.copyfile(data, dst)
    else:
        dst.write_bytes(data)


def _write_marker(out: Path, files: list[str]) -> None:
    _put(out, MARKER, (json.dumps({"rigmix_preview": 1, "files": files}, indent=1) + "\n").encode())


def write_viewer(glb, out_dir, *, title=None, three_dir=None, force=False) -> Path:
    """Write the viewer folder for one glTF binary.

    Parameters
    ----------
    glb : str or Path
        The character (``.glb``; a ``.gltf`` whose buffers and images are ``data:`` URIs also
        loads). It is read with :func:`rigmix.io.gltf.read_gltf` first: nothing is written
        for a file rigmix cannot read.
    out_dir : str or Path
        Created if needed; ``index.html``, ``viewer.js``, ``model.glb``, ``vendor/`` and the
        marker :data:`MARKER` are (over)written there. An existing folder must be empty or a
        previous preview (it holds the marker), unless ``force``.
    title : str, optional
        Page title (default: the file name).
    three_dir : str or Path, optional
        The npm ``three`` package (default: :func:`find_three`).
    force : bool
        Write into a folder that holds other files (they are left there, and not served).

    Returns
    -------
    Path
        ``out_dir / "index.html"``.

    Raises
    ------
    InputError
        The file is missing or not glTF that rigmix reads, three.js is missing, or the folder
        holds other files (without ``force``).
    """
    glb = Path(glb)
    model = _check_model(glb)
    three = Path(three_dir) if three_dir else find_three()
    vendor: dict = {}  # "vendor/..." -> the three.js file; all found before anything is written
    for src_root, rel, prefix in [(three / "build", "three.module.js", "vendor"),
                                  *((three / "examples" / "jsm", addon, "vendor/addons") for addon in ADDONS)]:
        seen: dict = {}
        _module_closure(src_root, rel, seen)
        vendor.update((f"{prefix}/{name}", src) for name, src in seen.items())
    out = Path(out_dir)
    _prepare_folder(out, force)
    _write_marker(out, [])  # claims the folder first: a rerun after an interrupted write needs no --force
    for name, src in vendor.items():
        _put(out, name, src)
    _put(out, "model.glb", model)
    _put(out, "viewer.js", HERE / "viewer.js")
    page = (HERE / "viewer.html").read_text(encoding="utf-8")
    _put(out, "index.html", page.replace("__TITLE__", html.escape(title or glb.name)).encode("utf-8"))
    _write_marker(out, ["index.html", "viewer.js", "model.glb", *vendor])
    logger.info("preview: wrote %s", out / "index.html")
    return out / "index.html"


def _safe_name(name) -> bool:
    """A plain relative POSIX path: no empty, ``.`` or ``..`` part, no backslash or control character."""
    return (isinstance(name, str) and bool(name) and not name.startswith("/")
            and not any(c == "\\" or ord(c) < 32 or ord(c) == 127 for c in name)
            and all(part not in ("", ".", "..") for part in name.split("/")))


def _routes(root: Path) -> dict[str, Path]:
    """URL path (``/index.html``...) -> file, from the marker of the preview folder ``root``."""
    try:
        files = json.loads((root / MARKER).read_text(encoding="utf-8"))["files"]
        if not isinstance(files, list) or not files:
            raise ValueError
    except (OSError, ValueError, KeyError, TypeError):
        raise InputError(f"preview: {root.name} is not a complete rigmix preview folder (no valid {MARKER}); "
                         "write it with `rigmix preview FILE.glb --out FOLDER`") from None
    routes = {}
    for name in files:
        if not _safe_name(name):
            raise InputError(f"preview: {root.name}/{MARKER} lists a file outside the folder; write it again")
        routes["/" + name] = root.joinpath(*name.split("/"))
    if "/index.html" not in routes:
        raise InputError(f"preview: {root.name}/{MARKER} does not list index.html; write the folder again")
    routes["/"] = routes["/index.html"]
    return routes


def _open_regular(path: Path):
    """``path`` opened for reading if it is a regular file reached through no symbolic link, else None."""
    if os.path.realpath(path) != str(path):  # a link anywhere on the way
        return None
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return None
    f = os.fdopen(fd, "rb")
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        f.close()
        return None
    return f


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    routes: dict[str, Path]
    hosts: frozenset

    def handle_error(self, request, client_address):
        # A client that goes away mid-answer (the browser aborts a request) is no error worth a
        # traceback on the terminal; anything else is logged, never printed.
        logger.debug("preview: request from %s failed", client_address[0], exc_info=True)


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = 60  # an idle connection does not hold a thread for ever

    def version_string(self):
        return "rigmix-preview"

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        logger.debug("preview: %s %s", self.address_string(), format % args)

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        super().end_headers()

    def _file(self):
        """``(open file, path)`` for the file the request names, or None once an error has been answered."""
        hosts = self.headers.get_all("Host") or []
        if len(hosts) != 1 or hosts[0].strip().lower() not in self.server.hosts:
            self.send_error(HTTPStatus.FORBIDDEN, "Host not allowed: open the address rigmix printed")
            return None
        try:  # the request target is printable ASCII; what it encodes, UTF-8 without control characters
            if any(not 33 <= ord(c) <= 126 for c in self.path) or _BAD_ESCAPE.search(self.path):
                raise ValueError
            path = unquote(urlsplit(self.path).path, errors="strict")
        except (UnicodeDecodeError, ValueError):
            self.send_error(HTTPStatus.BAD_REQUEST, "Bad encoding in the request path")
            return None
        if not path.startswith("/") or any(ord(c) < 32 or ord(c) == 127 for c in path):
            self.send_error(HTTPStatus.BAD_REQUEST, "Bad request path")
            return None
        target = self.server.routes.get(path)
        f = _open_regular(target) if target is not None else None
        if f is None:
            self.send_error(HTTPStatus.NOT_FOUND, "Not found")
            return None
        return f, target

    def _answer(self, body: bool) -> None:
        found = self._file()
        if found is None:
            return
        f, target = found
        with f:
            size = os.fstat(f.fileno()).st_size
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", CONTENT_TYPES.get(target.suffix.lower(), "application/octet-stream"))
            self.send_header("Content-Length", str(size))
            self.end_headers()
            if body:
                shutil.copyfileobj(f, self.wfile)

    def do_GET(self):  # noqa: N802 - http.server's name
        self._answer(body=True)

    def do_HEAD(self):  # noqa: N802 - http.server's name
        self._answer(body=False)


def serve(directory, *, port=0):
    """Serve a folder written by :func:`write_viewer` over HTTP on 127.0.0.1, in a background thread.

    Only the files its marker lists are served; see the module docstring.

    Parameters
    ----------
    directory : str or Path
    port : int
        0 (default) picks a free port.

    Returns
    -------
    server : http.server.ThreadingHTTPServer
        Call ``server.shutdown()`` to stop it.
    url : str
        ``http://127.0.0.1:PORT/``.

    Raises
    ------
    InputError
        Not a preview folder, a port outside 0-65535, or a port that cannot be used.
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise InputError(f"preview: port {port!r} is not a TCP port (1-65535, or 0 for a free one)")
    root = Path(os.path.realpath(directory))
    routes = _routes(root)
    try:
        server = _Server(("127.0.0.1", port), _Handler)
    except OSError as exc:
        raise InputError(f"preview: cannot listen on 127.0.0.1 port {port} ({exc.strerror or exc}); "
                         "choose another --port, or leave it out to pick a free one") from None
    p = server.server_address[1]
    server.routes = routes
    server.hosts = frozenset([f"{h}:{p}" for h in LOCAL_HOSTS] + (list(LOCAL_HOSTS) if p == 80 else []))
    thread = threading.Thread(target=server.serve_forever, name="rigmix-preview", daemon=True)
    thread.start()
    return server, f"http://127.0.0.1:{p}/"


def preview(glb, out_dir=None, *, port=0, title=None, force=False):
    """Write the viewer for ``glb`` and serve it.

    Parameters
    ----------
    glb : str or Path
    out_dir : str or Path, optional
        Default: ``<glb stem>_preview`` beside the file.
    port, title, force
        As :func:`serve` and :func:`write_viewer`.

    Returns
    -------
    server, url
        As :func:`serve`.
    """
    glb = Path(glb)
    out = Path(out_dir) if out_dir else glb.with_name(glb.stem + "_preview")
    write_viewer(glb, out, title=title, force=force)
    return serve(out, port=port)
