"""Fitting: :mod:`~emccdcal.fit.series` (the one door to the likelihood: a series of
acquisitions, each a model half and a data half), :mod:`~emccdcal.fit.engine` (the one
likelihood engine behind it), :mod:`~emccdcal.fit.layouts` (the methods as parameter
layouts), :mod:`~emccdcal.fit.mv` (mean-variance methods), :mod:`~emccdcal.fit.gof`
(goodness of fit) and :mod:`~emccdcal.fit.posterior` (MCMC of single pixels)."""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
