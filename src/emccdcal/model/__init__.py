"""The camera's noise model: :mod:`~emccdcal.model.noise` (the exact pmf of the counts,
gamma EM register), :mod:`~emccdcal.model.cascade` (the exact Bernoulli-cascade
register) and :mod:`~emccdcal.model.psf` (the pixel-integrated Gaussian spot)."""
