"""Pointwise evaluation of the noise model: every count under its own parameters.

Bead fitting (:mod:`emccdcal.beads.fit`) evaluates each pixel of each frame under its own
photoelectron mean: :func:`logpmf_rows` evaluates the counts of many parameter rows in
batched FFT windows, and :class:`LogpmfTable` tabulates log p as a smooth function of E
alone per pixel, exactly, for a fit that moves E only (docs/methods.md).
"""

from __future__ import annotations

import numpy as np

from .. import defaults
from ..errors import OptionError
from . import _engine
from .noise import _check_counts, _check_params, _evaluate_public, as_em_model, register_groups

__all__ = ["LogpmfTable", "logpmf_rows"]

#: Points of FFT windows evaluated together by :func:`logpmf_rows`; bounds its memory
#: (a few tens of bytes per point).
_ROWS_POINTS = 2**22


def logpmf_rows(
    counts,
    row,
    photoelectrons,
    em_gain,
    e_per_adu,
    offset,
    read_noise,
    *,
    grad=False,
    em_model=defaults.DEFAULT_EM_MODEL,
):
    """Log-pmf of counts, each under a parameter set picked by index (no broadcasting).

    :func:`logpmf` broadcasts its arguments and looks for repeated parameter sets among
    all of them; when the parameter sets are already known to be distinct (one per pixel
    and trial intensity, as in bead fitting) this is the direct route: the queries name
    their row, and the rows are evaluated in batches of bounded memory. The values are
    those of :func:`logpmf` (the same exact evaluator).

    Parameters
    ----------
    counts : array_like of int, shape (Q,)
        Raw counts S (ADU), non-negative integers.
    row : array_like of int, shape (Q,)
        Index of each count's parameter set, ``0 <= row < U``.
    photoelectrons, em_gain, e_per_adu, offset, read_noise : array_like, shape (U,)
        One parameter set per row, as in :func:`logpmf`: E (e⁻), g (1; exactly 1 selects
        the Poisson–normal model), φ (e⁻/ADU), S0 (ADU), σ (ADU).
    grad : bool, optional
        Also return ∂ ln p / ∂E (1/e⁻).
    em_model : str or EMModel, optional
        The register model, as in :func:`logpmf`.

    Returns
    -------
    logp : ndarray, shape (Q,)
        ln P(S = counts), nats.
    dlogp_dE : ndarray, shape (Q,)
        Only with ``grad``.

    Examples
    --------
    >>> lp = logpmf_rows([90, 100, 130], [0, 0, 1], [10.0, 10.0], [1.0, 1.0], [3.5, 3.5],
    ...                  [100.0, 100.0], [10.0, 10.0])
    >>> [f"{v:.10e}" for v in np.exp(lp)]
    ['1.7503385211e-02', '3.8157156576e-02', '1.0291887305e-03']
    """
    k = _check_counts(counts).ravel()
    idx = np.asarray(row).ravel()
    params = [
        np.atleast_1d(a).ravel()
        for a in _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    ]
    U = max(a.size for a in params)
    if any(a.size not in (1, U) for a in params):
        raise OptionError(
            "photoelectrons, em_gain, e_per_adu, offset and read_noise must "
            "have one value per row (or a single value)"
        )
    E, g, phi, S0, sigma = (np.broadcast_to(a, (U,)) for a in params)
    if idx.shape != k.shape:
        raise OptionError(f"row has {idx.size} entries but counts has {k.size}")
    if idx.size and (idx.dtype.kind not in "iu" or idx.min() < 0 or idx.max() >= U):
        raise OptionError(f"row must hold integer indices from 0 to {U - 1}")
    model = as_em_model(em_model)
    logp = np.empty(k.size)
    dE = np.empty(k.size) if grad else None
    if k.size == 0:
        return (logp, dE) if grad else logp
    order = np.argsort(idx, kind="stable")
    used, first = np.unique(idx[order], return_index=True)
    bounds = np.append(first, order.size)
    length = _window_lengths(E[used], g[used], phi[used], S0[used], sigma[used], model)
    # Consecutive runs of used rows whose windows add up to at most _ROWS_POINTS.
    cum = np.cumsum(length)
    starts = [0]
    while starts[-1] < used.size:
        base = cum[starts[-1] - 1] if starts[-1] else 0
        stop = int(np.searchsorted(cum, base + _ROWS_POINTS, side="right"))
        starts.append(max(stop, starts[-1] + 1))
    cic = np.zeros(U)
    for a, b in zip(starts[:-1], starts[1:]):
        r = used[a:b]
        q = order[bounds[a] : bounds[b]]
        local = np.repeat(np.arange(b - a), np.diff(bounds[a : b + 1]))
        lp, d = _evaluate_public(
            E[r], g[r], phi[r], S0[r], sigma[r], cic[r], local, k[q], model, grad=grad
        )
        logp[q] = lp
        if grad:
            dE[q] = d["photoelectrons"]
    return (logp, dE) if grad else logp


