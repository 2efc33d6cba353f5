"""The main job: a manifest in, a labelled calibration out (``emccdcal calibrate``).

files → :mod:`io` (manifest) → :mod:`stats` (per-pixel histograms) → :mod:`fitting`
driven by a :mod:`methods` layout, tile by tile → :mod:`result` (dataset, files).
"""

from __future__ import annotations

import copy
import json
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from . import result
from ._util import e_per_adu_map
from ._util import progress as progress_bar
from .data import quality, stats
from .data.manifest import Manifest, read_manifest
from .errors import MethodError, OptionError
from .fit import engine, gof, layouts, mv

if TYPE_CHECKING:
    import xarray

__all__ = ["METHODS", "INTERVALS", "DEFAULT_BLOCK", "calibrate", "format_summary"]

METHODS = ("mv-adu", "mv-gain") + layouts.LIKELIHOOD_METHODS
#: Interval kinds of :func:`calibrate`: ``estimate ± 1.96 SE`` only, or profile bounds too.
INTERVALS = ("wald", "profile")

#: Pixels fitted together: large enough to amortise Python overhead, small enough that
#: the FFT windows of a block (pixels × window × derivatives) stay within a few hundred MB
#: and that two threads share the blocks evenly (128 fitted a 32 × 32 gain series 11 %
#: faster than 256 on two cores; docs/benchmarks.md).
DEFAULT_BLOCK = 128


def _load(manifest):
    if isinstance(manifest, Manifest):
        return manifest
    return read_manifest(manifest)


def _labels(acqs):
    return [a.level if a.level is not None else a.name for a in acqs]


def _statistics(manifest, acqs, progress, workers):
    """Per-pixel histograms of every acquisition (threads: sorting releases the GIL)."""

    def one(acq):
        return stats.histograms(acq.frames(), adc_max=manifest.adc_max)

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        hists = list(progress_bar(pool.map(one, acqs), enabled=progress, desc="reading",
                                  unit="acq", total=len(acqs)))
    found = []
    for acq, h in zip(acqs, hists):
        n_sat = int(h.n_saturated.sum())
        if n_sat:
            found.append(
                f"{acq.frames_path.name}: {n_sat} frame values at the ADC maximum "
                f"({manifest.adc_max} ADU) in {int((h.n_saturated > 0).sum())} pixel(s) were "
                "excluded from the fit"
            )
        if np.any(h.n < 2):
            raise OptionError(f"{acq.frames_path}: fewer than 2 usable frames in some pixels")
    return hists, found


