"""Posterior sampling of single pixels (``emccdcal posterior``): MCMC with honest diagnostics.

For each requested pixel the method's acquisitions are read for that pixel alone, the
maximum-likelihood fit of the method's likelihood
(:class:`emccdcal.fit.series.SeriesLikelihood`) gives a start, and an affine-invariant
ensemble sampler (:class:`emcee.EnsembleSampler`) explores its free parameters.

Prior
-----
By default (``prior="log-uniform"``) the prior is flat in the *log* of every free
parameter (ln φ, ln E, ln g: the space the engine works in) inside the method's bounds
(:data:`emccdcal.fit.layouts.BOUNDS`) and zero outside: p(θ) ∝ 1/θ in each physical
parameter. ``prior="uniform"`` is flat in the physical parameters themselves (the
authors' choice, docs/posterior.md) inside the same bounds: it adds the Jacobian Σ x to the log
density. With thousands of frames per acquisition the two give the same posterior to far
below its width. A layout's own prior (the hierarchical gain series' penalty) is part of
the engine's objective and is included in both cases.

Convergence
-----------
The chain is extended until, after discarding a burn-in of 5 τ_max steps, the kept
chain is at least 50 τ_max long, the effective sample size ``n_walkers × kept / τ`` is at
least ``min_ess`` for every parameter, and the mean acceptance fraction lies in
[0.15, 0.8] (τ: the integrated autocorrelation time of each parameter, in steps,
:func:`emcee.autocorr.integrated_time`). If ``max_steps`` is reached first the pixel is
refused with :class:`NotConvergedError`, which says what to change: an unconverged chain
is never returned as a result.

Outputs (:func:`save`): ``OUT/posterior.nc`` (the samples in physical units),
``OUT/posterior.json`` (summaries and diagnostics per pixel and parameter, with the
engine's estimate and standard error for comparison); the command line adds
``OUT/posterior_<row>_<col>.png``, a corner plot (:mod:`emccdcal.report.corner`).
"""

from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import _xp, defaults
from .._output import atomic_write, atomic_write_text, write_netcdf
from .._util import e_per_adu_map, emcee_progress, finite_or_none, parse_pixel
from ..data import stats
from ..data.manifest import Manifest, read_manifest
from ..errors import DataQualityWarning, FitWarning, MethodError, NotConvergedError, OptionError
from . import layouts
from .series import SeriesLikelihood, acquisition_models, specify

if TYPE_CHECKING:
    import xarray

__all__ = [
    "NotConvergedError",
    "PRIORS",
    "sample_pixels",
    "summary",
    "save",
    "POSTERIOR_FILE",
    "SUMMARY_FILE",
]

POSTERIOR_FILE = "posterior.nc"
SUMMARY_FILE = "posterior.json"
PRIORS = defaults.PRIORS

#: Convergence criteria (see the module docstring).
MIN_LENGTH_TAUS = 50.0
BURN_TAUS = 5.0
ACCEPTANCE = (0.15, 0.8)
DEFAULT_MIN_ESS = 1000
DEFAULT_MAX_STEPS = defaults.DEFAULT_MAX_STEPS
DEFAULT_FIRST_STEPS = defaults.DEFAULT_FIRST_STEPS
#: Walkers start in a Gaussian ball of this fraction of the Laplace (inverse observed
#: information) covariance's standard deviations around the maximum-likelihood estimate.
INIT_SCALE = 0.1

SAMPLER = "emcee.EnsembleSampler, moves: 0.8 DEMove + 0.2 DESnookerMove"

_UNITS = {"e_per_adu": "e-/ADU", "photoelectrons": "e-", "em_gain": "1"}
_QUANTILES = {"q025": 0.025, "q16": 0.16, "median": 0.5, "q84": 0.84, "q975": 0.975}