def _window_lengths(E, g, phi, S0, sigma, model):
    """Length (counts) of the window that covers each row's distribution."""
    length = np.zeros(g.shape, dtype=np.int64)
    for register, part in register_groups(g, model):
        if part.any():
            rows = register.rows(E[part], g[part], phi[part], np.zeros(int(part.sum())))
            length[part] = _engine.window_start(rows, S0[part], sigma[part])[1]
    return length


#: Smallest photoelectron value a :class:`LogpmfTable` covers (e⁻); below, E is clamped.
TABLE_MIN_PHOTOELECTRONS = 1e-3


def _table_layout(e_lo, e_hi):
    """Chebyshev nodes and variable per pixel for ranges [e_lo, e_hi] (e⁻).

    Returns the number of nodes and whether the variable is ln E (else √E). Measured
    (tests/test_noise_pointwise.py): in √E, 16 nodes keep |Δ ln p| below 1e-7 for ranges
    up to a factor 4 in E and 24 up to a factor 40; wider ranges reach down to where
    p(S | E) ∝ E^n for a few-electron count (ln p ~ n ln E, singular in √E at 0) and use
    ln E, with 32 nodes up to a factor 1e5 and 48 beyond.
    """
    ratio = e_hi / np.maximum(e_lo, TABLE_MIN_PHOTOELECTRONS)
    nodes = np.select([ratio <= 4.0, ratio <= 40.0, ratio <= 1e5], [16, 24, 32], 48)
    return nodes, ratio > 40.0


