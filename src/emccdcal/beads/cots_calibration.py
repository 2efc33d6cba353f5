"""Calibration-on-the-spot on a bead manifest: every bead at every EM set-point, as a result.

:func:`cots_calibrate` finds the beads once, runs :func:`emccdcal.beads.cots.cots_spot` on
each at every set-point above 1, and writes a result in the calibration contract
(``docs/results.md``): g = G·φ in the beads' ROI pixels. ``emccdcal cots MANIFEST -o OUT``
is the command line; ``docs/cots.md`` describes the method.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np

from .. import result
from .._util import check_number, e_per_adu_map
from .._util import progress as progress_bar
from ..data.manifest import Manifest, read_manifest
from ..errors import BeadWarning, InputError, ManifestError, OptionError
from ..fit.series import choose_register
from ..model import noise, psf
from .cots import DEFAULT_HALF_SIZE, DEFAULT_WIDTH, MIN_FRAMES, cots_spot

if TYPE_CHECKING:
    import xarray

__all__ = ["cots_calibrate", "register_gain", "format_summary"]


def _phi_map(manifest):
    if manifest.e_per_adu is None:
        raise ManifestError(
            f"{manifest.path}: COTS needs e_per_adu (e-/ADU) to turn its gain in ADU per "
            "photoelectron into the EM gain g = G·e_per_adu; set e_per_adu in the manifest "
            "(a number or a map file)"
        )
    return e_per_adu_map(manifest.e_per_adu, manifest.shape)


def cots_calibrate(
    manifest,
    *,
    half_size=DEFAULT_HALF_SIZE,
    width=DEFAULT_WIDTH,
    em_model=None,
    stages=None,
    progress=True,
    out=None,
) -> xarray.Dataset:
    """COTS on every bead of a bead manifest, as a calibration result.

    Beads are found once, with :func:`emccdcal.model.psf.find_beads` on the offset-subtracted
    mean image of the acquisition at the highest set-point, and the same beads are used
    at every set-point. For every bead and every acquisition with ``em_gain_setpoint > 1``,
    :func:`cots_spot` runs on a (2Δ + 1)² ROI centred on the bead's brightest pixel (the
    ROI follows the spot if it moves). Acquisitions at set-point 1 are not analysed: the
    EM gain there is 1 by contract.

    Parameters
    ----------
    manifest : str, Path or :class:`emccdcal.Manifest`
        The TOML manifest of the bead stacks; it must give ``e_per_adu`` (e⁻/ADU).
    half_size : int
        ROI half-width Δ (pixel): the ROI is (2Δ + 1) × (2Δ + 1) pixels and a bead needs
        Δ pixels on every side and no other bead within 2Δ + 1 pixels.
    width : float
        Expected PSF standard deviation (pixel): for bead finding and as the fit's start.
    em_model : {"cascade", "gamma"} or EMModel, optional
        The EM register whose excess-noise factor F² turns the slope of variance against
        mean into the gain: the exact Bernoulli cascade (F² below 2 at low gain: 1.795 at
        5× for 536 stages) or the gamma model (F² = 2, COTS as published). Default as for
        :func:`emccdcal.calibrate`: the manifest's, else the cascade.
    stages : int, optional
        The cascade's stages: default the manifest's ``register_stages``, else the camera
        model's where known, else 536.
    progress : bool
        A progress bar (default): in a notebook or on a terminal; none in a pipe.
    out : str or Path, optional
        Directory to write ``calibration.nc`` and ``summary.json`` into.

    Returns
    -------
    xarray.Dataset
        The calibration result (``docs/results.md``, method ``"cots"``). In each bead's
        ROI pixels: ``em_gain`` = G·φ per set-point (1 with SE 0 at set-point 1, everywhere)
        and ``photoelectrons`` = (mean counts − dark offset)/G, the mean photoelectrons
        per pixel per frame with COTS's gain and the manifest's offset map (NaN at
        set-point 1); NaN outside the beads, where ``converged`` is False. ``converged``
        is True in the ROI of a bead with a usable COTS estimate at every set-point > 1. ``e_per_adu`` is the manifest's φ (SE 0). The per-bead table (dims
        ``bead``, ``setpoint``): ``bead_row``, ``bead_col``, ``cots_gain_adu_per_e``,
        ``cots_offset``, ``cots_em_gain`` (each with ``_se``), ``cots_spot_photoelectrons``,
        ``cots_width``, ``cots_frames_used``.

    Raises
    ------
    emccdcal.InputError
        No ``e_per_adu``; no acquisition above set-point 1; an acquisition with fewer than
        :data:`MIN_FRAMES` frames; no beads found. One line naming the file.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> beads = emccdcal.simulate_beads(tempfile.mkdtemp(), beads=6, seed=1)  # doctest: +SKIP
    >>> ds = emccdcal.cots(beads.manifest)  # doctest: +SKIP
    >>> ds.em_gain.dims  # doctest: +SKIP
    ('setpoint', 'bead')
    """
    return result.run_recorded(
        lambda: _cots_calibrate(manifest, half_size, width, em_model, stages, progress), out
    )


def _cots_calibrate(manifest, half_size, width, em_model, stages, progress):
    if not isinstance(manifest, Manifest):
        manifest = read_manifest(manifest)
    model, stages_source = choose_register(em_model, stages, manifest)
    half_size = int(half_size)
    if half_size < 1:
        raise OptionError(f"half_size must be a positive integer (pixel), got {half_size}")
    width = check_number("width", width, positive=True)  # the PSF's SD, px
    phi = _phi_map(manifest)
    em = [a for a in manifest.acquisitions if a.em_gain_setpoint > 1]
    if not em:
        raise ManifestError(
            f"{manifest.path}: COTS needs an acquisition with em_gain_setpoint > 1 (found "
            "only 1x); it measures the gain of the EM register"
        )
    for a in em:
        if a.n_frames < MIN_FRAMES:
            raise InputError(
                f"{a.frames_path}: {a.n_frames} frame(s) to use; COTS needs at least "
                f"{MIN_FRAMES} frames of the beads"
            )
    ref = max(em, key=lambda a: a.em_gain_setpoint)
    beads = _find_beads(ref, width, half_size)
    setpoints = list(manifest.setpoints)
    spots = _fit_spots(
        manifest, em, beads, setpoints, half_size, width, phi, model.register, progress
    )
    maps, table, ok_bead = _estimates(
        spots, beads, setpoints, phi, manifest.shape, half_size, model.register
    )
    if not ok_bead.any():
        raise InputError(
            f"{manifest.path}: COTS gave no usable estimate for any of the {len(beads)} "
            "bead(s) at every set-point (see the warnings)"
        )
    converged = np.zeros(manifest.shape, bool)
    for r, c in beads[ok_bead]:
        converged[r - half_size : r + half_size + 1, c - half_size : c + half_size + 1] = True
    return result.make_dataset(
        method="cots",
        setpoints=[float(s) for s in setpoints],
        e_per_adu=phi,
        e_per_adu_se=0.0,
        em_gain=maps["em_gain"],
        em_gain_se=maps["em_gain_se"],
        photoelectrons=maps["photoelectrons"],
        photoelectrons_se=maps["photoelectrons_se"],
        photoelectrons_dims=("setpoint", "row", "col"),
        converged=converged,
        manifest_hash=manifest.content_hash,
        manifest_path=str(manifest.path.resolve()),
        extra=_bead_variables(beads, table),
        attrs={
            **result.identity_attrs(manifest),
            "half_size": half_size,
            "width": float(width),
            "bead_frames": str(ref.frames_path),
            **model.attrs,
            **({"register_stages_source": stages_source} if stages_source else {}),
        },
    )


def _find_beads(ref, width, half_size) -> np.ndarray:
    """The beads (row, col) on the offset-subtracted mean image of ``ref``."""
    mean = np.mean(ref.frames(), axis=0, dtype=float) - ref.offset
    found = psf.find_beads(mean, width=width, half_size=half_size)
    if len(found.positions) == 0:
        raise InputError(
            f"{ref.frames_path}: no beads found on the mean image (threshold "
            f"{found.threshold:.3g} ADU above the background; {len(found.at_edge)} "
            f"candidate(s) too near the edge, {len(found.too_close)} too close to another, "
            f"for --half-size {half_size})"
        )
    if len(found.at_edge) or len(found.too_close):
        warnings.warn(
            f"{ref.frames_path}: {len(found.at_edge)} bead(s) too near the edge and "
            f"{len(found.too_close)} too close to another were left out",
            stacklevel=4,
            category=BeadWarning,
        )
    return found.positions


def _fit_spots(manifest, em, beads, setpoints, half_size, width, phi, register, progress) -> dict:
    """COTS on every bead of every multiplied acquisition: per set-point index, a list of
    (bead index, :class:`~emccdcal.beads.cots.CotsSpot`, the offset map in the bead's box).
    The bias correction takes the darks' read noise and the ``register``'s cumulants."""
    rows, cols = manifest.shape
    size = 2 * half_size + 1
    margin = size  # the ROI may follow the spot this far
    per_sp: dict[int, list] = {}
    with progress_bar(enabled=progress, desc="cots", unit="fit", total=len(beads) * len(em)) as bar:
        for a in em:
            si = setpoints.index(a.em_gain_setpoint)
            frames = a.frames()
            for bi, (r, c) in enumerate(beads):
                r0, c0 = max(0, r - half_size - margin), max(0, c - half_size - margin)
                r1 = min(rows, r + half_size + 1 + margin)
                c1 = min(cols, c + half_size + 1 + margin)
                box = np.asarray(frames[:, r0:r1, c0:c1])
                roi = (r - half_size - r0, c - half_size - c0, size, size)
                try:
                    spot = cots_spot(
                        box,
                        roi=roi,
                        width=width,
                        adc_max=manifest.adc_max,
                        read_noise=a.read_noise[r0:r1, c0:c1],
                        register=register,
                        e_per_adu=phi[r, c],
                    )
                except ValueError as exc:
                    warnings.warn(
                        f"{a.frames_path}: bead at ({r}, {c}): {exc}",
                        stacklevel=4,
                        category=BeadWarning,
                    )
                    spot = None
                if spot is not None and spot.n_saturated:
                    warnings.warn(
                        f"{a.frames_path}: bead at ({r}, {c}): {spot.n_saturated} frame(s) "
                        f"with saturated pixels (>= {manifest.adc_max} ADU) left out",
                        stacklevel=4,
                        category=BeadWarning,
                    )
                if spot is not None:
                    dark = a.offset[
                        r - half_size : r + half_size + 1, c - half_size : c + half_size + 1
                    ]
                    per_sp.setdefault(si, []).append((bi, spot, dark))
                bar.update(1)
    return per_sp


#: Per-bead estimates in the table of :func:`_estimates`.
_TABLE_KEYS = (
    "gain",
    "gain_se",
    "offset",
    "offset_se",
    "em_gain",
    "em_gain_se",
    "spot_e",
    "width",
    "used",
)


def _estimates(per_sp, beads, setpoints, phi, shape, half_size, register):
    """Each bead's estimates per set-point (several acquisitions at one set-point combined
    by inverse-variance weights) as a table (bead, set-point), the maps of em_gain and
    photoelectrons over the beads' boxes, and the beads with an estimate at every
    multiplied set-point. The gain is the ``register``'s (:func:`register_gain`)."""
    S, B = len(setpoints), len(beads)
    table = {k: np.full((B, S), np.nan) for k in _TABLE_KEYS}
    maps = {
        k: np.full((S,) + tuple(shape), np.nan)
        for k in ("em_gain", "em_gain_se", "photoelectrons", "photoelectrons_se")
    }
    ok_bead = np.ones(B, bool)
    for si, sp in enumerate(setpoints):
        if sp == 1:
            maps["em_gain"][si], maps["em_gain_se"][si] = 1.0, 0.0
            continue
        by_bead: dict[int, list] = {}
        for bi, spot, dark in per_sp.get(si, []):
            by_bead.setdefault(bi, []).append((spot, dark))
        for bi in range(B):
            if bi not in by_bead:
                ok_bead[bi] = False
                continue
            r, c = beads[bi]
            g, g_se, s0, s0_se, spot_e, wid, used, pe_b, pe_b_se = _combine(
                by_bead[bi], lambda G, se, phi_rc=phi[r, c]: register_gain(register, G, se, phi_rc)
            )
            sl = np.s_[r - half_size : r + half_size + 1, c - half_size : c + half_size + 1]
            for key, value in zip(
                _TABLE_KEYS,
                (g, g_se, s0, s0_se, g * phi[r, c], g_se * phi[r, c], spot_e, wid, used),
            ):
                table[key][bi, si] = value
            maps["em_gain"][si][sl] = g * phi[sl]
            maps["em_gain_se"][si][sl] = g_se * phi[sl]
            maps["photoelectrons"][si][sl] = pe_b
            maps["photoelectrons_se"][si][sl] = pe_b_se
    return maps, table, ok_bead