# --------------------------------------------------------------------------------------
# Input
# --------------------------------------------------------------------------------------
def _check_pixels(pixels, shape):
    out = []
    if isinstance(pixels, tuple) and len(pixels) == 2 and all(np.ndim(p) == 0 for p in pixels):
        pixels = [pixels]  # a single (row, col)
    for p in pixels:
        if isinstance(p, str):
            p = parse_pixel(p)
        if len(p) != 2 or not all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in p
        ):
            raise OptionError(f"malformed pixel {p!r}: expected (row, col) integers")
        row, col = int(p[0]), int(p[1])
        if not (0 <= row < shape[0] and 0 <= col < shape[1]):
            raise OptionError(
                f"pixel ({row}, {col}) is outside the array of shape {shape[0]}x{shape[1]} "
                f"(rows x cols; rows 0..{shape[0] - 1}, cols 0..{shape[1] - 1})"
            )
        if (row, col) not in out:
            out.append((row, col))
    if not out:
        raise OptionError("no pixel given: pass at least one (row, col)")
    return out


def _pixel_series(manifest, used, method, row, col, phi_map, options, em_model):
    """The method's likelihood of one pixel (the calibrate pipeline, P = 1)."""
    hists, models = [], []
    for acq in used:
        frames = acq.frames()[:, row : row + 1, col : col + 1]
        h = stats.histograms(frames, adc_max=manifest.adc_max)
        if int(h.n_saturated.sum()):
            warnings.warn(
                f"{acq.frames_path.name}: {int(h.n_saturated.sum())} frame values at the ADC "
                f"maximum ({manifest.adc_max} ADU) at pixel ({row}, {col}) were excluded",
                stacklevel=3,
                category=DataQualityWarning,
            )
        if np.any(h.n < 2):
            raise OptionError(
                f"{acq.frames_path}: fewer than 2 usable frames at pixel ({row}, {col})"
            )
        if not acq.read_noise[row, col] > 0:  # a dark that never changes: calibrate's too
            raise OptionError(
                f"{acq.read_noise_source}: read noise 0 at pixel ({row}, {col}) (its dark "
                "counts never change: a stuck pixel, which calibrate leaves out)"
            )
        hists.append(h)
        models += acquisition_models(
            [acq.em_gain_setpoint],
            [acq.offset[row, col : col + 1]],
            [acq.read_noise[row, col : col + 1]],
            em_model,
        )
    phi = None if phi_map is None else np.array([phi_map[row, col]])
    return SeriesLikelihood(method, models, hists, e_per_adu=phi, options=options)


def _physical_names(lik, used, method):
    """Physical names and units of the free parameters (all are exp(x))."""
    names, units = [], []
    for p in lik.parameters:
        if p.acquisition is None:
            label = p.quantity
        else:
            acq = used[p.acquisition]
            if method.startswith("is-"):
                tag = acq.level if acq.level is not None else acq.name
            else:
                tag = f"{acq.em_gain_setpoint:g}x"
            label = f"{p.quantity}[{tag}]"
        names.append(label)
        units.append(_UNITS[p.quantity])
    return names, units


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------
class _LogPosterior:
    """Vectorised log posterior of one pixel: rows of x (n, F) → (n,), nats."""

    def __init__(self, likelihood, prior):
        self.likelihood, self.prior = likelihood, prior
        self.lower, self.upper = likelihood.bounds
        self._cache = {}
        self.calls = 0

    def _replicated(self, n):
        if n not in self._cache:
            self._cache[n] = self.likelihood.take(np.zeros(n, dtype=int))
        return self._cache[n]

    def __call__(self, x):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        self.calls += 1
        inside = np.all((x >= self.lower) & (x <= self.upper), axis=1)
        inside &= np.all(np.isfinite(x), axis=1)
        xc = np.clip(np.nan_to_num(x), self.lower, self.upper)
        with np.errstate(all="ignore"):
            obj = self._replicated(x.shape[0]).objective(xc)
        if self.prior == "uniform":
            obj = obj + x.sum(axis=1)  # flat in θ = exp(x): p(x) ∝ Π exp(x_f)
        return np.where(inside & np.isfinite(obj), obj, -np.inf)