class LogpmfTable:
    """ln p(S_q | E) of fixed counts S_q as smooth functions of E, exact to ~1e-8 nats.

    In a fit of a model of the intensities (a bead's image), every pixel has its own
    count, noise parameters and trial intensity E, which changes at every iteration. The
    counts are data, fixed during the fit: for each one, ln p(S | E) is an analytic
    function of E over the pixel's plausible range ``[e_lo, e_hi]``. It is tabulated at
    Chebyshev nodes in √E by the exact evaluator (:func:`logpmf_rows`, each pixel's own
    g, φ, offset and read noise) and interpolated: ln p, ∂/∂E and ∂²/∂E² then cost a
    few dozen multiply-adds per count. Ranges wider than a factor 40 are tabulated in
    ln E instead of √E (a count far in the tail of a dim pixel has ln p ~ n ln E near
    E = 0). Interpolation error is below 1e-7 nats (typically
    1e-9, the exact evaluator's own accuracy) inside the ranges; outside, E is clamped
    to the range and the query flagged, so that the caller can widen the range
    (:meth:`set_range`) and evaluate again.

    Parameters
    ----------
    counts : array_like of int, shape (Q,)
        Raw counts (ADU).
    pixel : array_like of int, shape (Q,)
        Index of each count's pixel, ``0 <= pixel < K``.
    e_lo, e_hi : array_like, shape (K,)
        Range of E per pixel (e⁻), ``0 <= e_lo < e_hi``.
    em_gain, e_per_adu, offset, read_noise : array_like, shape (K,)
        Each pixel's noise parameters, as in :func:`logpmf` (``em_gain == 1``: PN).
    em_model : str or EMModel, optional
        The register model, as in :func:`logpmf`.

    Examples
    --------
    >>> t = LogpmfTable([700, 3000], [0, 1], [100.0, 100.0], [300.0, 300.0],
    ...                 [1.0, 25.0], [3.859, 3.859], [587.0, 587.0], [15.5, 15.5])
    >>> lp, d1, d2, outside = t.evaluate(np.array([150.0, 200.0]))
    >>> from emccdcal.model.noise import logpmf
    >>> bool(np.allclose(lp, logpmf([700, 3000], [150.0, 200.0], [1.0, 25.0], 3.859,
    ...                              587.0, 15.5), atol=1e-7))
    True
    """

    def __init__(
        self,
        counts,
        pixel,
        e_lo,
        e_hi,
        em_gain,
        e_per_adu,
        offset,
        read_noise,
        *,
        em_model=defaults.DEFAULT_EM_MODEL,
    ):
        self.em_model = as_em_model(em_model)
        self.counts = _check_counts(counts).ravel()
        self.pixel = np.asarray(pixel).ravel()
        if self.pixel.shape != self.counts.shape:
            raise OptionError(
                f"pixel has {self.pixel.size} entries but counts has {self.counts.size}"
            )
        params = [
            np.atleast_1d(a).astype(float).ravel()
            for a in _check_params(1.0, em_gain, e_per_adu, offset, read_noise)[1:]
        ]
        K = max(a.size for a in params)
        self.em_gain, self.e_per_adu, self.offset, self.read_noise = (
            np.broadcast_to(a, (K,)).copy() for a in params
        )
        if self.pixel.size and (
            self.pixel.dtype.kind not in "iu" or self.pixel.min() < 0 or self.pixel.max() >= K
        ):
            raise OptionError(f"pixel must hold integer indices from 0 to {K - 1}")
        self.u_lo = np.zeros(K)
        self.u_hi = np.zeros(K)
        self.degree = np.zeros(K, dtype=int)
        self.log = np.zeros(K, dtype=bool)
        self.coef = np.zeros((16, self.counts.size))
        self.set_range(np.arange(K), e_lo, e_hi)

    def _to_e(self, x, pix):
        return np.where(self.log[pix], np.exp(x), x**2)

    @property
    def e_range(self):
        """Per-pixel range (e_lo, e_hi) of E covered, e⁻."""
        pix = np.arange(self.u_lo.size)
        return self._to_e(self.u_lo, pix), self._to_e(self.u_hi, pix)

    def set_range(self, pixels, e_lo, e_hi):
        """(Re)tabulate the counts of ``pixels`` over new ranges ``[e_lo, e_hi]`` (e⁻)."""
        pixels = np.atleast_1d(np.asarray(pixels))
        lo = np.broadcast_to(np.asarray(e_lo, float), pixels.shape)
        hi = np.broadcast_to(np.asarray(e_hi, float), pixels.shape)
        if not (
            np.all(np.isfinite(lo))
            and np.all(np.isfinite(hi))
            and np.all(lo >= 0)
            and np.all(hi > lo)
        ):
            raise OptionError("table ranges must be finite with 0 <= e_lo < e_hi (e-)")
        lo = np.maximum(lo, TABLE_MIN_PHOTOELECTRONS)
        hi = np.maximum(hi, 2.0 * lo)
        self.degree[pixels], self.log[pixels] = _table_layout(lo, hi)
        lg = self.log[pixels]
        self.u_lo[pixels] = np.where(lg, np.log(lo), np.sqrt(lo))
        self.u_hi[pixels] = np.where(lg, np.log(hi), np.sqrt(hi))
        D = int(self.degree.max())
        if self.coef.shape[0] < D:
            self.coef = np.concatenate(
                [self.coef, np.zeros((D - self.coef.shape[0], self.coef.shape[1]))]
            )
        chosen = np.zeros(self.degree.size, dtype=bool)
        chosen[pixels] = True
        q = np.flatnonzero(chosen[self.pixel])
        if q.size == 0:
            return
        # Distinct (pixel, count) pairs; each is tabulated at its pixel's nodes.
        # (one integer key per pair: np.unique along an axis sorts rows, far slower)
        span = np.int64(self.counts.max()) + 1
        key, inv = np.unique(
            self.pixel[q].astype(np.int64) * span + self.counts[q], return_inverse=True
        )
        pix, cnt = key // span, key % span
        coef = np.zeros((self.coef.shape[0], pix.size))
        for d in np.unique(self.degree[pix]):
            sel = np.flatnonzero(self.degree[pix] == d)
            px_d, first = np.unique(pix[sel], return_inverse=True)
            t = np.cos(np.pi * (np.arange(d) + 0.5) / d)
            mid = 0.5 * (self.u_lo[px_d] + self.u_hi[px_d])
            half = 0.5 * (self.u_hi[px_d] - self.u_lo[px_d])
            x = mid[:, None] + half[:, None] * t[None, :]
            nodes_E = np.where(self.log[px_d][:, None], np.exp(x), x**2).ravel()
            rows = np.repeat(px_d, d)
            query_row = (first[:, None] * d + np.arange(d)[None, :]).ravel()
            values = logpmf_rows(
                np.repeat(cnt[sel], d),
                query_row,
                nodes_E,
                self.em_gain[rows],
                self.e_per_adu[rows],
                self.offset[rows],
                self.read_noise[rows],
                em_model=self.em_model,
            ).reshape(sel.size, d)
            # Chebyshev coefficients from values at first-kind nodes (a DCT-II).
            m = np.arange(d)
            basis = np.cos(np.pi * np.outer(m, np.arange(d) + 0.5) / d) * (2.0 / d)
            basis[0] *= 0.5
            coef[:d, sel] = basis @ values.T
        self.coef[:, q] = coef[:, inv.ravel()]

    def evaluate(self, photoelectrons, index=None):
        """ln p and its first two derivatives by E at the given intensities.

        Parameters
        ----------
        photoelectrons : ndarray, shape (n,)
            E (e⁻) of each query.
        index : ndarray of int, shape (n,), optional
            Which counts (positions in ``counts``) the values of ``photoelectrons`` belong
            to; default all, in order.

        Returns
        -------
        logp : ndarray, shape (n,)
            ln p(S | E), nats (at the clamped E where outside).
        dlogp : ndarray, shape (n,)
            ∂ ln p / ∂E, 1/e⁻.
        d2logp : ndarray, shape (n,)
            ∂² ln p / ∂E², 1/e⁻².
        outside : ndarray of bool, shape (n,)
            E was outside its pixel's range and was clamped to it.
        """
        E = np.asarray(photoelectrons, dtype=float)
        coef = self.coef if index is None else self.coef[:, index]
        pix = self.pixel if index is None else self.pixel[index]
        lo, hi, lg = self.u_lo[pix], self.u_hi[pix], self.log[pix]
        e_lo, e_hi = self._to_e(lo, pix), self._to_e(hi, pix)
        outside = (E < e_lo * (1 - 1e-12)) | (E > e_hi * (1 + 1e-12)) | ~np.isfinite(E)
        Ec = np.clip(np.nan_to_num(E, nan=0.0), e_lo, e_hi)
        u = np.clip(np.where(lg, np.log(Ec), np.sqrt(Ec)), lo, hi)
        half = 0.5 * (hi - lo)
        t = (u - 0.5 * (hi + lo)) / half
        # T_m, T'_m, T''_m by their three-term recurrences, summed as they go.
        T0, T1 = np.ones_like(t), t
        D0, D1 = np.zeros_like(t), np.ones_like(t)
        S0_, S1 = np.zeros_like(t), np.zeros_like(t)
        f = coef[0] + coef[1] * t
        ft = coef[1].copy()
        ftt = np.zeros_like(t)
        for m in range(2, coef.shape[0]):
            T2 = 2.0 * t * T1 - T0
            D2 = 2.0 * T1 + 2.0 * t * D1 - D0
            S2 = 4.0 * D1 + 2.0 * t * S1 - S0_
            c = coef[m]
            f += c * T2
            ft += c * D2
            ftt += c * S2
            T0, T1, D0, D1, S0_, S1 = T1, T2, D1, D2, S1, S2
        # Chain rule: t = (x − mid)/half with x = √E or ln E.
        dx = np.where(lg, 1.0 / Ec, 0.5 / u)  # dx/dE
        d2x = np.where(lg, -1.0 / Ec**2, -0.25 / u**3)  # d²x/dE²
        d1 = ft / half * dx
        d2 = ftt / half**2 * dx**2 + ft / half * d2x
        return f, d1, d2, outside