def _bead_variables(beads, table) -> dict:
    """The per-bead variables of a COTS result (``make_dataset``'s ``extra``)."""
    bead_dims = ("bead", "setpoint")
    return {
        "bead_row": (
            ("bead",),
            beads[:, 0].astype(np.int64),
            "pixel",
            "sensor row of the bead's brightest pixel (ROI centre)",
        ),
        "bead_col": (
            ("bead",),
            beads[:, 1].astype(np.int64),
            "pixel",
            "sensor column of the bead's brightest pixel (ROI centre)",
        ),
        "cots_gain_adu_per_e": (
            bead_dims,
            table["gain"],
            "ADU/e-",
            "COTS system gain G (counts per photoelectron)",
        ),
        "cots_gain_adu_per_e_se": (
            bead_dims,
            table["gain_se"],
            "ADU/e-",
            "standard error of the COTS system gain G",
        ),
        "cots_offset": (bead_dims, table["offset"], "ADU", "COTS offset S0"),
        "cots_offset_se": (
            bead_dims,
            table["offset_se"],
            "ADU",
            "standard error of the COTS offset S0",
        ),
        "cots_em_gain": (
            bead_dims,
            table["em_gain"],
            "1",
            "COTS EM gain g = G * e_per_adu at the bead's pixel",
        ),
        "cots_em_gain_se": (
            bead_dims,
            table["em_gain_se"],
            "1",
            "standard error of the COTS EM gain g",
        ),
        "cots_spot_photoelectrons": (
            bead_dims,
            table["spot_e"],
            "e-",
            "mean fitted spot total N/G per frame",
        ),
        "cots_width": (bead_dims, table["width"], "pixel", "mean fitted PSF standard deviation"),
        "cots_frames_used": (
            bead_dims,
            table["used"],
            "1",
            "frames whose fits were usable (NaN: bead not analysed)",
        ),
    }


