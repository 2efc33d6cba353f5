"""A tile of the sensor and what a worker executes (:func:`run_tile`): the tile's rows read once into per-pixel histograms and the statistics of the data-quality checks, its pixels fitted in blocks on threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .. import _xp
from ..data import quality, stats
from ..data.manifest import Manifest, read_manifest
from ..data.stacks import read_band
from ..errors import (
    InputError,
)
from ..fit.series import acquisition_models, fit_series
from ..defaults import METHODS
from ..model import noise

if TYPE_CHECKING:
    pass


#: Methods that hold φ (e⁻/ADU) fixed at a given value, and those that estimate it.
ESTIMATE_E_PER_ADU = ("mv-adu", "is-adu")
FIXED_E_PER_ADU = tuple(m for m in METHODS if m not in ESTIMATE_E_PER_ADU)

#: Names of the per-acquisition statistics a tile returns for the data-quality checks.
_QUALITY = "quality"


def _load(manifest):
    if isinstance(manifest, Manifest):
        return manifest
    return read_manifest(manifest)


def _labels(acqs):
    return [a.level if a.level is not None else a.name for a in acqs]


# --------------------------------------------------------------------------------------
# Tiles
# --------------------------------------------------------------------------------------
def plan_tiles(n_pixels: int, tile_pixels: int, block_size: int) -> list[tuple[int, int]]:
    """Ranges of pixels ``(first, stop)`` (C order) of whole blocks, about ``tile_pixels`` each.

    A pixel is fitted with the same block of pixels whatever the tiles, so the result
    does not depend on them: tiles are made of whole blocks of ``block_size``.

    Examples
    --------
    >>> plan_tiles(20, 8, 4)
    [(0, 8), (8, 16), (16, 20)]
    """
    step = max(1, int(tile_pixels) // int(block_size)) * int(block_size)
    return [(p, min(n_pixels, p + step)) for p in range(0, n_pixels, step)]


@dataclass(frozen=True)
class TileJob:
    """One tile of a calibration (a range of pixels) with everything needed to compute it.

    Plain data (picklable): a Dask worker runs :func:`run_tile` on it, reading the rows
    that hold the tile's pixels from the stacks' paths. Maps are those of the tile's
    pixels, shape (A, pixels).
    """

    pixels: tuple[int, int]
    cols: int
    method: str
    frames: tuple[tuple[str, int], ...]  # (path, skip_frames) per acquisition
    setpoints: tuple[float, ...]
    labels: tuple[str, ...]
    offsets: np.ndarray
    read_noise: np.ndarray
    e_per_adu: np.ndarray | None
    dark_frames: tuple
    map_groups: tuple
    adc_max: int
    options: dict | None
    intervals: str
    block_size: int
    threads: int
    checks: bool
    fft_threads: int | None = None
    e_per_adu_se: np.ndarray | None = None
    em_model: noise.EMModel = noise.EMModel()
    device: str | None = None

    @property
    def key(self) -> str:
        """Name of the tile in a run's store."""
        return f"pixels-{self.pixels[0]:09d}-{self.pixels[1]:09d}"

    @property
    def n_pixels(self) -> int:
        """Pixels of the tile."""
        return self.pixels[1] - self.pixels[0]


def run_tile(job: TileJob, progress=None) -> dict:
    """Read, summarise and fit one tile; ``progress(n)`` is told of every n pixels done.

    Returns
    -------
    dict of ndarray
        Per pixel of the tile (C order), pixels first: ``usable`` (every acquisition has
        two or more unsaturated frames that are not all equal, and a read noise above 0:
        a dark that changes), ``n_saturated`` (P, A);
        for the mean–variance methods the moments ``mean``, ``var``, ``n`` (P, A); for the
        likelihood methods the estimates (``photoelectrons``, ``em_gain``, ``e_per_adu``
        with ``_se`` and bounds, (P, A)), ``loglik``, ``gof_pvalue`` (P, A),
        ``converged``, ``n_floored``, ``iterations`` and the hyperparameters of
        ``gs-hierarchical``. With ``checks``, ``quality<a>_<name>`` are the
        :func:`emccdcal.data.quality.band_statistics` of acquisition ``a``.
    """
    p0, p1 = job.pixels
    r0, r1 = p0 // job.cols, -(-p1 // job.cols)  # the rows that hold the tile's pixels

    mean_variance = job.method.startswith("mv-")

    def read(a):
        path, skip = job.frames[a]
        band = read_band(path, r0, r1, skip)
        own = band.reshape(band.shape[0], 1, -1)[:, :, p0 - r0 * job.cols : p1 - r0 * job.cols]
        q = (
            quality.band_statistics(own, job.adc_max, third=job.setpoints[a] == 1)
            if job.checks
            else None
        )
        # The likelihood methods histogram each block's pixels as they fit it (the
        # threads then share the work evenly); the mean–variance methods need moments.
        data = _histograms(job, a, own) if mean_variance else own
        return data, stats.frame_usage(own, job.adc_max), q

    with ThreadPoolExecutor(max_workers=max(1, min(job.threads, len(job.frames)))) as pool:
        read_back = list(pool.map(read, range(len(job.frames))))
    out = {"n_saturated": np.stack([n_sat for _, (_, n_sat), _ in read_back], axis=1)}
    for a, (_, _, q) in enumerate(read_back):
        for name, value in (q or {}).items():
            out[f"{_QUALITY}{a}_{name}"] = value
    usable = np.all([u for _, (u, _), _ in read_back], axis=0)
    usable &= np.all(job.read_noise > 0, axis=0)  # a dark that never changes: stuck
    if job.e_per_adu is not None:  # a chained φ is NaN where its own fit failed
        usable &= np.isfinite(job.e_per_adu)
    out["usable"] = usable
    fitted = np.flatnonzero(usable)
    data = [d for d, _, _ in read_back]
    del read_back
    if mean_variance:
        for name in ("mean", "var", "n"):
            out[name] = np.stack([getattr(h, name) for h in data], axis=1)
    else:
        out.update(_fit_pixels(job, data, fitted, progress))
    if progress is not None:  # the pixels not fitted here (all of them for mean-variance)
        progress(job.n_pixels - (0 if mean_variance else fitted.size))
    return out


