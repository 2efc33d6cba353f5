"""The tiles assembled into one labelled result: the likelihood methods' and the mean-variance methods' datasets, their bounds, findings, warnings and provenance."""

from __future__ import annotations

import copy
import json
import math
import warnings
from typing import TYPE_CHECKING

import numpy as np

from .. import defaults, result
from .._util import nanmedian
from ..data import dark_current, quality
from ..data.dark import map_variances
from ..data.telegraph import MAX_STATES
from ..errors import (
    DataQualityWarning,
    LeftOutWarning,
    SaturationWarning,
    FitWarning,
)
from ..fit import gof, mv
from .tiles import _QUALITY, _bounds_of, _labels

if TYPE_CHECKING:
    pass


def _add_findings(ds, manifest, used, parts, tiles) -> None:
    """The data-quality checks' findings, warned and in ``ds.attrs["quality"]``: they
    quote the light this fit found, not a rough guess of it."""
    report, messages = _quality(manifest, used, parts, tiles, _fitted_light(ds, used))
    for w in messages:  # a finding knows its kind (drift, read-noise growth ...)
        warnings.warn(w, stacklevel=3, category=getattr(w, "category", DataQualityWarning))
    if report is not None:
        ds.attrs["quality"] = json.dumps(report)

    # a finding after which the result does not stand makes the verdict doubtful, one that
    # asks for a check says so: its subject and what was found (the warning says what to do)
    def subjects(flag):
        return [": ".join(w.split(": ")[:2]) for w in messages if getattr(w, flag, False)]

    before = str(ds.attrs.get("verdict", "stands"))
    if subjects("doubtful"):
        found = "; ".join(subjects("doubtful")) + " (its warning says what to do)"
        rest = "" if before == "stands" else "; " + before.removeprefix("doubtful: ")
        ds.attrs["verdict"] = "doubtful: " + found + rest
    elif subjects("caution") and before == "stands":  # stands, once a check is made
        ds.attrs["verdict"] = (
            "stands; check first " + "; ".join(subjects("caution")) + " (its warning says how)"
        )


def _joined(parts) -> dict:
    """The tiles' per-pixel arrays joined, each moved out of ``parts`` (one copy at a
    time); the data-quality statistics stay in ``parts``."""
    return {
        key: np.concatenate([p.pop(key) for p in parts])
        for key in [k for k in parts[0] if not k.startswith(_QUALITY)]
    }


def _record_provenance(
    ds, method, manifest, model, register_attrs, device, phi_source, phi_has_se: bool
) -> None:
    """Write into ``ds.attrs`` what the numbers came from: the register model, the device,
    the camera's identity, where φ came from."""
    if method != "mv-adu":  # the register model of the likelihood, or mv-gain's F²
        ds.attrs.update(model.attrs, **register_attrs)
    if not method.startswith("mv-"):  # where the likelihood was computed
        ds.attrs["device"] = device or "cpu"
    ds.attrs.update(result.identity_attrs(manifest))  # the camera and pixels it holds for
    if phi_source is not None:
        ds.attrs["e_per_adu_source"] = str(phi_source)
        if phi_source.kind == "result":  # chained: the result φ and its error came from
            ds.attrs["e_per_adu_result"] = str(phi_source.path)
    if phi_has_se:
        ds.attrs["standard_errors"] += (
            f"; and the error of e_per_adu ({phi_source}): it moves every E and g of a pixel "
            "together (delta method through the likelihood, or the photon-transfer formulas)"
        )


def _warn_saturated_and_unusable(manifest, used, arrays):
    rows, cols = manifest.shape
    for a, acq in enumerate(used):
        n_sat = arrays["n_saturated"][:, a]
        if n_sat.sum():
            warnings.warn(
                f"{acq.frames_path.name}: {int(n_sat.sum())} frame values at the ADC maximum "
                f"({manifest.adc_max} ADU) in {int((n_sat > 0).sum())} pixel(s) were "
                "excluded from the fit, so those pixels' gain and light read low; the other "
                "pixels' results stand; lower the light (or the EM gain) and record again "
                "for these",
                stacklevel=3,
                category=SaturationWarning,
            )
    bad = np.flatnonzero(~arrays["usable"])
    if bad.size:
        where = ", ".join(f"({p // cols}, {p % cols})" for p in bad[:5])
        warnings.warn(
            f"{bad.size} of {rows * cols} pixel(s) have fewer than 2 usable frames, or frames "
            "or dark frames that never change, in some acquisition (saturated, dead or "
            f"stuck): {where}"
            f"{', ...' if bad.size > 5 else ''}; they are left out (NaN, converged = False), "
            "and the other pixels' results stand",
            stacklevel=3,
            category=LeftOutWarning,
        )