def calibrate(
    manifest,
    method="gs",
    *,
    e_per_adu=None,
    out=None,
    block_size=DEFAULT_BLOCK,
    options=None,
    progress=False,
    workers=None,
    checks=True,
    map_errors=True,
    intervals="wald",
) -> xarray.Dataset:
    """Calibrate a camera from the acquisitions of a manifest.

    Parameters
    ----------
    manifest : str, Path or :class:`emccdcal.Manifest`
        The TOML manifest (see ``docs/manifest.md``).
    method : str
        One of :data:`METHODS`: ``mv-adu``, ``mv-gain``, ``is-adu``, ``is-gain``, ``gs``,
        ``gs-no1x``, ``gs-hierarchical``.
    e_per_adu : float or ndarray (rows, cols), optional
        φ (e⁻/ADU) overriding the manifest's, for the methods that hold it fixed.
    out : str or Path, optional
        Directory to write ``calibration.nc`` and ``summary.json`` into.
    block_size : int
        Pixels fitted together.
    options : dict, optional
        Method options; only ``gs-hierarchical`` takes any (:func:`emccdcal.fit.layouts.check_options`):
        ``mu_sd`` and ``sigma_sd``, the scales of its hyperpriors in photoelectrons (the
        authors' 25 e⁻ by default, for an illumination of about 370 e⁻: scale them in
        proportion to yours), and ``centre`` (``"gs"`` or the authors' ``"setpoint"``).
    progress : bool
        Show progress bars on stderr.
    workers : int, optional
        Threads fitting blocks at once (default: the number of CPUs).
    checks : bool
        Run the data-quality checks (:mod:`emccdcal.data.quality`: illumination stationarity
        and drift, saturation, hot/dead pixels) and store them in the result
        (``attrs["quality"]``, JSON) and ``summary.json``; findings are warnings.
    map_errors : bool
        Include in the standard errors of the likelihood methods the error of offset and
        read-noise maps estimated from dark frames (``dark`` stacks, or maps with
        ``dark_frames`` in the manifest): the offset map's own SE is σ/√n_dark, which moves
        E at 1× by φσ/√n_dark. ``False`` gives SEs conditional on the maps. Maps without a
        known number of dark frames are always taken as exact.
    intervals : {"wald", "profile"}
        ``"profile"`` adds 95 % profile-likelihood bounds ``<name>_lower``/``<name>_upper``
        for the likelihood methods' free parameters: they follow a skewed likelihood
        (few photoelectrons, weak set-points) where ``estimate ± 1.96 SE`` does not. They
        include the maps' errors as the SEs do (their deviance target grows by the ratio
        of the variances with and without them) and cost about ten refits per parameter. The
        mean–variance methods have no likelihood (``"profile"`` is an error there); their
        results always carry 95 % Fieller bounds (:func:`emccdcal.fit.mv.fieller_interval`).
        ``gs-hierarchical`` results always carry bounds too, those of the same model
        without its prior (:func:`emccdcal.fit.layouts.unpooled_bounds`): its MAP ± 1.96 SE
        over-covers where the true E is shared and under-covers where it is not.

    Returns
    -------
    xarray.Dataset
        The calibration (see ``docs/results.md``); ``ds.attrs["seconds"]`` is the wall time.

    Examples
    --------
    >>> ds = calibrate("gain-series/manifest.toml", method="gs")  # doctest: +SKIP
    >>> ds.em_gain.sel(setpoint=300).mean().item()                 # doctest: +SKIP
    261.6
    """
    if method not in METHODS:
        raise MethodError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if intervals not in INTERVALS:
        raise OptionError(f"unknown intervals {intervals!r}; choose one of {', '.join(INTERVALS)}")
    if intervals == "profile" and method.startswith("mv-"):
        raise MethodError(f"{method} has no likelihood: profile intervals need a "
                                  "likelihood method ({method} results always carry Fieller "
                                  "bounds)")
    # Every warning of the run (manifest, saturation, convergence, misfit) is recorded in
    # the result and issued again to the caller.
    return result.run_recorded(
        lambda: _run_calibration(manifest, method, e_per_adu, block_size, options, progress,
                                 workers, checks, map_errors, intervals),
        out,
    )


def _run_calibration(manifest, method, e_per_adu, block_size, options, progress, workers,
                     checks, map_errors, intervals):
    manifest = _load(manifest)
    acqs = manifest.acquisitions
    rows, cols = manifest.shape
    phi_map = e_per_adu_map(manifest.e_per_adu if e_per_adu is None else e_per_adu, (rows, cols))
    setpoints_all = [a.em_gain_setpoint for a in acqs]

    if method not in METHODS:
        raise MethodError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    options = layouts.check_options(method, options)  # before any stack is read
    if method.startswith("mv-"):
        idx = _select_mv(method, setpoints_all, phi_map is not None)
    else:
        idx = layouts.select_acquisitions(
            method, setpoints_all, [a.level for a in acqs], phi_map is not None
        )
    used = [acqs[i] for i in idx]
    workers = os.cpu_count() if workers is None else workers
    if checks:
        quality.prefetch()  # its imports overlap the reading of the stacks
    hists, found = _statistics(manifest, used, progress, workers)
    for w in found:
        warnings.warn(w, stacklevel=2)
    # The data-quality checks read the stacks once more (warnings are process-global, so
    # they are not run on a side thread).
    report, messages = _quality(manifest, used) if checks else (None, [])
    for w in messages:
        warnings.warn(w, stacklevel=2)
    if method.startswith("mv-"):
        ds = _calibrate_mv(method, manifest, used, hists, phi_map)
        ds.attrs["standard_errors"] = "from the photon-transfer fit, conditional on the offset maps"
    else:
        dark_frames, map_groups, se_note = _map_error_sources(used, map_errors)
        ds = _calibrate_likelihood(method, manifest, used, hists, phi_map, block_size,
                                   options, progress, workers, dark_frames, map_groups,
                                   intervals)
        ds.attrs["standard_errors"] = se_note
    if report is not None:
        ds.attrs["quality"] = json.dumps(report)
    return ds


