"""Checks of a whole manifest (:func:`check_manifest`): each acquisition's, the offset from the photon transfer, the findings in words and their weight, and the report (:func:`format_report`)."""

from __future__ import annotations

import math

import numpy as np

from ...errors import (
    DataQualityWarning,
    DriftWarning,
    Finding,
    InputError,
    ReadNoiseGrowthWarning,
    SaturationWarning,
)
from ..dark import check_read_noise_growth
from .drift import (
    DEFAULT_ALPHA,
    DEFAULT_DRIFT_THRESHOLD,
    DEFAULT_K,
    DRIFT_ALPHA,
    MIN_FRAMES,
    _MAD_TO_SD,
)
from .stacks import StackSummary, check_acquisition


# --------------------------------------------------------------------------------------
# Whole manifest
# --------------------------------------------------------------------------------------
def offset_from_transfer(acquisitions, summaries) -> dict | None:
    """Where the 1× levels' photon transfer says the offset is, against the offset maps.

    At 1× the excess variance is linear in the signal through the offset: var − σ² =
    (mean − S₀)/φ. A curve through each pixel's levels, fitted against ``mean − offset
    map``, therefore crosses zero excess variance where the map is wrong by ``shift`` ADU
    (positive: the true offset is above the map). The curve is a parabola, not a line: a
    steady lamp's small drift or an ADC's slight non-linearity bends the transfer at
    high signal, which would move a straight line's crossing by tens of ADU (93 ADU on
    the ProEM intensity series).

    Returns
    -------
    dict or None
        ``n_levels``, ``n_pixels``, ``shift`` (median over pixels, ADU), ``shift_se``
        (1.4826 MAD/√n), ``off`` (|shift| > 5 SE and > 1 ADU); None with fewer than 4
        set-point-1 acquisitions or 5 pixels.
    """
    idx = [i for i, a in enumerate(acquisitions) if float(a.em_gain_setpoint) == 1]
    if len(idx) < 4 or summaries[idx[0]].mean.size < 5:
        return None
    x = np.stack([summaries[i].mean - acquisitions[i].offset.ravel() for i in idx], axis=1)
    y = np.stack(
        [summaries[i].sd ** 2 - acquisitions[i].read_noise.ravel() ** 2 for i in idx], axis=1
    )
    scale = np.maximum(np.abs(x).max(axis=1, keepdims=True), 1.0)  # conditioning
    design = np.stack([np.ones_like(x), x / scale, (x / scale) ** 2], axis=2)  # (P, A, 3)
    try:
        coef = np.linalg.solve(
            np.einsum("pak,pal->pkl", design, design), np.einsum("pak,pa->pk", design, y)[..., None]
        )[..., 0]
    except np.linalg.LinAlgError:  # levels that do not differ
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = -coef[:, 0] / coef[:, 1] * scale[:, 0]  # first order: where y reaches 0
    shift = shift[np.isfinite(shift) & (coef[:, 1] > 0)]
    if shift.size < 5:
        return None
    med = float(np.median(shift))
    se = _MAD_TO_SD * float(np.median(np.abs(shift - med))) / math.sqrt(shift.size)
    return {
        "n_levels": len(idx),
        "n_pixels": int(shift.size),
        "shift": med,
        "shift_se": se,
        "off": bool(abs(med) > 5 * se and abs(med) > 1.0),
    }


def _fmt_pixels(pixels: list, n: int) -> str:
    shown = ", ".join(f"({r},{c})" for r, c in pixels[:5])
    return shown + (f" and {n - 5} more" if n > 5 else "")


def _steady_cell(d: dict) -> str:
    """The table's verdict with its reason: the rule is p below α and the size above the
    threshold, so a large drift with a large SE is steady and a smaller precise one not."""
    if d["drifts"]:
        return "NO"
    if d["pvalue"] < d["alpha"]:
        return f"yes: < {d['threshold_pct']:g} %"
    return f"yes: p ≥ {d['alpha']:.2g}"


def _drift_bias_pct(drift_pct: float, photoelectrons: float, multiplied: bool) -> float:
    """Bias (%) of the EM gain (``multiplied``) or of φ (at 1×) from a linear drift of E.

    A linear drift d (fraction) spreads E uniformly over E(1 ± d/2): variance E²d²/12
    added to the count's own, 2E for the multiplied Poisson count (in units of g²) and
    E at 1×. A fit of the histogram's shape reads it as EM gain, g(1 + E·d²/24), or at 1×
    as a smaller φ (e⁻/ADU), φ(1 − E·d²/12), to first order.
    """
    excess = photoelectrons * (drift_pct / 100.0) ** 2 / 12.0
    return 100.0 * (excess / 2.0 if multiplied else -excess)