def _fitted_light(ds, used) -> list:
    """What the fit found for each used acquisition, for the checks' findings to quote:
    None where the method estimates no E for it, else a dict: ``photoelectrons`` (E, e⁻
    per pixel and frame), ``absorbed`` (whether the spread of a drifting light biases an
    estimate there: not where the estimates come from the acquisition's mean, as at 1×
    with φ given, or in ``gs``, whose E is shared with the 1× light) and
    ``relative_se`` (that estimate's, the EM gain or φ at 1×, or None); medians over
    converged pixels."""
    if "photoelectrons" not in ds:
        return [None] * len(used)
    ok = ds.converged.values.astype(bool)
    phi_given = "e_per_adu_source" in ds.attrs
    pinned = phi_given and ds.attrs.get("method") == "gs"

    def median_at(name, a):
        sel = ds[name]
        if "setpoint" in sel.dims:
            sel = sel.sel(setpoint=a.em_gain_setpoint)
        if "level" in sel.dims:
            sel = sel.sel(level=a.level)
        values = np.asarray(sel.values, dtype=float)
        return float(nanmedian(values[ok])) if values.shape == ok.shape else math.nan

    out: list[dict | None] = []
    for a in used:
        try:
            light = median_at("photoelectrons", a)
        except (KeyError, ValueError):
            light = math.nan
        if not (math.isfinite(light) and light > 0):
            out.append(None)
            continue
        what = "em_gain" if a.em_gain_setpoint != 1 and "em_gain" in ds else "e_per_adu"
        try:
            rse = median_at(f"{what}_se", a) / median_at(what, a)
        except (KeyError, ValueError):
            rse = math.nan
        out.append(
            {
                "photoelectrons": light,
                "absorbed": not (pinned or (phi_given and a.em_gain_setpoint == 1)),
                "relative_se": rse if math.isfinite(rse) and rse > 0 else None,
            }
        )
    return out


def _quality(manifest, used, parts, tiles, fitted=None):
    """Data-quality checks (drift, saturation, defects) of the used stacks,
    from the statistics the tiles gathered as they read them; ``fitted``: for each
    stack, what :func:`_fitted_light` found (or None), which the findings quote.

    Returns the report and its findings as messages for the caller to issue.
    """
    summaries = []
    for a, acq in enumerate(used):
        summary = quality.StackSummary(acq.n_frames, manifest.shape, manifest.adc_max)
        for (p0, _), part in zip(tiles, parts):
            prefix = f"{_QUALITY}{a}_"
            summary.add(p0, {k[len(prefix) :]: v for k, v in part.items() if k.startswith(prefix)})
        summaries.append(summary)
    sub = copy.copy(manifest)
    sub.acquisitions = list(used)
    try:
        report = quality.check_manifest(sub, summaries=summaries, fitted=fitted)
    except ValueError as exc:  # frame means that cannot be tested (not finite)
        return None, [f"data-quality checks skipped: {exc}"]
    grown = set(manifest.warnings)  # read-noise growth was already reported by the manifest
    return report, [w for w in report["warnings"] if not any(w in g or g in w for g in grown)]


def _map_error_sources(used, map_errors):
    """Dark-frame counts and sharing groups of the maps, and a note for the result."""
    dark_frames = [a.dark_frames if map_errors else None for a in used]
    # Acquisitions whose maps come from one file (or one dark stack) share their errors.
    groups = [a.offset_source if a.offset_source.kind != "value" else i for i, a in enumerate(used)]
    known = [f"{a.name}: {n} dark frames" for a, n in zip(used, dark_frames) if n is not None]
    exact = [a.name for a, n in zip(used, dark_frames) if n is None]
    if not map_errors:
        note = "conditional on the offset and read-noise maps (map errors not included)"
    elif not known:
        note = (
            "conditional on the offset and read-noise maps (no dark-frame counts known; "
            "give 'dark' stacks or 'dark_frames' in the manifest to include their errors)"
        )
    else:
        note = "include the errors of the offset and read-noise maps (" + "; ".join(known)
        note += f"; taken as exact: {', '.join(exact)})" if exact else ")"
    return dark_frames, groups, note