def _quality(manifest, used):
    """Data-quality checks (stationarity, drift, saturation, defects) of the used stacks.

    Returns the report and its findings as messages for the caller to issue.
    """
    sub = copy.copy(manifest)
    sub.acquisitions = list(used)
    try:
        report = quality.check_manifest(sub)
    except ValueError as exc:  # e.g. too few frames for the stationarity tests
        return None, [f"data-quality checks skipped: {exc}"]
    grown = set(manifest.warnings)  # read-noise growth was already reported by io
    return report, [w for w in report["warnings"] if not any(w in g or g in w for g in grown)]


def _select_mv(method, setpoints, has_phi):
    sp = np.asarray(setpoints, dtype=float)
    if method == "mv-adu":
        if np.any(sp != 1):
            raise MethodError("mv-adu needs 1x (EM gain off) data only")
        return np.arange(sp.size)
    if not has_phi:
        raise MethodError(
            "mv-gain needs e_per_adu (e-/ADU): set it in the manifest or pass --e-per-adu"
        )
    return np.argsort(sp, kind="stable")


def _maps(used):
    """Offset and read-noise maps of the acquisitions, stacked as (A, P), ADU."""
    offsets = np.stack([a.offset.ravel() for a in used])
    read_noise = np.stack([a.read_noise.ravel() for a in used])
    return offsets, read_noise


def _map_error_sources(used, map_errors):
    """Dark-frame counts and sharing groups of the maps, and a note for the result."""
    dark_frames = [a.dark_frames if map_errors else None for a in used]
    # Acquisitions whose maps come from one file (or one dark stack) share their errors.
    groups = [a.offset_source if not a.offset_source.startswith("value") else i
              for i, a in enumerate(used)]
    known = [f"{a.name}: {n} dark frames" for a, n in zip(used, dark_frames) if n is not None]
    exact = [a.name for a, n in zip(used, dark_frames) if n is None]
    if not map_errors:
        note = "conditional on the offset and read-noise maps (map errors not included)"
    elif not known:
        note = ("conditional on the offset and read-noise maps (no dark-frame counts known; "
                "give 'dark' stacks or 'dark_frames' in the manifest to include their errors)")
    else:
        note = "include the errors of the offset and read-noise maps (" + "; ".join(known)
        note += (f"; taken as exact: {', '.join(exact)})" if exact else ")")
    return dark_frames, groups, note


