"""Fitting: :mod:`~emccdcal.fit.engine` (the one likelihood engine),
:mod:`~emccdcal.fit.layouts` (the methods as parameter layouts), :mod:`~emccdcal.fit.mv`
(mean-variance methods), :mod:`~emccdcal.fit.gof` (goodness of fit) and
:mod:`~emccdcal.fit.posterior` (MCMC of single pixels)."""
