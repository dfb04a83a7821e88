"""The web viewer behind ``rigmix preview OUT.glb`` (:mod:`rigmix.cli`).

:func:`write_viewer` writes a self-contained folder: ``index.html`` (clip selector, play/pause,
timeline, skeleton overlay), ``viewer.js``, the character as ``model.glb`` and the parts of
three.js it imports (copied from the npm package ``three`` in ``node_modules``, resolved from
the import statements, so the page needs no network). :func:`serve` serves a folder on
127.0.0.1 (ES modules do not load from ``file://``); :func:`preview` does both.

The page exposes its state as ``window.rigmixViewer`` (``ready``, ``clips``, ``current``,
``time``, ``duration``, ``select(name)``, ``setTime(t)``, ``play()``, ``pause()``) and mirrors
the current clip and time in ``document.body.dataset`` for scripts and tests.
"""

from __future__ import annotations

import functools
import html
import logging
import os
import re
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from ..errors import InputError

__all__ = ["find_three", "relative_imports", "write_viewer", "serve", "preview"]

logger = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
#: three.js addons the viewer imports (their own relative imports are followed).
ADDONS = ("loaders/GLTFLoader.js", "controls/OrbitControls.js")
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


def _copy_module_closure(src_root: Path, rel: str, dst_root: Path, seen: set) -> None:
    """Copy ``src_root/rel`` and, recursively, the files it imports by relative path."""
    rel = os.path.normpath(rel)
    if rel in seen:
        return
    seen.add(rel)
    src = src_root / rel
    if not src.is_file():
        raise InputError(f"preview: three.js file {src} is missing (reinstall with `npm ci`)")
    dst = dst_root / rel
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    for dep in relative_imports(src.read_text(encoding="utf-8")):
        _copy_module_closure(src_root, os.path.join(os.path.dirname(rel), dep), dst_root, seen)


def write_viewer(glb, out_dir, *, title=None, three_dir=None) -> Path:
    """Write the viewer folder for one glTF binary.

    Parameters
    ----------
    glb : str or Path
        The character (``.glb``; a ``.gltf`` with embedded buffers also loads).
    out_dir : str or Path
        Created if needed; ``index.html``, ``viewer.js``, ``model.glb`` and ``vendor/`` are
        (over)written there.
    title : str, optional
        Page title (default: the file name).
    three_dir : str or Path, optional
        The npm ``three`` package (default: :func:`find_three`).

    Returns
    -------
    Path
        ``out_dir / "index.html"``.
    """
    glb = Path(glb)
    if not glb.is_file():
        raise InputError(f"preview: {glb} does not exist")
    if glb.suffix.lower() not in (".glb", ".gltf"):
        raise InputError(f"preview: {glb.name}: expected a .glb (or self-contained .gltf) file")
    three = Path(three_dir) if three_dir else find_three()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    vendor = out / "vendor"
    seen: set = set()
    _copy_module_closure(three / "build", "three.module.js", vendor, seen)
    for addon in ADDONS:
        _copy_module_closure(three / "examples" / "jsm", addon, vendor / "addons", set())
    shutil.copyfile(glb, out / "model.glb")
    shutil.copyfile(HERE / "viewer.js", out / "viewer.js")
    page = (HERE / "viewer.html").read_text(encoding="utf-8")
    page = page.replace("__TITLE__", html.escape(title or glb.name))
    (out / "index.html").write_text(page, encoding="utf-8")
    logger.info("preview: wrote %s", out / "index.html")
    return out / "index.html"


class _Handler(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map,
                      ".js": "text/javascript", ".mjs": "text/javascript",
                      ".glb": "model/gltf-binary", ".gltf": "model/gltf+json"}

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        logger.debug("preview: %s %s", self.address_string(), format % args)

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()


def serve(directory, *, host="127.0.0.1", port=0):
    """Serve ``directory`` over HTTP in a background thread.

    Parameters
    ----------
    directory : str or Path
    host : str
        ``127.0.0.1`` by default: the viewer is for this machine only.
    port : int
        0 picks a free port.

    Returns
    -------
    server : http.server.ThreadingHTTPServer
        Call ``server.shutdown()`` to stop it.
    url : str
        ``http://HOST:PORT/``.
    """
    handler = functools.partial(_Handler, directory=str(Path(directory).resolve()))
    server = ThreadingHTTPServer((host, int(port)), handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="rigmix-preview", daemon=True)
    thread.start()
    h, p = server.server_address[:2]
    return server, f"http://{h}:{p}/"


def preview(glb, out_dir=None, *, host="127.0.0.1", port=0, title=None):
    """Write the viewer for ``glb`` and serve it.

    Parameters
    ----------
    glb : str or Path
    out_dir : str or Path, optional
        Default: ``<glb stem>_preview`` beside the file.

    Returns
    -------
    server, url
        As :func:`serve`.
    """
    glb = Path(glb)
    out = Path(out_dir) if out_dir else glb.with_name(glb.stem + "_preview")
    write_viewer(glb, out, title=title)
    return serve(out, host=host, port=port)