def _leave_out(a: dict) -> str:
    """How to leave one acquisition out of a calibration (its manifest table)."""
    which = f'level = "{a["level"]}"' if a.get("level") else f'frames = "{a["frames"]}"'
    return f"delete its [[acquisition]] table ({which}) from the manifest and calibrate again"


#: How a drift finding says that its bias exceeds the estimate's standard error: of an
#: estimate pooled over levels (a check to make), or of the acquisition's own.
_MAY_NOT_STAND = "the result may not stand"
_DOES_NOT_STAND = "the result does not stand as it is"


def _doubtful(text: str) -> Finding:
    """A finding after which the result does not stand as it is (the verdict says so)."""
    return Finding(text, DataQualityWarning, doubtful=True)


def _drift_effect(a: dict) -> str:
    """What a drift of one acquisition does to the result, whether it stands, and the fix."""
    d = a["drift"]
    multiplied = a["em_gain_setpoint"] != 1
    E = a.get("photoelectrons_estimate")
    light = (
        (
            f"this acquisition's {E:.4g} e⁻ per pixel and frame"
            + (" (as fitted)" if a.get("photoelectrons_source") == "fit" else "")
        )
        if E
        else ""
    )
    if a.get("drift_absorbed") is False:
        return (
            "This method takes the estimates here from the acquisition's mean (φ given, "
            + ("the gain at 1× is 1)" if not multiplied else "E shared with the 1× light)")
            + ", which a drift does not move: the result stands, and the drift's spread "
            "only lowers this acquisition's goodness of fit"
            + (
                ""
                if not multiplied
                else ", provided the light's average was the same at every set-point (a source "
                "that drifts over the session breaks that: 'calibrate --method "
                "gs-hierarchical' fits the light of each set-point)"
            )
        )
    what = "EM gain g" if multiplied else "φ (e⁻/ADU)"
    head = "The estimate is the acquisition's average, and the drift's spread reads as noise: "
    if not E:
        return (
            head + f"{what} is biased by an amount that grows with the illumination; "
            "where that is below the estimate's standard error (the summary's ±) the "
            "result stands"
        )
    bias = _drift_bias_pct(d["drift_pct"], E, multiplied)
    head += f"{what} is biased by about {bias:+.2g} % at {light}"
    fix = (
        "steady the source (warm it up, stabilise its power) and record again, or leave "
        "this acquisition out: " + _leave_out(a)
    )
    rse = a.get("estimate_relative_se")
    if not rse:
        return (
            head + "; where that bias is below the estimate's standard error (the "
            f"summary's ±) the result stands; where not, {fix}"
        )
    times = abs(bias) / (100 * rse)
    se = f"{times:.2g} times its standard error ({100 * rse:.2g} % per pixel)"
    if a.get("level") is not None and not multiplied:
        # φ pools every level of an intensity series: this level biases it by its share
        return (
            head
            + f"; φ pools every level, so its bias is at most that, {se}: "
            + (
                "the result stands"
                if times < 1
                else f"{_MAY_NOT_STAND}: leave this acquisition out to see how far φ "
                f"moves ({_leave_out(a)}); if it moves beyond its standard error, steady "
                "the source and record again"
            )
        )
    return (
        head
        + f"; that is {se}, so "
        + ("the result stands" if times < 1 else f"{_DOES_NOT_STAND}: {fix}")
    )