def _warn_fit_problems(method, used, arrays, model) -> None:
    """Warn of pixels that did not converge and of acquisitions the model misfits."""
    setpoints = [a.em_gain_setpoint for a in used]
    converged, gof_p = arrays["converged"], arrays["gof_pvalue"]
    not_conv = int((~converged & arrays["usable"]).sum())
    if not_conv:
        warnings.warn(
            f"{method}: {not_conv} of {int(arrays['usable'].sum())} fitted pixel(s) "
            "did not converge (converged = False): their numbers are not estimates "
            "and must not be used; the converged pixels' results stand",
            stacklevel=4,
            category=FitWarning,
        )
    kind, keys = _acquisition_keys(method, used)
    multiplied = [k for k, sp in zip(keys, setpoints) if sp != 1]
    for w in gof.misfit_warnings(dict(zip(keys, gof_p.T)), kind=kind):
        hint = model.register.misfit_hint
        if hint and any(w.startswith(f"{kind} {k}:") for k in multiplied):
            # An approximate register's commonest misfit (the gamma model's excess noise
            # is 2, an exact register's below it, most at low gain).
            w += "; " + hint
        else:
            w += (
                ": the estimates there are doubtful; the checks' findings (or 'emccdcal "
                "check MANIFEST') name a cause to fix (drift, saturation, offset or "
                "read-noise maps of another mode, a mislabelled set-point); where they name "
                "none, leave that acquisition out of the manifest and compare"
            )
        warnings.warn(w, stacklevel=4, category=FitWarning)


def _dark_variables(used, per_acq_dim, shape) -> dict:
    """What the dark stacks showed besides the maps: the multiplied events' rate of the
    darks fitted with them, the stuck pixels of every dark stack and the random-telegraph
    pixels of 1× darks tested for them, with their offset states."""
    out: dict[str, tuple] = {}
    for name, text in (
        (
            "stuck",
            "1 where a dark stack's counts never change (a dead or stuck pixel: no read "
            "noise to measure, left out of the fit)",
        ),
        (
            "telegraph",
            "1 where a 1x dark holds two or more offset states (a random-telegraph pixel, "
            "its offset and read noise one normal's: doubtful)",
        ),
    ):
        found = [f for a in used if (f := getattr(a, "dark_" + name, None)) is not None]
        if found:
            out[name] = (("row", "col"), np.any(found, axis=0).astype(np.int8), "1", text)
    states = [s for a in used if (s := a.dark_telegraph_states) is not None]
    if states:
        out["telegraph_states"] = (
            ("row", "col"),
            np.max(states, axis=0).astype(np.int8),
            "1",
            "offset states a 1x dark holds: 1 (one normal), or 2 to "
            f"{MAX_STATES} at a random-telegraph pixel ({MAX_STATES}: that many or more), "
            "counted by Schwarz's criterion",
        )
    if any(a.dark_event_rate is not None for a in used):
        rates = np.stack(
            [
                np.full(shape, np.nan) if a.dark_event_rate is None else a.dark_event_rate
                for a in used
            ]
        )
        out["dark_event_rate"] = (
            (per_acq_dim, "row", "col"),
            rates,
            "e-",
            "multiplied electrons per pixel per frame in the dark "
            "stack (clock-induced charge, dark current)",
        )
    return out


def _map_errors(used, offsets, read_noise, per_acq_dim, shape) -> dict:
    """The offset and read-noise maps' standard errors (ADU) per acquisition, from the
    dark frames behind them (NaN where that count is unknown), where any is known."""
    if all(a.dark_frames is None for a in used):
        return {}
    se = np.full((2, len(used), *shape), np.nan)
    for i, a in enumerate(used):
        variances = map_variances(offsets[i], read_noise[i], a.dark_frames, a.em_gain_setpoint == 1)
        if variances[0] is not None:
            se[:, i] = np.sqrt(np.stack(variances)).reshape(2, *shape)
    what = "standard error of the {} map, from the dark frames it was computed from"
    return {
        f"{name}_se": ((per_acq_dim, "row", "col"), values, "ADU", what.format(name))
        for name, values in zip(("offset", "read_noise"), se)
    }


