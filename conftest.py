"""Collection of the package's own modules (``--doctest-modules``): a module that needs an
optional extra is left out where that extra is not installed, so that ``make test`` passes
on the bare ``.[test]`` install a fresh clone gets (its tests in tests/ skip alike)."""

import importlib.util

#: Package modules importing an optional extra at module level, with what they import.
_OPTIONAL = {
    "src/emccdcal/napari/_widgets.py": ("magicgui", "qtpy"),
    "src/emccdcal/acquire/devices.py": ("pymmcore_plus",),
}


def _missing(modules) -> bool:
    return any(importlib.util.find_spec(m) is None for m in modules)


collect_ignore = [path for path, needs in _OPTIONAL.items() if _missing(needs)]