def _findings(a: dict) -> list[str]:
    """Human-readable warnings of one acquisition's checks: what was found, whether the
    result stands, and what fixes it."""
    name = f"{a['name']} (set-point {a['em_gain_setpoint']:g})"
    d = a["drift"]
    out = []
    if d is None:
        out.append(
            f"{name}: {a['n_frames']} frames are too few for the drift test "
            f"(at least {MIN_FRAMES}); the illumination's steadiness is unchecked: the "
            f"result stands if the source was steady; record {MIN_FRAMES} frames or "
            "more to check it"
        )
    elif d["drifts"]:
        effect = _drift_effect(a)
        out.append(
            Finding(
                f"{name}: the frame mean drifts by {d['drift_pct']:+.2f} ± "
                f"{d['drift_pct_se']:.2f} % over the acquisition (p = {d['pvalue']:.1g}): "
                f"the illumination or the EM gain is not steady. {effect}.",
                DriftWarning,
                doubtful=_DOES_NOT_STAND in effect,
                caution=_MAY_NOT_STAND in effect,
            )
        )
    off = a.get("offset")
    if off and off["above_data"]:
        out.append(
            _doubtful(
                f"{name}: the offset map lies above the mean count of {off['n_below_offset']} of "
                f"{off['n_pixels']} pixels: it cannot be this data's offset (other units, another "
                "camera mode or read-out speed?), and nothing fitted from it stands: record darks "
                "in the read-out mode of these frames, give them as the acquisition's dark (or "
                "'emccdcal scan' a folder holding both) and calibrate again"
            )
        )
    mult = a.get("multiplication")
    if mult and mult["multiplied"]:
        out.append(
            _doubtful(
                f"{name}: the counts look EM-multiplied: their cumulant ratio κ₃κ₁/κ₂² is "
                f"{mult['R']:.2f} ± {mult['R_se']:.2f} over {mult['n_pixels']} pixels (1 for "
                "unmultiplied photoelectrons, 1.5 for multiplied ones): was the EM gain on for "
                "data labelled 1×? If so, the result does not stand (φ and every gain scaled by "
                "it are wrong): record the 1× "
                "acquisition with the EM gain off (or give this one its real em_gain_setpoint) "
                "and calibrate again"
            )
        )
    bad = a.get("frames_defective") or {}
    for kind, what in (
        (
            "constant",
            "have every pixel at one value (e.g. all zero): "
            "frames the camera or its software dropped",
        ),
        ("repeated", "repeat an earlier frame exactly: frames written twice"),
    ):
        if bad.get(f"n_{kind}"):
            shown = ", ".join(map(str, bad[kind])) + (", ..." if bad[f"n_{kind}"] > 10 else "")
            frames = bad[kind]
            # defects only at the start are skipped by the manifest; elsewhere the file
            # must be cut (or recorded again)
            leading = (
                len(frames) == bad[f"n_{kind}"]
                and frames[0] <= 1
                and frames == list(range(frames[0], frames[0] + len(frames)))
            )
            fix = (
                f"set skip_frames = {a.get('skip_frames', 0) + frames[-1] + 1} in its "
                "[[acquisition]] table and calibrate again"
                if leading
                else "remove them from the file (or record again) and calibrate again"
            )
            out.append(
                _doubtful(
                    f"{name}: {bad[f'n_{kind}']} of {a['n_frames']} frames {what} "
                    f"(frames {shown}); they bias every estimate, so the result does not "
                    f"stand as it is: {fix}"
                )
            )
    sat = a["saturation"]
    if sat["n_values"]:
        out.append(
            Finding(
                f"{name}: {sat['n_values']} saturated pixel-frames (counts ≥ {sat['adc_max']}, "
                f"{sat['fraction']:.2%} of its pixel-frames) in {sat['n_frames']} frames, "
                f"{sat['n_pixels']} pixels: {_fmt_pixels(sat['pixels'], sat['n_pixels'])}; "
                "they are excluded from fits, which cuts the top off those pixels' counts, so "
                "their photoelectrons and gain read low, the more the more of their frames hit "
                "the ceiling. Every other pixel's result stands; for these, lower the light (or "
                "the EM gain) until no frame saturates and record again",
                SaturationWarning,
            )
        )
    px = a["pixels"]
    for kind, what in (("hot", "above"), ("dead", "below")):
        if px[f"n_{kind}"]:
            out.append(
                f"{name}: {px[f'n_{kind}']} {kind} pixel(s), mean more than {px['k']:g} "
                f"robust SDs ({px['robust_sd']:.3g} ADU) {what} the median: "
                f"{_fmt_pixels(px[kind], px[f'n_{kind}'])}; each pixel is fitted on its "
                "own, so every other pixel's result stands; these pixels' own results are "
                "doubtful: do not use them unless they converged with standard errors like "
                "their neighbours'"
            )
    if px.get("n_telegraph"):  # a report of an older version has none
        out.append(
            f"{name}: {px['n_telegraph']} random-telegraph pixel(s), mean more than "
            f"{px['k']:g} robust SDs ({px['robust_sd']:.3g} ADU) from the median: "
            f"{_fmt_pixels(px['telegraph'], px['n_telegraph'])}; their offset jumps between "
            "states, so the dark's offset map is not this stack's (variable telegraph); "
            "these pixels' own results are doubtful, every other pixel's stands"
        )
    if px["n_stuck"]:
        out.append(
            f"{name}: {px['n_stuck']} stuck pixel(s) whose counts never change: "
            f"{_fmt_pixels(px['stuck'], px['n_stuck'])}; they have no result (NaN, "
            "converged = False); the others' results stand"
        )
    return out