def _add_dark_current(ds, manifest, used) -> None:
    """Each pixel's dark current (e⁻/s) into ``ds`` where the series' 1× stacks give two
    or more exposures (:mod:`emccdcal.data.dark_current`): its darks', and on the
    photon-free path (``light = false``) every stack's."""
    if not manifest.light:
        ds.attrs["photon_free"] = 1  # the levels' photoelectrons are the dark signal's
    points = dark_current.exposure_points(used, light=manifest.light)
    se = ds["e_per_adu_se"].values if "e_per_adu_se" in ds else None
    found = dark_current.dark_current(points, ds["e_per_adu"].values, se)
    if found is None:
        return
    exposures = ", ".join(f"{p.label} at {p.exposure_s:g} s" for p in points)
    what = {
        "dark_current": "dark current: phi times the slope of the mean counts against "
        f"the exposure ({exposures})",
        "dark_current_se": "standard error of dark_current",
    }
    ok = ds["converged"].values
    for name, text in what.items():
        ds[name] = (("row", "col"), np.where(ok, found[name], np.nan))
        ds[name].attrs.update(units="e-/s", long_name=text)
    _warn_dark_signal_in_the_dark(ds, used)
    hot = dark_current.hot_pixels(ds["dark_current"].values, ds["dark_current_se"].values)
    if hot is not None:
        ds["hot"] = (("row", "col"), hot[0].astype(np.int8))
        ds["hot"].attrs.update(
            units="1",
            threshold_e_per_s=hot[1],
            long_name=f"1 where the dark current exceeds the median pixel's by more than "
            f"{defaults.DEFAULT_K:g} robust SDs ({hot[1]:.4g} e-/s): a hot pixel",
        )
    if found["pvalue"] is not None:
        ds["dark_current_pvalue"] = (("row", "col"), np.where(ok, found["pvalue"], np.nan))
        ds["dark_current_pvalue"].attrs.update(
            units="1",
            long_name="p-value of the straight line of mean counts against exposure "
            "(chi-square, points - 2 degrees of freedom): the dark signal linear in "
            "the exposure and the offset unchanged by it",
        )


def _warn_dark_signal_in_the_dark(ds, used) -> None:
    """Warn where a 1× dark's own dark signal, λ0 = dark current × its exposure (e⁻),
    is more than 1 % of the read-noise variance (σφ)² at pixels whose photon numbers
    show (σφ < 0.5 e⁻): the dark's maps then take the dark's few electrons for read
    noise, a wrong shape under a resolved comb, and φ is biased (docs/cmos.md)."""
    rate, phi = ds["dark_current"].values, ds["e_per_adu"].values
    for a in used:
        if a.em_gain_setpoint != 1 or a.dark_exposure_s is None:
            continue
        lam0, sigma_e = rate * a.dark_exposure_s, a.read_noise * phi
        with np.errstate(invalid="ignore"):
            bad = (sigma_e < 0.5) & (lam0 > 0.01 * sigma_e**2)
        if bad.any():
            warnings.warn(
                f"{a.name}: its dark ({a.offset_source}, {a.dark_exposure_s:g} s) holds a "
                f"median {np.nanmedian(lam0[bad]):.3g} e- of dark signal at {int(bad.sum())} "
                "pixel(s) whose photon numbers show, over 1 % of their read-noise variance: "
                "their maps take it for read noise and their e_per_adu is biased; record "
                "the dark at a shorter exposure",
                stacklevel=4,
                category=FitWarning,
            )
            return