def _diagnose(sampler, min_ess):
    """Burn-in, autocorrelation times, ESS and what is missing (empty list: converged)."""
    total = sampler.iteration
    W = sampler.nwalkers
    chain = sampler.get_chain()
    tau0 = _integrated_time(chain)
    burn = int(math.ceil(BURN_TAUS * np.nanmax(tau0))) if np.all(np.isfinite(tau0)) else total // 2
    burn = min(burn, total // 2)
    kept = total - burn
    tau = _integrated_time(chain[burn:])
    ess = W * kept / tau
    acc = float(np.mean(sampler.acceptance_fraction))
    problems = []
    if not np.all(np.isfinite(tau)):
        problems.append("the autocorrelation time could not be estimated")
    else:
        if kept < MIN_LENGTH_TAUS * tau.max():
            problems.append(
                f"kept chain of {kept} steps is shorter than {MIN_LENGTH_TAUS:g} autocorrelation "
                f"times ({MIN_LENGTH_TAUS * tau.max():.0f} steps)"
            )
        if np.any(ess < min_ess):
            problems.append(f"effective sample size {ess.min():.0f} < {min_ess}")
    if not (ACCEPTANCE[0] <= acc <= ACCEPTANCE[1]):
        problems.append(f"acceptance fraction {acc:.3f} outside [{ACCEPTANCE[0]}, {ACCEPTANCE[1]}]")
    return dict(
        total=total, burn=burn, kept=kept, tau=tau, ess=ess, acceptance=acc, problems=problems
    )


def _integrated_time(chain):
    """Integrated autocorrelation time (steps) of a chain (steps, walkers, F), no length check."""
    import emcee

    if chain.shape[0] < 4:
        return np.full(chain.shape[2], np.nan)
    return emcee.autocorr.integrated_time(chain, tol=0, quiet=True)


def _needed_steps(d, n_walkers, min_ess):
    """Total steps the current τ estimate asks for (with a 20 % margin)."""
    tau = d["tau"]
    if not np.all(np.isfinite(tau)):
        return 2 * d["total"]
    kept = max(MIN_LENGTH_TAUS * tau.max(), min_ess * tau.max() / n_walkers)
    return int(math.ceil(1.2 * (kept + BURN_TAUS * tau.max())))


def _moves():
    """Differential-evolution moves (80 %) with snooker updates (20 %), ter Braak & Vrugt
    (2008): on the strongly correlated φ–E posterior of ``is-adu`` they halve the
    autocorrelation time of emcee's default stretch move (25 against 50 steps)."""
    import emcee

    return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]


def _sample_pixel(
    logp, x_hat, cov, n_walkers, first_steps, max_steps, min_ess, rng, progress, where
):
    import emcee

    F = x_hat.size
    sd = np.sqrt(np.diag(cov)) if np.all(np.isfinite(cov)) else None
    if sd is None or not np.all(sd > 0):
        warnings.warn(
            f"{where}: the observed information is not positive definite at the "
            "maximum; walkers start in a tiny isotropic ball",
            stacklevel=3,
            category=FitWarning,
        )
        start = x_hat + 1e-4 * rng.standard_normal((n_walkers, F))
    else:
        # A ball shaped like the Laplace approximation, shrunk by INIT_SCALE.
        L = np.linalg.cholesky(cov + 1e-300 * np.eye(F))
        start = x_hat + INIT_SCALE * rng.standard_normal((n_walkers, F)) @ L.T
    start = np.clip(start, logp.lower, logp.upper)
    sampler = emcee.EnsembleSampler(n_walkers, F, logp, vectorize=True, moves=_moves())
    sampler.random_state = np.random.RandomState(rng.integers(2**32 - 1)).get_state()
    steps = min(first_steps, max_steps)
    sampler.run_mcmc(start, steps, **emcee_progress(progress))
    while True:
        d = _diagnose(sampler, min_ess)
        if not d["problems"]:
            return sampler, d
        if sampler.iteration >= max_steps:
            break
        target = min(
            max_steps, max(_needed_steps(d, n_walkers, min_ess), int(1.5 * sampler.iteration))
        )
        sampler.run_mcmc(None, target - sampler.iteration, **emcee_progress(progress))
    acc_bad = any(p.startswith("acceptance") for p in d["problems"])
    advice = (
        "the posterior may be multimodal or pressed against a bound; check the maximum-"
        "likelihood fit, or try more walkers (n_walkers / --walkers)"
        if acc_bad
        else f"raise max_steps (--max-steps, now {max_steps}) to about "
        f"{_needed_steps(d, n_walkers, min_ess)} or use more walkers (n_walkers / --walkers, "
        f"now {n_walkers})"
    )
    raise NotConvergedError(
        f"{where}: chain not converged after {sampler.iteration} steps x {n_walkers} walkers "
        f"({'; '.join(d['problems'])}): {advice}"
    )