def register_gain(register, gain, gain_se, e_per_adu):
    """The system gain G (ADU/e⁻) of a register from COTS's F² = 2 estimate of it.

    COTS measures the slope of a pixel's variance against its mean, F²·G; read with
    F² = 2 it gives ``gain`` = F²·G/2. The register's own F² depends on its gain g = G·φ:
    g solves g·F²(g) = 2·gain·φ (``register.gain_from_gain_f2``; for the gamma register
    F² = 2 and G = ``gain``), and the SE follows by the slope d(g F²)/dg.

    Parameters
    ----------
    register : a register of :mod:`emccdcal.model.noise` (``EMModel(...).register``)
    gain, gain_se : float
        COTS's G and its SE under F² = 2, ADU/e⁻.
    e_per_adu : float
        φ at the bead, e⁻/ADU.

    Returns
    -------
    (float, float)
        G and its SE, ADU/e⁻.

    Examples
    --------
    >>> from emccdcal.model.noise import EMModel
    >>> cascade = EMModel("cascade", 536).register
    >>> G, se = register_gain(cascade, 1.795203 * 5.0 / 3.859 / 2, 0.01, 3.859)
    >>> round(G * 3.859, 4), round(se, 5)  # g = 5, its F^2 = 1.795
    (5.0, 0.01005)
    """
    g, slope = register.gain_from_gain_f2(2.0 * gain * e_per_adu)
    g, slope = float(g), float(slope)
    return g / e_per_adu, 2.0 * gain_se / slope