def _likelihood_dataset(
    method, manifest, used, arrays, offsets, read_noise, options, intervals, model, se_note
):
    """The result of a likelihood method from the per-pixel arrays of every tile."""
    rows, cols = manifest.shape
    setpoints = np.array([a.em_gain_setpoint for a in used])
    est, gof_p, converged = arrays, arrays["gof_pvalue"], arrays["converged"]
    _warn_fit_problems(method, used, arrays, model)
    grid = lambda a: a.T.reshape((-1, rows, cols)) if a.ndim == 2 else a.reshape(rows, cols)  # noqa: E731
    labels = _labels(used)
    per_acq_dim = "level" if method.startswith("is-") else "setpoint"
    loglik = arrays["loglik"]
    extra = {
        "offset": ((per_acq_dim, "row", "col"), grid(offsets.T), "ADU"),
        "read_noise": ((per_acq_dim, "row", "col"), grid(read_noise.T), "ADU"),
        "n_saturated": ((per_acq_dim, "row", "col"), grid(arrays["n_saturated"]), "1"),
        "n_floored": (("row", "col"), grid(arrays["n_floored"]), "1"),
        "iterations": (("row", "col"), grid(arrays["iterations"]), "1"),
        "gof_pvalue": (
            (per_acq_dim, "row", "col"),
            grid(gof_p),
            "1",
            "p-value of the binned chi-square goodness-of-fit test",
        ),
        "acquisition_loglik": (
            (per_acq_dim, "row", "col"),
            grid(arrays["acquisition_loglik"]),
            "nats",
            "each acquisition's part of loglik",
        ),
    }
    extra.update(_map_errors(used, offsets, read_noise, per_acq_dim, (rows, cols)))
    extra.update(_dark_variables(used, per_acq_dim, (rows, cols)))
    fixed_phi_se = grid(est["e_per_adu_se"][:, 0])  # NaN unless φ came with its error
    common = dict(
        loglik=grid(loglik),
        converged=grid(converged),
        manifest_hash=manifest.content_hash,
        manifest_path=str(manifest.path.resolve()),
        extra=extra,
    )
    if method == "is-adu":
        ds = result.make_dataset(
            method=method,
            setpoints=[1.0],
            levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=grid(est["e_per_adu_se"][:, 0]),
            em_gain=np.ones((1, rows, cols)),
            em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            **common,
        )
    elif method == "is-gain":
        ds = result.make_dataset(
            method=method,
            setpoints=[float(setpoints[0])],
            levels=labels,
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"][:, :1]),
            em_gain_se=grid(est["em_gain_se"][:, :1]),
            photoelectrons=grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"]),
            photoelectrons_dims=("level", "row", "col"),
            **common,
        )
    else:
        shared = method in ("gs", "gs-no1x")
        if method == "gs-hierarchical":
            extra["hyper_photoelectrons"] = (
                ("row", "col"),
                grid(arrays["hyper_photoelectrons"]),
                "e-",
            )
            extra["hyper_sd_photoelectrons"] = (
                ("row", "col"),
                grid(arrays["hyper_sd_photoelectrons"]),
                "e-",
            )
        ds = result.make_dataset(
            method=method,
            setpoints=[float(s) for s in setpoints],
            e_per_adu=grid(est["e_per_adu"][:, 0]),
            e_per_adu_se=fixed_phi_se,
            em_gain=grid(est["em_gain"]),
            em_gain_se=grid(est["em_gain_se"]),
            photoelectrons=grid(est["photoelectrons"][:, 0])
            if shared
            else grid(est["photoelectrons"]),
            photoelectrons_se=grid(est["photoelectrons_se"][:, 0])
            if shared
            else grid(est["photoelectrons_se"]),
            photoelectrons_dims=("row", "col") if shared else ("setpoint", "row", "col"),
            attrs={"options": json.dumps(options)} if options else None,
            **common,
        )
    bounds = _bounds_of(method, intervals)
    if bounds is not None:
        _add_bounds(ds, est, grid, *bounds)
    ds.attrs["standard_errors"] = se_note
    ds.attrs["verdict"] = _verdict(method, used, gof_p, model)
    return ds


def _acquisition_keys(method, used) -> tuple[str, list[str]]:
    """What the acquisitions are ("level" or "set-point") and their labels in messages."""
    if method.startswith("is-"):
        return "level", _labels(used)
    return "set-point", [result.format_setpoint(a.em_gain_setpoint) + "x" for a in used]