def sample_pixels(
    manifest,
    method,
    pixels,
    *,
    e_per_adu=None,
    e_per_adu_se=None,
    e_per_adu_source=None,
    accept_phi=False,
    n_walkers=None,
    n_steps=None,
    seed=0,
    max_steps=DEFAULT_MAX_STEPS,
    min_ess=DEFAULT_MIN_ESS,
    prior="log-uniform",
    options=None,
    out=None,
    progress=True,
    em_model=None,
    stages=None,
    device=None,
) -> xarray.Dataset:
    """MCMC posterior of a method's free parameters for single pixels, φ given as arrays:
    :func:`emccdcal.sample_posterior` (which reads a chained φ's result first) says what
    every parameter means.

    Parameters
    ----------
    e_per_adu, e_per_adu_se : ndarray (rows, cols), optional
        A φ the method holds fixed (e⁻/ADU; None: the manifest's) and its standard error
        (a chained result's, or None): with an SE, each draw is moved as a draw of ln φ
        from its error moves the estimate (the linear response calibrate's standard
        errors use), so the samples carry φ's uncertainty as calibrate's SEs do.
    e_per_adu_source : emccdcal.data.manifest.Source, optional
        Where that φ came from (for messages and the result's attributes).
    accept_phi : bool
        Use a given φ that the 1× acquisition's photon transfer contradicts.
    """
    t0 = time.perf_counter()
    _check_sampling(prior, method, max_steps, min_ess, n_steps)
    _xp.resolve(device)  # an unknown or missing device: one line before any work
    if not isinstance(manifest, Manifest):
        manifest = read_manifest(manifest)
    pixels = _check_pixels(pixels, manifest.shape)
    if e_per_adu is None:
        e_per_adu, e_per_adu_se = manifest.e_per_adu, None
    phi_map = e_per_adu_map(e_per_adu, manifest.shape)
    spec = specify(
        manifest,
        method,
        e_per_adu=phi_map,
        e_per_adu_se=e_per_adu_se,
        e_per_adu_source=e_per_adu_source,
        accept_phi=accept_phi,
        em_model=em_model,
        stages=stages,
        options=options,
    )
    model, stages_source, used = spec.em_model, spec.stages_source, list(spec.acquisitions)
    options = spec.options

    per_pixel = []
    names = units = None
    for row, col in pixels:
        t_pixel = time.perf_counter()
        lik = _pixel_series(manifest, used, method, row, col, phi_map, options, model)
        if names is None:
            names, units = _physical_names(lik, used, method)
        phi_se = None if e_per_adu_se is None else e_per_adu_se[row, col]
        sampling = (n_walkers, n_steps, int(max_steps), int(min_ess), prior, int(seed), progress)
        per_pixel.append(_sample_one(lik, method, row, col, sampling, device, phi_se))
        per_pixel[-1]["seconds"] = time.perf_counter() - t_pixel

    ds = _posterior_dataset(
        per_pixel,
        names,
        units,
        {
            "method": method,
            "prior": prior,
            "seed": int(seed),
            "min_ess": int(min_ess),
            "max_steps": int(max_steps),
            "manifest_hash": manifest.content_hash,
            "manifest_path": str(manifest.path),
            "sampler": SAMPLER,
            "prior_description": _prior_text(prior),
        },
    )
    ds.attrs["seconds"] = time.perf_counter() - t0
    ds.attrs.update(model.attrs, device=device or "cpu")
    if spec.e_per_adu is not None:
        ds.attrs["e_per_adu_source"] = str(e_per_adu_source or "manifest")
        ds.attrs["e_per_adu_se_included"] = int(e_per_adu_se is not None)
    if stages_source:
        ds.attrs["register_stages_source"] = stages_source
    if out is not None:
        save(ds, out)
    return ds


