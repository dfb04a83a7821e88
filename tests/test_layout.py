"""The layout the README describes: one package per stage, no private names across modules,
no dict of stage results, dfd standalone, no import cycle between rigmix's modules."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TREES = ("rigmix", "dfd", "tests", "benchmarks")


def _sources():
    for tree in TREES:
        yield from sorted((ROOT / tree).rglob("*.py"))


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _absolute(path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ``ImportFrom`` names, relative imports resolved."""
    if not node.level:
        return node.module or ""
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_imports_a_private_name_from_another():
    offenders = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno}: {a.name}" for a in node.names
                              if _private(a.name)]
    assert not offenders, "private names imported across modules:\n" + "\n".join(offenders)


def test_no_dict_of_stage_results():
    hits = [f"{p.relative_to(ROOT)}:{i + 1}" for p in _sources() if p.name != "test_layout.py"
            for i, line in enumerate(p.read_text().splitlines()) if "stages[" in line or ".stages.get(" in line]
    assert not hits, hits
    assert not (ROOT / "rigmix" / "skin_weights.py").exists()
    assert not (ROOT / "rigmix" / "fusion" / "stage.py").exists()


def test_dfd_never_imports_rigmix():
    for path in sorted((ROOT / "dfd").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            assert not any(n == "rigmix" or n.startswith("rigmix.") for n in names), path


def _module_imports(path: Path) -> set[str]:
    """rigmix modules imported at module level (not inside functions: those run on use)."""
    out = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            mod = _absolute(path, node)
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_no_import_cycle_between_rigmix_modules():
    paths = {_module_name(p): p for p in sorted((ROOT / "rigmix").rglob("*.py"))}

    def targets(m, p):
        """Modules that importing ``p`` runs: each imported module and its packages' ``__init__``
        (importing ``a.b.c`` runs ``a.b`` first), except the packages ``m`` itself lies in."""
        out = set()
        for n in _module_imports(p):
            parts = n.split(".")
            for k in range(1, len(parts) + 1):
                q = ".".join(parts[:k])
                if q in paths and q != m and not m.startswith(q + "."):
                    out.add(q)
        return sorted(out)

    graph = {m: targets(m, p) for m, p in paths.items()}
    # a package's __init__ re-exporting its own modules is not a cycle through them
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in graph[m]:
            if state.get(n) == 1:
                pytest.fail("import cycle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m)


def test_readme_layout_matches_the_tree():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Layout.*?```(.*?)```", text, re.S)
    assert block, "README.md has a ## Layout code block"
    listed = set(re.findall(r"^[ \t]*([\w./]+?)/?[ \t]{2,}", block.group(1), re.M))
    top = {p.name if p.is_dir() else p.name for p in (ROOT / "rigmix").iterdir()
           if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.name != "__init__.py")}
    missing = sorted(t for t in top if t not in listed and t.removesuffix(".py") not in listed)
    stale = sorted(x for x in listed if not (ROOT / "rigmix" / x).exists() and x not in
                   {"rigmix", "dfd", "examples", "tests", "benchmarks"} and not (ROOT / x).exists())
    assert not missing, f"in rigmix/ but not in the README's layout: {missing}"
    assert not stale, f"in the README's layout but not in rigmix/: {stale}"


@pytest.mark.parametrize("module", ["rigmix.config", "rigmix.pipeline", "rigmix.weights", "rigmix.operations",
                                    "rigmix.animation", "rigmix.fusion", "rigmix.io", "rigmix.cli"])
def test_each_stage_package_imports_first(module):
    """Each entry point imports in a fresh interpreter, before anything else has been loaded (a
    cycle shows only in the import order that enters it first)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]


#: Libraries that reading and checking a config, or starting the CLI, must not load: they cost
#: seconds, and a refused config or file is answered before any of them is needed.
KERNELS = ("igl", "gpytoolbox", "torch", "scipy", "skimage", "pxr")


def test_a_config_and_the_cli_load_no_numerical_kernel():
    """``rigmix.pipeline``, ``rigmix.config`` and ``rigmix.cli`` import none of :data:`KERNELS`
    (the fusion, weights and operations packages load their modules on first use,
    :mod:`rigmix.lazy`): a refused config exits in a fraction of a second."""
    import subprocess
    import sys

    code = ("import sys, rigmix.pipeline, rigmix.config, rigmix.cli; "
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({KERNELS!r})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout


def _type_checking_imports(path: Path) -> dict[str, str]:
    """Name -> absolute module of the ``from .x import name`` lines under ``if TYPE_CHECKING:``."""
    out = {}
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for sub in node.body:
                if isinstance(sub, ast.ImportFrom):
                    out.update((a.name, _absolute(path, sub)) for a in sub.names)
    return out


@pytest.mark.parametrize("package", ["rigmix.fusion", "rigmix.weights", "rigmix.operations"])
def test_lazy_package_names_are_their_modules_objects(package):
    """Every public name of a lazily loaded package resolves to the object of the module its
    ``TYPE_CHECKING`` import names (what linters and editors read), is listed by ``dir``, and an
    unknown name raises AttributeError."""
    import importlib

    pkg = importlib.import_module(package)
    declared = _type_checking_imports(Path(pkg.__file__))
    assert declared and set(declared) <= set(pkg.__all__)
    for name in pkg.__all__:
        value = getattr(pkg, name)
        if name in declared:
            assert value is getattr(importlib.import_module(declared[name]), name), name
        assert name in dir(pkg)
    with pytest.raises(AttributeError, match="no_such_name"):
        getattr(pkg, "no_such_name")