def _combine(pairs, gain_of):
    """Combine the COTS estimates of one bead from one or more acquisitions.

    ``pairs`` holds (CotsSpot, dark offset map of the ROI); ``gain_of(G, se)`` turns
    COTS's F² = 2 system gain into the register's (:func:`register_gain`), before the
    photoelectrons are computed with it. Photoelectrons per pixel are (mean counts − dark
    offset)/G: COTS's own S0 absorbs the read noise (it is S0 − σ²/(F²G)) and is far
    less precise than the darks.
    """
    spots = [p[0] for p in pairs]
    excess = [p[0].mean_counts - p[1] for p in pairs]
    if len(spots) == 1:
        s = spots[0]
        g, g_se, s0, s0_se = s.gain, s.gain_se, s.offset, s.offset_se
        mean_excess, mean_se = excess[0], s.mean_counts_se
        spot_counts, wid, used = s.spot_counts, s.width, s.n_used
    else:
        wg = np.array([1 / s.gain_se**2 for s in spots])
        ws = np.array([1 / s.offset_se**2 for s in spots])
        g = float(np.sum(wg * [s.gain for s in spots]) / wg.sum())
        g_se = float(1 / np.sqrt(wg.sum()))
        s0 = float(np.sum(ws * [s.offset for s in spots]) / ws.sum())
        s0_se = float(1 / np.sqrt(ws.sum()))
        n = np.array([s.n_used for s in spots], float)
        mean_excess = np.sum([x * k for x, k in zip(excess, n)], axis=0) / n.sum()
        mean_se = (
            np.sqrt(np.sum([(s.mean_counts_se * k) ** 2 for s, k in zip(spots, n)], axis=0))
            / n.sum()
        )
        spot_counts = float(np.sum([s.spot_counts * k for s, k in zip(spots, n)]) / n.sum())
        wid = float(np.sum([s.width * k for s, k in zip(spots, n)]) / n.sum())
        used = int(n.sum())
    g, g_se = gain_of(g, g_se)
    pe = mean_excess / g
    var = (mean_se**2 + pe**2 * g_se**2) / g**2  # δpe = δS̄/G − pe·δG/G
    return (g, g_se, s0, s0_se, spot_counts / g, wid, used, pe, np.sqrt(np.maximum(var, 0)))