def _histograms(job, a, frames):
    """:func:`emccdcal.data.stats.histograms` of acquisition ``a``'s frames; bad counts
    are one line naming the file and the acquisition."""
    try:
        return stats.histograms(frames, adc_max=job.adc_max)
    except InputError as exc:
        raise InputError(f"'{job.frames[a][0]}' ({job.labels[a]}): {exc}") from None


def _bounds_of(method, intervals):
    """Interval bounds of a likelihood result: (kind, description), or None."""
    if intervals == "profile":
        comb = (
            "; Wald on the log scale where rival ripples of the photoelectron comb set "
            "the error of e_per_adu (their deviance does not follow chi-squared)"
            if method == "is-adu"
            else ""
        )
        return (
            "profile-likelihood",
            "profile likelihood, 95 %, widened by the errors of the offset and "
            "read-noise maps where the standard errors include them" + comb,
        )
    if method == "gs-hierarchical":
        return (
            "unpooled",
            "95 %, of the same model without the prior (each set-point its own E): "
            "Wald on the log scale, profile likelihood where that is unreliable; "
            "the MAP's own ± 1.96 SE reflect its shrinkage",
        )
    return None


def _fit_pixels(job, frames, usable, progress=None):
    """The likelihood fit of the pixels ``usable`` of a tile, from each acquisition's
    ``frames`` (F, 1, P); NaN (not converged) elsewhere."""
    P, A = job.n_pixels, len(frames)
    out = {
        k: np.full((P, A), np.nan)
        for k in (
            "photoelectrons",
            "photoelectrons_se",
            "em_gain",
            "em_gain_se",
            "e_per_adu",
            "e_per_adu_se",
            "gof_pvalue",
            "acquisition_loglik",
        )
    }
    out.update(
        loglik=np.full(P, np.nan),
        converged=np.zeros(P, dtype=bool),
        n_floored=np.zeros(P, dtype=np.int64),
        iterations=np.zeros(P, dtype=np.int64),
    )
    if job.method == "gs-hierarchical":
        out.update(
            hyper_photoelectrons=np.full(P, np.nan), hyper_sd_photoelectrons=np.full(P, np.nan)
        )

    def fit_block(idx):
        models = acquisition_models(
            job.setpoints,
            job.offsets[:, idx],
            job.read_noise[:, idx],
            job.em_model,
            job.dark_frames,
            job.map_groups,
        )
        sub = lambda v: None if v is None else v[idx]  # noqa: E731
        # the histograms, the fit and its checks, each FFT on the CPUs the tile's
        # threads leave it
        with _xp.computing_on(job.device, fft_workers=job.fft_threads):
            hists = [_histograms(job, a, f[:, :, idx]) for a, f in enumerate(frames)]
            return idx, fit_series(
                job.method,
                models,
                hists,
                e_per_adu=sub(job.e_per_adu),
                e_per_adu_se=sub(job.e_per_adu_se),
                options=job.options,
                intervals=job.intervals,
            )

    chunks = [usable[s : s + job.block_size] for s in range(0, usable.size, job.block_size)]
    # Blocks are independent: threads overlap them (NumPy and the FFT release the GIL),
    # and the result does not depend on how many there are.
    with ThreadPoolExecutor(max_workers=max(1, job.threads)) as pool:
        for idx, e in pool.map(fit_block, chunks):
            for k, v in e.items():
                out.setdefault(k, np.full((P, A), np.nan))[idx] = v
            if progress is not None:
                progress(idx.size)
    return out
