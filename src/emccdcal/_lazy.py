"""Submodules reached as attributes and imported on first use (as scipy's subpackages
load theirs): ``import emccdcal; emccdcal.model.noise.pmf(...)`` works in a fresh
interpreter, and importing a package imports none of its modules' numerics."""

from __future__ import annotations

import importlib
import pkgutil


def submodules(package: str, path) -> tuple:
    """``(__getattr__, __dir__)`` for the package ``package`` whose folder is ``path``
    (its ``__path__``): each public module or subpackage in it is an attribute, imported
    when first asked for.

    Examples
    --------
    >>> import emccdcal.model
    >>> emccdcal.model.psf.__name__
    'emccdcal.model.psf'
    """
    names = frozenset(m.name for m in pkgutil.iter_modules(path) if not m.name.startswith("_"))

    def __getattr__(name: str):
        if name in names:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        module = importlib.import_module(package)
        return sorted(names | set(getattr(module, "__all__", ())))

    return __getattr__, __dir__