def format_summary(ds) -> str:
    """Per set-point: the bead-mean EM gain g ± its SE, and the bead-mean G and S0."""
    model = noise.EMModel.from_attrs(ds.attrs)
    lines = [
        (
            f"method cots: {int(np.isfinite(ds.bead_row.values).sum())} bead(s), "
            f"{ds.attrs.get('seconds', float('nan')):.1f} s, e_per_adu "
            f"{float(np.nanmedian(ds.e_per_adu.values)):.4f} e-/ADU"
            + ("" if model is None else f", register {model}")
        )
    ]
    for si, sp in enumerate(ds.setpoint.values):
        label = result.format_setpoint(sp)
        if sp == 1:
            lines.append(f"  {label}x: em_gain 1 (no multiplication; COTS not run)")
            continue
        g = ds.cots_em_gain.values[:, si]
        g_se = ds.cots_em_gain_se.values[:, si]
        ok = np.isfinite(g) & np.isfinite(g_se)
        if not ok.any():
            lines.append(f"  {label}x: no usable bead")
            continue
        k = int(ok.sum())
        mean_g = g[ok].mean()
        se_mean = np.sqrt(np.sum(g_se[ok] ** 2)) / k
        sd = g[ok].std(ddof=1) if k > 1 else float("nan")
        G = ds.cots_gain_adu_per_e.values[ok, si].mean()
        s0 = ds.cots_offset.values[ok, si].mean()
        lines.append(
            f"  {label}x: em_gain {mean_g:.4g} ± {se_mean:.2g} (mean of {k} bead(s), SD over "
            f"beads {sd:.2g}); G {G:.4g} ADU/e-, S0 {s0:.5g} ADU"
        )
    return "\n".join(lines)