def _sample_one(lik, method, row, col, sampling, device, phi_se):
    """One pixel's maximum-likelihood start, converged chain and summaries (a dict for
    :func:`_posterior_dataset`); ``sampling`` is (n_walkers, n_steps, max_steps,
    min_ess, prior, seed, progress)."""
    n_walkers, n_steps, max_steps, min_ess, prior, seed, progress = sampling
    where = f"{method} pixel ({row}, {col})"
    F = len(lik.parameters)
    W = int(n_walkers) if n_walkers is not None else max(32, 4 * F)
    if W < 2 * F or W % 2:
        raise OptionError(
            f"n_walkers must be even and at least {2 * F} (twice the {F} free "
            f"parameters of {method}), got {n_walkers}"
        )
    with _xp.computing_on(device):
        fit = lik.fit()
    if not fit.converged[0]:
        warnings.warn(
            f"{where}: the maximum-likelihood fit did not converge; "
            "sampling starts from its last point",
            stacklevel=3,
            category=FitWarning,
        )
    x_hat, cov = fit.x[0], fit.cov[0]
    rng = np.random.default_rng(np.random.SeedSequence([seed, row, col]))
    logp = _LogPosterior(lik, prior)
    first = DEFAULT_FIRST_STEPS if n_steps is None else int(n_steps)
    with _xp.computing_on(device):
        sampler, d = _sample_pixel(
            logp, x_hat, cov, W, first, max_steps, min_ess, rng, progress, where
        )
    thin = max(1, int(np.floor(d["tau"].min() / 2)))
    chain = sampler.get_chain(discard=d["burn"], thin=thin, flat=True)
    lp = sampler.get_log_prob(discard=d["burn"], thin=thin, flat=True)
    if phi_se is not None and np.isfinite(phi_se):
        chain, cov = _with_phi_error(lik, fit, chain, cov, phi_se, rng)
    mle_se = np.exp(x_hat) * np.sqrt(np.where(np.isfinite(np.diag(cov)), np.diag(cov), np.nan))
    return dict(
        row=row,
        col=col,
        samples=np.exp(chain),
        log_posterior=lp,
        diag=d,
        thin=thin,
        n_walkers=W,
        mle=np.exp(x_hat),
        mle_se=mle_se,
        mle_converged=bool(fit.converged[0]),
    )


def _with_phi_error(lik, fit, chain, cov, phi_se, rng):
    """The draws (ln parameters) and the estimate's covariance with a given φ's error:
    each draw moved by ``J·δ``, δ ~ N(0, (SE/φ)²) a draw of ln φ and J = d x̂/d ln φ
    (:func:`emccdcal.fit.profile.e_per_adu_sensitivity`), and the covariance as
    calibrate's (:func:`emccdcal.fit.profile.with_phi_error`)."""
    from . import profile

    sens = profile.e_per_adu_sensitivity(lik.layout, lik.blocks, fit.x)  # (1, F)
    rel = float(phi_se) / float(lik.e_per_adu[0])
    shifted = chain + rng.normal(0.0, rel, size=chain.shape[0])[:, None] * sens
    return shifted, profile.with_phi_error(cov[None], sens, [rel])[0]


