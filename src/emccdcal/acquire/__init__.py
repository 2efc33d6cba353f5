"""Before the files: what to record (:mod:`.plan`) and recording it through
Micro-Manager."""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