def check_manifest(
    manifest,
    *,
    k: float = DEFAULT_K,
    drift_threshold: float = DEFAULT_DRIFT_THRESHOLD,
    drift_alpha: float = DRIFT_ALPHA,
    unit_root_tests: bool = False,
    alpha: float = DEFAULT_ALPHA,
    regression: str = "c",
    read_noise_threshold: float = 0.05,
    summaries: list[StackSummary] | None = None,
    fitted=None,
) -> dict:
    """Data-quality checks of every acquisition of a manifest, and of the read noise.

    Parameters
    ----------
    manifest : str, Path or Manifest
        The manifest file, or as :func:`emccdcal.read_manifest` returns it.
    k, drift_threshold, unit_root_tests, alpha, regression
        As in :func:`check_acquisition`.
    drift_alpha : float, optional
        Family-wise level of the drift tests over the acquisitions (default
        :data:`DRIFT_ALPHA`): each is tested at ``drift_alpha`` / number of acquisitions
        (Bonferroni), so a steady manifest gets a drift finding at most that often.
    read_noise_threshold : float, optional
        Relative growth of the median read noise over the lowest set-point that is
        reported (default 0.05), :func:`emccdcal.data.dark.check_read_noise_growth`.
    summaries : list of StackSummary, optional
        One per acquisition, in order, when the stacks were already read (a calibration
        accumulates them in its one pass over the data); default: read every stack.
    fitted : list, optional
        One per acquisition, in order: None, or what a calibration fitted there, a dict
        of ``photoelectrons`` (E, e⁻ per pixel and frame), ``absorbed`` (whether a
        drift's spread biases an estimate there) and ``relative_se`` (that estimate's,
        or None), which the findings then quote instead of the moments' rough E, and
        against which they weigh a drift's bias.

    Returns
    -------
    dict
        JSON-serialisable: ``manifest`` (path), ``adc_max``, ``acquisitions`` (name →
        :func:`check_acquisition`; a repeated name gets a ``#2``, ``#3`` … suffix),
        ``read_noise_growth`` (list of messages) and ``warnings`` (every finding as one
        human-readable string, in acquisition order, read-noise growth last).

    Raises
    ------
    ValueError
        From :func:`check_acquisition` (naming the file).

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> report = emccdcal.check(sim.manifest)
    >>> sorted(report["acquisitions"]), report["warnings"]
    (['10x', '1x'], [])
    """
    if not (0 < drift_alpha < 1):
        raise InputError(f"drift_alpha must be between 0 and 1, got {drift_alpha!r}")
    if not hasattr(manifest, "acquisitions"):  # its file, as every verb takes it
        from ..manifest import read_manifest

        manifest = read_manifest(manifest)
    acqs: dict[str, dict] = {}
    warn: list[str] = []
    per_test = drift_alpha / max(1, len(manifest.acquisitions))
    used = []
    for i, acq in enumerate(manifest.acquisitions):
        summary = (
            StackSummary.of_file(
                acq.frames_path,
                acq.skip_frames,
                manifest.adc_max,
                third=float(acq.em_gain_setpoint) == 1,
            )
            if summaries is None
            else summaries[i]
        )
        used.append(summary)
        res = check_acquisition(
            acq,
            manifest.adc_max,
            k=k,
            drift_threshold=drift_threshold,
            drift_alpha=per_test,
            unit_root_tests=unit_root_tests,
            alpha=alpha,
            regression=regression,
            summary=summary,
        )
        if fitted is not None and fitted[i] is not None:
            # the calibration's own estimates, where they are known
            res["photoelectrons_estimate"] = float(fitted[i]["photoelectrons"])
            res["photoelectrons_source"] = "fit"
            res["drift_absorbed"] = bool(fitted[i]["absorbed"])
            res["estimate_relative_se"] = fitted[i]["relative_se"]
        key, i = acq.name, 1
        while key in acqs:
            i += 1
            key = f"{acq.name}#{i}"
        acqs[key] = res
        warn.extend(_findings(res))
    transfer = offset_from_transfer(manifest.acquisitions, used)
    if transfer is not None and transfer["off"]:
        warn.append(
            _doubtful(
                f"set-point 1: the photon transfer of its {transfer['n_levels']} levels (variance "
                f"against mean) reaches zero excess variance {transfer['shift']:+.1f} ± "
                f"{transfer['shift_se']:.1f} ADU from the offset maps: the offsets are off by "
                "about that much (another camera mode's, or none?), which biases φ and E, so the "
                "result does not stand as it is: record darks in the read-out mode of the light "
                "frames, give them as the acquisitions' dark (or 'emccdcal scan' a folder holding "
                "both) and calibrate again"
            )
        )
    growth = check_read_noise_growth(
        [a.em_gain_setpoint for a in manifest.acquisitions],
        [a.read_noise for a in manifest.acquisitions],
        threshold=read_noise_threshold,
    )
    warn.extend(Finding(g, ReadNoiseGrowthWarning) for g in growth)
    return {
        "manifest": str(manifest.path),
        "adc_max": int(manifest.adc_max),
        "drift_alpha": float(drift_alpha),
        "acquisitions": acqs,
        "offset_from_transfer": transfer,
        "read_noise_growth": list(growth),
        "warnings": warn,
    }