def _calibrate_likelihood(method, manifest, used, hists, phi_map, block_size, options, progress,
                          workers, dark_frames, map_groups, intervals):
    rows, cols = manifest.shape
    P = rows * cols
    setpoints = np.array([a.em_gain_setpoint for a in used])
    offsets, read_noise = _maps(used)
    phi = None if phi_map is None else phi_map.ravel()
    A = len(used)
    est = {k: np.full((P, A), np.nan) for k in (
        "photoelectrons", "photoelectrons_se", "em_gain", "em_gain_se", "e_per_adu",
        "e_per_adu_se")}
    loglik = np.full(P, np.nan)
    gof_p = np.full((P, A), np.nan)
    converged = np.zeros(P, dtype=bool)
    n_floored = np.zeros(P, dtype=np.int64)
    iterations = np.zeros(P, dtype=np.int64)
    hyper = {"hyper_photoelectrons": np.full(P, np.nan), "hyper_sd_photoelectrons": np.full(P, np.nan)}
    # Interval bounds: (function of a fitted block, kind, description), or None.
    bounds = None
    if intervals == "profile":
        bounds = (layouts.acquisition_bounds, "profile-likelihood",
                  "profile likelihood, 95 %, widened by the errors of the offset and "
                  "read-noise maps where the standard errors include them")
    elif method == "gs-hierarchical":
        bounds = (layouts.unpooled_bounds, "unpooled",
                  "95 %, of the same model without the prior (each set-point its own E): "
                  "Wald on the log scale, profile likelihood where that is unreliable; "
                  "the MAP's own ± 1.96 SE reflect its shrinkage")

    def fit_block(idx):
        blocks = layouts.make_blocks(hists, offsets, read_noise, setpoints, idx,
                                     dark_frames, map_groups)
        series = layouts.Series(blocks, setpoints, _labels(used),
                                None if phi is None else phi[idx])
        layout, x0 = layouts.build_layout(method, series, options)
        fit = engine.fit(layout, blocks, x0)
        e = layouts.acquisition_estimates(layout, fit.x, fit.cov)
        if bounds is not None:
            e.update(bounds[0](layout, blocks, fit))
        # Goodness of fit per acquisition; a free parameter shared by k acquisitions
        # counts 1/k towards each one's fitted-parameter number.
        touches = np.any(layout.matrix != 0, axis=1)  # (A, F)
        n_fitted = (touches / np.maximum(touches.sum(axis=0), 1)).sum(axis=1)
        pvals = np.stack([
            gof.gof_pvalues(blocks[a], e["photoelectrons"][:, a], e["em_gain"][:, a],
                            e["e_per_adu"][:, a], blocks[a].offset, blocks[a].read_noise,
                            n_fitted_params=float(n_fitted[a]))[0]
            for a in range(len(blocks))
        ], axis=1)
        return idx, layout, fit, e, pvals

    bar = progress_bar(enabled=progress, desc=f"fitting {method}", unit="px", total=P)
    tiles = [np.arange(s, min(P, s + block_size)) for s in range(0, P, block_size)]
    # Blocks are independent: threads overlap them (NumPy and the FFT release the GIL),
    # and the result does not depend on how many there are.
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        for idx, layout, fit, e, pvals in pool.map(fit_block, tiles):
            gof_p[idx] = pvals
            for k in e:
                est.setdefault(k, np.full((P, A), np.nan))[idx] = e[k]
            loglik[idx] = fit.loglik
            converged[idx] = fit.converged
            n_floored[idx] = fit.n_floored
            iterations[idx] = fit.iterations
            if method == "gs-hierarchical":
                mu, sigma_e = layout.hyperparameters(fit.x)
                hyper["hyper_photoelectrons"][idx] = mu
                hyper["hyper_sd_photoelectrons"][idx] = sigma_e
            bar.update(idx.size)
    bar.close()

    not_conv = int((~converged).sum())
    if not_conv:
        warnings.warn(f"{method}: {not_conv} of {P} pixel(s) did not converge (see 'converged')",
                      stacklevel=3)
    kind = "level" if method.startswith("is-") else "set-point"
    keys = _labels(used) if kind == "level" else [result.format_setpoint(s) + "x" for s in setpoints]
    for w in gof.misfit_warnings(dict(zip(keys, gof_p.T)), kind=kind):
        warnings.warn(w, stacklevel=3)
    grid = lambda a: a.T.reshape((-1, rows, cols)) if a.ndim == 2 else a.reshape(rows, cols)  # noqa: E731
    labels = _labels(used)
    per_acq_dim = "level" if method.startswith("is-") else "setpoint"
    extra = {
        "offset": ((per_acq_dim, "row", "col"), grid(offsets.T), "ADU"),
        "read_noise": ((per_acq_dim, "row", "col"), grid(read_noise.T), "ADU"),
        "n_saturated": ((per_acq_dim, "row", "col"),
                        np.stack([h.n_saturated.reshape(rows, cols) for h in hists]), "1"),
        "n_floored": (("row", "col"), grid(n_floored), "1"),
        "iterations": (("row", "col"), grid(iterations), "1"),
        "gof_pvalue": ((per_acq_dim, "row", "col"), grid(gof_p), "1",
                       "p-value of the binned chi-square goodness-of-fit test"),
    }
    fixed_phi_se = np.full((rows, cols), np.nan)
    if method == "is-adu":
        ds = result.make_dataset(
            method=method, setpoints=[1.0], levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]), e_per_adu_se=grid(est["e_per_adu_se"][:, 0]),
            em_gain=np.ones((1, rows, cols)), em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(est["photoelectrons"]), photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            loglik=grid(loglik), converged=grid(converged),
            manifest_hash=manifest.content_hash, manifest_path=str(manifest.path.resolve()), extra=extra,
        )
    elif method == "is-gain":
        ds = result.make_dataset(
            method=method, setpoints=[float(setpoints[0])], levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]), e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"][:, :1]), em_gain_se=grid(est["em_gain_se"][:, :1]),
            photoelectrons=grid(est["photoelectrons"]), photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            loglik=grid(loglik), converged=grid(converged),
            manifest_hash=manifest.content_hash, manifest_path=str(manifest.path.resolve()), extra=extra,
        )
    else:
        shared = method in ("gs", "gs-no1x")
        if method == "gs-hierarchical":
            extra["hyper_photoelectrons"] = (("row", "col"), grid(hyper["hyper_photoelectrons"]), "e-")
            extra["hyper_sd_photoelectrons"] = (("row", "col"), grid(hyper["hyper_sd_photoelectrons"]), "e-")
        ds = result.make_dataset(
            method=method, setpoints=[float(s) for s in setpoints],
            e_per_adu=grid(est["e_per_adu"][:, 0]), e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"]), em_gain_se=grid(est["em_gain_se"]),
            photoelectrons=grid(est["photoelectrons"][:, 0]) if shared else grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"][:, 0]) if shared else grid(est["photoelectrons_se"]),
            photoelectrons_dims=("row", "col") if shared else ("setpoint", "row", "col"),
            loglik=grid(loglik), converged=grid(converged),
            manifest_hash=manifest.content_hash, manifest_path=str(manifest.path.resolve()), extra=extra,
            attrs={"options": json.dumps(options)} if options else None,
        )
    if bounds is not None:
        _add_bounds(ds, est, grid, *bounds[1:])
    return ds


