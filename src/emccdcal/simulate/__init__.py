"""Synthetic EMCCD acquisitions with known truth.

- :mod:`~emccdcal.simulate.camera`: the camera (:class:`Camera`) and the in-memory core,
  :func:`simulate_frames`, with the generative model;
- :mod:`~emccdcal.simulate.series`: gain and intensity series written as a calibration
  session writes them (stacks, darks, maps, manifest, truth);
- :mod:`~emccdcal.simulate.beads`: bead movies for the bead validation.
"""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