def _check_sampling(prior, method, max_steps, min_ess, n_steps) -> None:
    """One line for a sampling option :func:`sample_pixels` cannot take."""
    if prior not in PRIORS:
        raise OptionError(f"unknown prior {prior!r}; choose one of {', '.join(PRIORS)}")
    if method not in layouts.LIKELIHOOD_METHODS:
        raise MethodError(
            f"posterior sampling needs a likelihood method ({', '.join(layouts.LIKELIHOOD_METHODS)})"
            f"; {method!r} is not one"
            + (
                " (the mean-variance methods have no likelihood)"
                if str(method).startswith("mv-")
                else ""
            )
        )
    for name, v, lo in (("max_steps", max_steps, 10), ("min_ess", min_ess, 1)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise OptionError(f"{name} must be an integer >= {lo}, got {v!r}")
    if n_steps is not None and (
        isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 10
    ):
        raise OptionError(f"n_steps must be an integer >= 10, got {n_steps!r}")


def _posterior_dataset(per_pixel, names, units, attrs) -> xarray.Dataset:
    """The labelled result of :func:`sample_pixels` from each pixel's draws and
    diagnostics (the pixels' chains padded with NaN to the longest)."""
    import xarray as xr

    n_draw = max(p["samples"].shape[0] for p in per_pixel)
    Pn, F = len(per_pixel), len(names)
    samples = np.full((Pn, n_draw, F), np.nan)
    logpost = np.full((Pn, n_draw), np.nan)
    for i, p in enumerate(per_pixel):
        samples[i, : p["samples"].shape[0]] = p["samples"]
        logpost[i, : p["log_posterior"].shape[0]] = p["log_posterior"]
    qs = {k: np.nanquantile(samples, q, axis=1) for k, q in _QUANTILES.items()}
    pdim, pf = ("pixel",), ("pixel", "parameter")
    col = lambda key: np.array([p[key] for p in per_pixel])  # noqa: E731
    dcol = lambda key: np.array([p["diag"][key] for p in per_pixel])  # noqa: E731
    return xr.Dataset(
        {
            "samples": (
                ("pixel", "draw", "parameter"),
                samples,
                {
                    "long_name": "posterior draws (burn-in discarded, thinned)",
                    "units": "per parameter: see the 'units' coordinate "
                    "(e_per_adu e-/ADU, photoelectrons e-, em_gain 1)",
                },
            ),
            "log_posterior": (("pixel", "draw"), logpost, {"units": "nats"}),
            **{k: (pf, v, {"long_name": f"posterior {k}"}) for k, v in qs.items()},
            "sd": (pf, np.nanstd(samples, axis=1, ddof=1), {"long_name": "posterior SD"}),
            "ess": (pf, dcol("ess"), {"long_name": "effective sample size", "units": "1"}),
            "autocorr_time": (
                pf,
                dcol("tau"),
                {"long_name": "integrated autocorrelation time", "units": "steps"},
            ),
            "mle": (pf, col("mle"), {"long_name": "engine's maximum-likelihood estimate"}),
            "mle_se": (
                pf,
                col("mle_se"),
                {"long_name": "engine's standard error (inverse observed information)"},
            ),
            "acceptance": (pdim, dcol("acceptance"), {"long_name": "mean acceptance fraction"}),
            "n_steps": (pdim, dcol("total"), {"units": "steps per walker"}),
            "burn": (pdim, dcol("burn"), {"units": "steps per walker"}),
            "thin": (pdim, col("thin"), {"units": "steps"}),
            "n_draws": (pdim, np.array([p["samples"].shape[0] for p in per_pixel])),
            "n_walkers": (pdim, col("n_walkers")),
            "mle_converged": (pdim, col("mle_converged")),
            "seconds": (
                pdim,
                col("seconds"),
                {"long_name": "wall time of the pixel", "units": "s"},
            ),
        },
        coords={
            "pixel": np.arange(Pn),
            "row": ("pixel", col("row")),
            "col": ("pixel", col("col")),
            "parameter": names,
            "units": ("parameter", units),
        },
        attrs=attrs,
    )


def _prior_text(prior):
    if prior == "uniform":
        return (
            "flat in the physical parameters (e_per_adu, photoelectrons, em_gain) inside "
            "emccdcal.fit.layouts.BOUNDS, zero outside; plus the layout's own prior if any"
        )
    return (
        "flat in the log of every free parameter (p(theta) ~ 1/theta) inside "
        "emccdcal.fit.layouts.BOUNDS, zero outside; plus the layout's own prior if any"
    )


# --------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------
def summary(ds):
    """The ``posterior.json`` content of a :func:`sample_pixels` result (a dict)."""
    stats_keys = (
        "median",
        "sd",
        "q16",
        "q84",
        "q025",
        "q975",
        "ess",
        "autocorr_time",
        "mle",
        "mle_se",
    )
    pixels = []
    for i in range(ds.sizes["pixel"]):
        params = {}
        for j, name in enumerate(ds.parameter.values.tolist()):
            entry = {"units": str(ds.units.values[j])}
            for k in stats_keys:
                entry[k] = finite_or_none(ds[k].values[i, j])
            entry["acceptance"] = finite_or_none(ds.acceptance.values[i])
            params[name] = entry
        pixels.append(
            {
                "row": int(ds.row.values[i]),
                "col": int(ds.col.values[i]),
                "acceptance": finite_or_none(ds.acceptance.values[i]),
                "n_walkers": int(ds.n_walkers.values[i]),
                "n_steps": int(ds.n_steps.values[i]),
                "burn": int(ds.burn.values[i]),
                "thin": int(ds["thin"].values[i]),
                "n_draws": int(ds.n_draws.values[i]),
                "mle_converged": bool(ds.mle_converged.values[i]),
                "seconds": finite_or_none(ds.seconds.values[i]),
                "parameters": params,
            }
        )
    return {
        "method": ds.attrs["method"],
        "prior": ds.attrs["prior"],
        "prior_description": ds.attrs["prior_description"],
        "sampler": ds.attrs["sampler"],
        "seed": ds.attrs["seed"],
        "min_ess": ds.attrs["min_ess"],
        "convergence": (
            f"kept chain >= {MIN_LENGTH_TAUS:g} tau after a burn-in of "
            f"{BURN_TAUS:g} tau; ess >= min_ess for every parameter; mean "
            f"acceptance in [{ACCEPTANCE[0]}, {ACCEPTANCE[1]}]"
        ),
        "manifest_hash": ds.attrs["manifest_hash"],
        "manifest_path": ds.attrs["manifest_path"],
        **{
            k: (int(ds.attrs[k]) if k == "register_stages" else str(ds.attrs[k]))
            for k in ("em_model", "register_stages", "register_stages_source")
            if k in ds.attrs
        },
        "seconds": finite_or_none(ds.attrs.get("seconds", float("nan"))),
        "pixels": pixels,
    }


def save(ds, out):
    """Write ``posterior.nc`` and ``posterior.json`` into directory ``out``.

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    nc = out / POSTERIOR_FILE
    atomic_write(nc, lambda tmp: write_netcdf(ds, tmp))
    written.append(nc)
    js = out / SUMMARY_FILE
    text = json.dumps(summary(ds), indent=2) + "\n"
    atomic_write_text(js, text)
    written.append(js)
    return written


def format_summary(ds):
    """Human-readable table: posterior median ± SD against the engine's MLE ± SE."""
    lines = [
        f"posterior ({ds.attrs['method']}, prior {ds.attrs['prior']}), "
        f"{ds.attrs.get('seconds', float('nan')):.1f} s"
    ]
    for i in range(ds.sizes["pixel"]):
        lines.append(
            f"pixel ({int(ds.row.values[i])}, {int(ds.col.values[i])}): "
            f"{int(ds.n_walkers.values[i])} walkers x {int(ds.n_steps.values[i])} steps, "
            f"acceptance {float(ds.acceptance.values[i]):.2f}"
        )
        for j, name in enumerate(ds.parameter.values.tolist()):
            lines.append(
                f"  {name:<22} {ds['median'].values[i, j]:.5g} ± {ds.sd.values[i, j]:.3g} "
                f"(MLE {ds.mle.values[i, j]:.5g} ± {ds.mle_se.values[i, j]:.3g}) "
                f"{ds.units.values[j]}  ess {ds.ess.values[i, j]:.0f}  "
                f"tau {ds.autocorr_time.values[i, j]:.1f}"
            )
    return "\n".join(lines)
