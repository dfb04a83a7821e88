"""Package attributes imported on first use (PEP 562), so that importing a package for one light
name does not load its heavy modules.

``rigmix.config`` needs only the option dataclasses of :mod:`rigmix.fusion` and
:mod:`rigmix.weights`; the other modules of those packages load libigl, gpytoolbox and scipy's
sparse and spatial modules, over a second, which a ``rigmix inspect`` or a refused ``rigmix
compose`` never needs. The packages list their public names, each with its module, and resolve
one the first time it is asked for."""

from __future__ import annotations

import importlib
from typing import Callable, Mapping

__all__ = ["lazy_exports"]


def lazy_exports(package: str, modules: Mapping[str, str]) -> tuple[Callable[[str], object], Callable[[], list]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    modules : mapping of str to str
        Public name -> the submodule defining it, relative to ``package`` (``"fuse"``).

    Returns
    -------
    (__getattr__, __dir__)
        ``__getattr__(name)`` imports the submodule, caches the attribute in the package's
        namespace (later lookups do not come back here) and returns it; unknown names raise
        ``AttributeError`` as usual.
    """
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        module = modules.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        namespace[name] = value
        return value

    def __dir__() -> list:
        return sorted(set(namespace) | set(modules))

    return __getattr__, __dir__