def _add_bounds(ds, est, grid, kind, description):
    """Bounds ``<name>_lower/_upper`` of ``est`` beside each estimate, on its dims."""
    bounds = {}
    for name in ("photoelectrons", "em_gain", "e_per_adu"):
        lower, upper = est[f"{name}_lower"], est[f"{name}_upper"]
        if np.all(np.isnan(lower)):
            continue  # fixed by the method
        da = ds[name]
        pick = (lambda a: a[:, 0]) if da.ndim == 2 else (lambda a: a[:, : da.shape[0]])  # noqa: E731
        bounds[name] = grid(pick(lower)), grid(pick(upper))
    _add_interval_vars(ds, bounds, kind, description)


def _add_interval_vars(ds, bounds, kind, description):
    """Store ``{name: (lower, upper)}`` as ``<name>_lower/_upper`` on the dims of ``name``."""
    for name, pair in bounds.items():
        da = ds[name]
        for side, arr in zip(("lower", "upper"), pair):
            ds[f"{name}_{side}"] = (da.dims, np.asarray(arr), {
                "units": da.attrs["units"],
                "long_name": f"{side} bound of the 95 % {kind} interval of {name}",
            })
    ds.attrs["intervals"] = description


def _calibrate_mv(method, manifest, used, hists, phi_map):
    rows, cols = manifest.shape
    offsets, read_noise = _maps(used)
    mean = np.stack([h.mean for h in hists])
    var = np.stack([h.var for h in hists])
    n = np.stack([h.n for h in hists])
    grid = lambda a: np.asarray(a).reshape(np.shape(a)[:-1] + (rows, cols))  # noqa: E731
    labels = _labels(used)
    setpoints = [a.em_gain_setpoint for a in used]
    if method == "mv-adu":
        fit = mv.fit_mv_adu(mean, var, offsets, read_noise, n)
        ds = result.make_dataset(
            method=method, setpoints=[1.0], levels=labels,
            e_per_adu=grid(fit.e_per_adu), e_per_adu_se=grid(fit.e_per_adu_se),
            em_gain=np.ones((1, rows, cols)), em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(fit.photoelectrons), photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=("level", "row", "col"),
            converged=grid(fit.valid), manifest_hash=manifest.content_hash,
            manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"e_per_adu": (grid(fit.e_per_adu_lower), grid(fit.e_per_adu_upper))}
    else:
        phi = phi_map.ravel()
        fit = mv.fit_mv_gain(mean, var, offsets, read_noise, n, phi, np.asarray(setpoints))
        by_level = len(set(setpoints)) == 1 and len(setpoints) > 1
        ds = result.make_dataset(
            method=method, setpoints=[float(s) for s in fit.setpoints],
            levels=labels if by_level else None,
            e_per_adu=phi_map, e_per_adu_se=np.full((rows, cols), np.nan),
            em_gain=grid(fit.em_gain), em_gain_se=grid(fit.em_gain_se),
            photoelectrons=grid(fit.photoelectrons), photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=(("level" if by_level else "setpoint"), "row", "col"),
            converged=grid(np.all(fit.valid, axis=0) if np.ndim(fit.valid) > 1 else fit.valid),
            manifest_hash=manifest.content_hash, manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"em_gain": (grid(fit.em_gain_lower), grid(fit.em_gain_upper))}
    bounds["photoelectrons"] = grid(fit.photoelectrons_lower), grid(fit.photoelectrons_upper)
    # Ratios of sample moments: Fieller bounds, valid where the slope is poorly determined
    # (and defined where the estimate is not), unlike estimate ± 1.96 SE.
    _add_interval_vars(ds, bounds, "Fieller",
                       "Fieller, 95 %, from the photon-transfer fit, conditional on the "
                       "offset/read-noise maps")
    return ds


