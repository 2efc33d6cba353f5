"""Synthetic EMCCD acquisitions with known truth.

- :mod:`~emccdcal.simulate.camera`: the camera (:class:`Camera`) and the in-memory core,
  :func:`simulate_frames`, with the generative model;
- :mod:`~emccdcal.simulate.series`: gain and intensity series written as a calibration
  session writes them (stacks, darks, maps, manifest, truth);
- :mod:`~emccdcal.simulate.beads`: bead movies for the bead validation.
"""
