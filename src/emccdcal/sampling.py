"""The posterior sampler as a user calls it (``emccdcal.sample_posterior``).

φ is read as :func:`emccdcal.calibrate` reads it (a number, a map or a chained result with
its standard error: :func:`emccdcal.given_phi.e_per_adu_inputs`, which reads results and
so lives outside ``fit/``), then the fit's door checks it and the sampler of
:mod:`emccdcal.fit.posterior` runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .data.manifest import Manifest, read_manifest
from .fit import posterior
from .given_phi import e_per_adu_inputs

if TYPE_CHECKING:
    import xarray

__all__ = ["sample_posterior"]


def sample_posterior(
    manifest,
    method,
    pixels,
    *,
    e_per_adu=None,
    accept_mismatch=(),
    accept_phi=False,
    n_walkers=None,
    n_steps=None,
    seed=0,
    max_steps=posterior.DEFAULT_MAX_STEPS,
    min_ess=posterior.DEFAULT_MIN_ESS,
    prior="log-uniform",
    options=None,
    out=None,
    progress=True,
    em_model=None,
    stages=None,
    device=None,
) -> xarray.Dataset:
    """MCMC posterior of a method's free parameters for single pixels.

    Parameters
    ----------
    manifest : str, Path or :class:`emccdcal.Manifest`
        The TOML manifest (``docs/manifest.md``).
    method : str
        A likelihood method (:data:`emccdcal.fit.layouts.LIKELIHOOD_METHODS`): ``is-adu``,
        ``is-gain``, ``gs``, ``gs-no1x``, ``gs-hierarchical``.
    pixels : sequence of (int, int) or str
        Pixels as (row, col), or ``"ROW,COL"`` strings; duplicates are sampled once.
    e_per_adu : float, ndarray (rows, cols), path, Dataset or Calibration, optional
        φ (e⁻/ADU) overriding the manifest's, for the methods that hold it fixed: a
        number, a map, or an ``is-adu``/``mv-adu`` result, as :func:`emccdcal.calibrate`
        takes it; a result's standard error per pixel goes into the draws (each moved as
        a draw of φ from its error moves the estimate), as into calibrate's SEs. Either
        way a φ the 1× acquisition's photon transfer contradicts is refused.
    accept_mismatch : iterable of str
        Identity fields in which the frames may differ from the result φ is taken from
        (:func:`emccdcal.calibrate`'s).
    accept_phi : bool
        Use a given φ the data contradict all the same.
    n_walkers : int, optional
        Walkers of the ensemble; default ``max(32, 4 F)`` for F free parameters
        (at least ``2 F``).
    n_steps : int, optional
        Steps per walker of the first run (default 1500, at most ``max_steps``); the chain
        is then extended, as the autocorrelation time asks, up to ``max_steps``.
    seed : int
        Seed of every random draw (start ball and sampler); pixel (r, c) uses the stream
        ``SeedSequence([seed, r, c])``, so its chain does not depend on the other pixels.
    max_steps : int
        Steps per walker beyond which an unconverged chain is refused.
    min_ess : int
        Effective sample size required of every parameter.
    prior : {"log-uniform", "uniform"}
        Flat in the log-parameters (default) or in the physical parameters, inside the
        method's bounds (see the module docstring).
    options : dict, optional
        Method options, as :func:`emccdcal.calibrate`'s.
    out : str or Path, optional
        Directory to write ``posterior.nc`` and ``posterior.json`` into (corner plots:
        :func:`emccdcal.report.corner.write_corner_figures`).
    progress : bool
        emcee's progress bars (in a notebook or on a terminal; none in a pipe).
    em_model, stages : optional
        The EM register's model (:func:`emccdcal.calibrate`); default the manifest's,
        else the exact cascade (stages from the manifest, the camera's model or 536;
        ``"auto"`` is :func:`emccdcal.calibrate`'s only).
    device : {"cpu", "cuda", "jax", "array-api-strict"}, optional
        Where the likelihood is computed, as :func:`emccdcal.calibrate`'s (the walkers'
        evaluations are one batch each step).

    Returns
    -------
    xarray.Dataset
        ``samples`` (pixel, draw, parameter) in physical units (the ``units`` coordinate:
        e⁻/ADU, e⁻ or 1), padded with NaN beyond ``n_draws``; ``log_posterior``
        (pixel, draw), nats; per (pixel, parameter) ``median``, ``sd``, ``q16``, ``q84``,
        ``q025``, ``q975``, ``ess``, ``autocorr_time`` (steps), ``mle`` and ``mle_se``
        (the engine's estimate and delta-method standard error); per pixel
        ``acceptance``, ``n_steps``, ``burn``, ``thin``, ``n_draws``, ``n_walkers``,
        ``mle_converged`` and ``seconds`` (wall time: reading, fit and sampling).
        ``attrs["seconds"]`` is the wall time.

    Raises
    ------
    ValueError
        A pixel outside the array or malformed, bad options, too few frames.
    emccdcal.MethodError
        A method the manifest cannot support.
    NotConvergedError
        A chain that did not converge within ``max_steps``.
    emccdcal.errors.InputError
        A given φ the data contradict, or a result of another camera or read-out state.

    Examples
    --------
    >>> ds = sample_posterior("adu/manifest.toml", "is-adu", [(1, 1)])   # doctest: +SKIP
    >>> float(ds.median.sel(parameter="e_per_adu")[0])                    # doctest: +SKIP
    3.94
    """
    if not isinstance(manifest, Manifest):
        manifest = read_manifest(manifest)
    phi_map, phi_se, phi_source = e_per_adu_inputs(manifest, e_per_adu, accept_mismatch)
    return posterior.sample_pixels(
        manifest,
        method,
        pixels,
        e_per_adu=phi_map,
        e_per_adu_se=phi_se,
        e_per_adu_source=phi_source,
        accept_phi=accept_phi,
        n_walkers=n_walkers,
        n_steps=n_steps,
        seed=seed,
        max_steps=max_steps,
        min_ess=min_ess,
        prior=prior,
        options=options,
        out=out,
        progress=progress,
        em_model=em_model,
        stages=stages,
        device=device,
    )