def format_summary(ds):
    """A short human-readable table of a calibration (median over converged pixels)."""
    ok = ds.converged.values
    lines = [f"method {ds.attrs['method']}: {int(ok.sum())}/{ok.size} pixels converged, "
             f"{ds.attrs.get('seconds', float('nan')):.1f} s"]

    def med(v):
        vals = np.asarray(v)[..., ok] if ok.any() else np.asarray(v).reshape(v.shape[:-2] + (-1,))
        return np.nanmedian(vals, axis=-1)

    lines.append(f"  e_per_adu  {med(ds.e_per_adu.values):.4f} e-/ADU "
                 f"(adu_per_e {1 / med(ds.e_per_adu.values):.4f} ADU/e-)")
    for i, sp in enumerate(ds.setpoint.values):
        g, se = med(ds.em_gain.values[i]), med(ds.em_gain_se.values[i])
        lines.append(f"  em_gain at {result.format_setpoint(sp)}x: {g:.4f} ± {se:.4f}")
    pe = ds.photoelectrons
    if pe.ndim == 2:
        lines.append(f"  photoelectrons {med(pe.values):.2f} ± {med(ds.photoelectrons_se.values):.2f} e-")
    else:
        dim = pe.dims[0]
        for i, lab in enumerate(pe[dim].values):
            lines.append(f"  photoelectrons [{dim} {lab}] {med(pe.values[i]):.2f} ± "
                         f"{med(ds.photoelectrons_se.values[i]):.2f} e-")
    return "\n".join(lines)