def _p(p: float, bound: str | None = None) -> str:
    if math.isnan(p):
        return "n/a"
    if bound == "lower":
        return "≤0.01"
    if bound == "upper":
        return "≥0.1"
    return f"{p:.2g}" if p >= 1e-4 else "<1e-4"


def _threshold(report: dict) -> str:
    for a in report["acquisitions"].values():
        if a.get("drift") is not None:
            return f"{a['drift']['threshold_pct']:g}"
    return f"{DEFAULT_DRIFT_THRESHOLD:g}"


def format_report(report: dict) -> str:
    """A check report as a human-readable table followed by its warnings.

    Parameters
    ----------
    report : dict
        From :func:`check_manifest`.

    Returns
    -------
    str
        Multi-line text (no trailing newline).
    """
    unit_root = any(a["stationarity"] for a in report["acquisitions"].values())
    header: tuple[str, ...] = (
        "acquisition",
        "set-pt",
        "frames",
        "level ADU",
        "drift % ± SE",
        "p",
        "steady",
    )
    if unit_root:
        header += ("ADF p", "KPSS p")
    header += ("sat. values/frames/px", "hot", "dead", "stuck")
    # random-telegraph pixels beyond k, where a camera's darks found them (not hot or dead)
    strays = any(a["pixels"].get("n_telegraph") for a in report["acquisitions"].values())
    header += ("RTS",) if strays else ()
    rows: list[tuple[str, ...]] = [header]
    for name, a in report["acquisitions"].items():
        d, s, sat, px = a.get("drift"), a["stationarity"], a["saturation"], a["pixels"]
        if d is None and s is not None:  # a report of an earlier version: ADF/KPSS decided
            d = {**s, "pvalue": math.nan, "drifts": not s["stationary"]}
        if d is None:
            level, drift, p, steady = "n/a", "n/a", "n/a", "?"
        else:
            level = f"{d['level']:.1f}"
            drift = (
                "n/a"
                if d["drift_pct"] is None
                else f"{d['drift_pct']:+.2f} ± {d['drift_pct_se']:.2f}"
            )
            p, steady = _p(d["pvalue"]), _steady_cell(d)
        row: tuple[str, ...] = (
            name,
            f"{a['em_gain_setpoint']:g}",
            str(a["n_frames"]),
            level,
            drift,
            p,
            steady,
        )
        if unit_root:
            row += (
                ("n/a", "n/a")
                if s is None
                else (_p(s["adf_pvalue"]), _p(s["kpss_pvalue"], s["kpss_p_bound"]))
            )
        rows.append(
            row
            + (
                f"{sat['n_values']}/{sat['n_frames']}/{sat['n_pixels']}",
                str(px["n_hot"]) if px["tested"] else "n/a",
                str(px["n_dead"]) if px["tested"] else "n/a",
                str(px["n_stuck"]),
            )
            + ((str(px.get("n_telegraph", 0)),) if strays else ())
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = [f"Data-quality checks: {report['manifest']} (ADC maximum {report['adc_max']} ADU)"]
    if "drift_alpha" in report:
        each = next(
            (a["drift"]["alpha"] for a in report["acquisitions"].values() if a.get("drift")), None
        )
        lines.append(
            f"steady: no drift of at least {_threshold(report)} % significant at a "
            f"family-wise {100 * report['drift_alpha']:g} % over the acquisitions"
            + (
                ""
                if each is None
                else f" (each p must be below {each:.2g}: "
                "a large drift with a large SE can be steady, a smaller precise one "
                "not)"
            )
        )
    for j, r in enumerate(rows):
        cells = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))]
        lines.append("  ".join(cells).rstrip())
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    if report["warnings"]:
        lines.append("")
        lines.append(f"{len(report['warnings'])} finding(s):")
        lines.extend(f"- {w}" for w in report["warnings"])
    else:
        lines.append("")
        lines.append("No findings.")
    return "\n".join(lines)