def _verdict(method, used, gof_p, model) -> str:
    """``"stands"``, or ``"doubtful: ..."`` naming each acquisition whose goodness of fit
    rejects the model at most pixels (:func:`emccdcal.fit.gof.rejected_acquisitions`) and
    what to check: such a result is never reported as a success."""
    kind, keys = _acquisition_keys(method, used)
    rejected = gof.rejected_acquisitions(dict(zip(keys, gof_p.T)), kind=kind)
    if not rejected:
        return "stands"
    check = (
        "check that acquisition's dark or maps (another read-out mode or speed, a "
        "byte-swapped or damaged file), its set-point and the data-quality checks' "
        "findings ('emccdcal check MANIFEST')"
    )
    if model.register.misfit_hint:
        check += "; " + model.register.misfit_hint
    return "doubtful: " + "; ".join(rejected) + "; " + check


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
            ds[f"{name}_{side}"] = (
                da.dims,
                np.asarray(arr),
                {
                    "units": da.attrs["units"],
                    "long_name": f"{side} bound of the 95 % {kind} interval of {name}",
                },
            )
    ds.attrs["intervals"] = description


def _mv_dataset(method, manifest, used, arrays, phi_map, phi_se=None, model=None):
    """The result of a mean–variance method from the moments of every tile's pixels."""
    rows, cols = manifest.shape
    offsets = np.stack([a.offset.reshape(-1) for a in used])
    read_noise = np.stack([a.read_noise.reshape(-1) for a in used])
    usable = arrays["usable"]
    # Left-out pixels (no usable frames) get no moments: NaN estimates, not converged.
    mean, var, n = (
        np.where(usable, arrays[k].T, np.nan if k != "n" else 0) for k in ("mean", "var", "n")
    )
    grid = lambda a: np.asarray(a).reshape(np.shape(a)[:-1] + (rows, cols))  # noqa: E731
    labels = _labels(used)
    setpoints = [a.em_gain_setpoint for a in used]
    if method == "mv-adu":
        fit = mv.fit_mv_adu(mean, var, offsets, read_noise, n)
        ds = result.make_dataset(
            method=method,
            setpoints=[1.0],
            levels=labels,
            e_per_adu=grid(fit.e_per_adu),
            e_per_adu_se=grid(fit.e_per_adu_se),
            em_gain=np.ones((1, rows, cols)),
            em_gain_se=np.zeros((1, rows, cols)),
            photoelectrons=grid(fit.photoelectrons),
            photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=("level", "row", "col"),
            converged=grid(fit.valid & usable),
            manifest_hash=manifest.content_hash,
            manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"e_per_adu": (grid(fit.e_per_adu_lower), grid(fit.e_per_adu_upper))}
    else:
        phi = phi_map.ravel()
        fit = mv.fit_mv_gain(
            mean,
            var,
            offsets,
            read_noise,
            n,
            phi,
            np.asarray(setpoints),
            e_per_adu_se=None if phi_se is None else phi_se.ravel(),
            em_model=model,
        )
        by_level = len(set(setpoints)) == 1 and len(setpoints) > 1
        ds = result.make_dataset(
            method=method,
            setpoints=[float(s) for s in fit.setpoints],
            levels=labels if by_level else None,
            e_per_adu=phi_map,
            e_per_adu_se=np.full((rows, cols), np.nan) if phi_se is None else phi_se,
            em_gain=grid(fit.em_gain),
            em_gain_se=grid(fit.em_gain_se),
            photoelectrons=grid(fit.photoelectrons),
            photoelectrons_se=grid(fit.photoelectrons_se),
            photoelectrons_dims=(("level" if by_level else "setpoint"), "row", "col"),
            converged=grid(
                (np.all(fit.valid, axis=0) if np.ndim(fit.valid) > 1 else fit.valid) & usable
            ),
            manifest_hash=manifest.content_hash,
            manifest_path=str(manifest.path.resolve()),
        )
        bounds = {"em_gain": (grid(fit.em_gain_lower), grid(fit.em_gain_upper))}
    bounds["photoelectrons"] = grid(fit.photoelectrons_lower), grid(fit.photoelectrons_upper)
    # Ratios of sample moments: Fieller bounds, valid where the slope is poorly determined
    # (and defined where the estimate is not), unlike estimate ± 1.96 SE.
    _add_interval_vars(
        ds,
        bounds,
        "Fieller",
        "Fieller, 95 %, from the photon-transfer fit, conditional on the offset/read-noise maps",
    )
    ds.attrs["standard_errors"] = "from the photon-transfer fit, conditional on the offset maps"
    return ds
