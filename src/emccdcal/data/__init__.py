"""From files to acquisitions: :mod:`~emccdcal.data.manifest` (the manifest, checked),
:mod:`~emccdcal.data.stacks` (readers), :mod:`~emccdcal.data.dark` (offset and
read-noise maps), :mod:`~emccdcal.data.stats` (per-pixel histograms) and
:mod:`~emccdcal.data.quality` (data-quality checks)."""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
