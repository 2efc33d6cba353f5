"""The likelihood engine: a series of acquisitions, a block of pixels, one optimiser.

Every likelihood method of the paper (Table 2) is a *parameter layout* over this engine
(:mod:`emccdcal.fit.layouts`): which of the per-acquisition parameters — photoelectrons E,
EM gain g, ADU conversion factor φ — are free, shared across acquisitions or fixed. The
engine only sees a per-pixel vector ``x`` of free parameters and the layout's map from
``x`` to each acquisition's ``(ln E, ln g, ln φ)``.

For each acquisition the exact log-likelihood of a pixel is ``Σ_k n_k ln p(k)`` over its
histogram (:mod:`emccdcal.data.stats`), with ``p`` the noise model of :mod:`emccdcal.model.noise`
evaluated on one FFT window per pixel, batched over the block. One more inverse FFT per
parameter gives the scores (each value's derivatives), hence the outer-product
information; the gradient and the second derivatives are needed only summed against
the data, which one forward FFT of the data's weights gives for every parameter and
pair (Parseval).

Optimisation is Newton's with Levenberg–Marquardt damping
(:func:`emccdcal._optimize.maximize`), vectorised over pixels: the observed information
from the start, kept while the steps gain what they promised (the trials between need
the gradient alone, which the same Parseval sum gives), the outer product of the
per-frame scores (BHHH) where it is not positive definite, or a prior's kink or a
comb's ripples make it change too fast; each iteration evaluates only the pixels that
have not converged, there is no Python loop over pixels. Standard errors come from the
inverse observed information at the optimum.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from .. import _xp
from .._optimize import declined_step, invert_information, maximize, positive_definite
from ..model import noise

__all__ = [
    "AcquisitionBlock",
    "FitResult",
    "Layout",
    "Parameter",
    "QUANTITIES",
    "fit",
    "objective",
]

# Values whose model probability is below this fraction of the pixel's peak are beyond
# what the FFT resolves (round-off ~1e-16 of the peak): they count at this floor, with
# zero gradient, and are reported as ``n_floored`` (cosmic rays, hot events).
_FLOOR = 1e-14


@dataclass
class AcquisitionBlock:
    """The data of one acquisition for a block of P pixels.

    Attributes
    ----------
    values, counts : ndarray, shape (P, K), or None
        Histogram of each pixel's counts (ADU values, and frames at each; padding has
        count 0), as :class:`emccdcal.data.stats.PixelHistograms`; None in a block of
        the model alone (:func:`emccdcal.fit.scores.expected_information` needs no data).
    offset, read_noise : ndarray, shape (P,)
        S0 and σ maps (ADU).
    poisson_normal : bool
        True for the 1× acquisition (no EM multiplication).
    mean, var : ndarray, shape (P,), or None
        Moments of the counts (ADU, ADU²), for starting values.
    n : ndarray, shape (P,), or None
        Frames used.
    offset_var, read_noise_var : ndarray, shape (P,), optional
        Variance of the S0 and σ maps themselves (ADU²), from the dark frames they were
        estimated from; ``None`` for exact maps.
    map_group : hashable, optional
        Acquisitions with the same group share one pair of maps (one dark stack), so their
        map errors are the same draw.
    em_model : noise.EMModel
        The register model of a multiplied acquisition (by default the package's,
        :data:`emccdcal.defaults.DEFAULT_EM_MODEL`).
    """

    values: np.ndarray
    counts: np.ndarray
    offset: np.ndarray
    read_noise: np.ndarray
    poisson_normal: bool
    mean: np.ndarray
    var: np.ndarray
    n: np.ndarray
    offset_var: np.ndarray | None = None
    read_noise_var: np.ndarray | None = None
    map_group: object = None
    em_model: noise.EMModel = noise.EMModel()
    #: The histogram on the device where the fit computes, (xp, dev, values, counts):
    #: moved there once per fit (:meth:`on_device`) and carried along by :meth:`take`.
    resident: tuple | None = field(default=None, init=False, compare=False, repr=False)

    def on_device(self, xp, dev, name):
        """The block's ``"values"`` or ``"counts"`` (as floats) as an array of ``xp`` on
        ``dev``: moved from the host the first time in a fit, then kept, since the data
        do not change while the parameters do."""
        if _xp.is_numpy_namespace(xp):
            return self.values if name == "values" else self.counts.astype(float)
        if self.resident is None or self.resident[:2] != (xp, dev):
            counts = None if self.counts is None else self.counts.astype(float)
            values = _xp.on(xp, dev, self.values)
            self.resident = (xp, dev, values, None if counts is None else _xp.on(xp, dev, counts))
        return self.resident[2] if name == "values" else self.resident[3]

    @property
    def has_map_errors(self) -> bool:
        """Whether the offset or read-noise map carries a variance of its own."""
        return self.offset_var is not None or self.read_noise_var is not None

    def take(self, idx):
        """The block restricted to pixels ``idx``."""
        sub = lambda a: None if a is None else a[idx]  # noqa: E731
        resident = None
        if self.resident is not None:  # the rows taken on the device, no data moved
            xp, dev, values, counts = self.resident
            rows = _xp.on(xp, dev, np.arange(len(self.offset))[idx])
            taken = [None if a is None else xp.take(a, rows, axis=0) for a in (values, counts)]
            resident = (xp, dev, *taken)
        block = AcquisitionBlock(
            sub(self.values),
            sub(self.counts),
            self.offset[idx],
            self.read_noise[idx],
            self.poisson_normal,
            sub(self.mean),
            sub(self.var),
            sub(self.n),
            sub(self.offset_var),
            sub(self.read_noise_var),
            self.map_group,
            self.em_model,
        )
        block.resident = resident
        return block


#: The per-acquisition quantities, in the order of the layouts' log-parameters.
QUANTITIES = ("photoelectrons", "em_gain", "e_per_adu")


@dataclass(frozen=True)
class Parameter:
    """One free parameter of a layout: the logarithm of ``quantity`` (one of
    :data:`QUANTITIES`) of acquisition ``acquisition``, or shared by the acquisitions
    that use it (``acquisition`` None)."""

    quantity: str
    acquisition: int | None = None

    @property
    def name(self) -> str:
        """``ln_<quantity>`` or ``ln_<quantity>[a]``: for messages and tables only."""
        tail = "" if self.acquisition is None else f"[{self.acquisition}]"
        return f"ln_{self.quantity}{tail}"


@dataclass
class Layout:
    """A parameter layout: free parameters ``x`` (P, F) → per-acquisition log-parameters.

    ``matrix`` (A, 3, F) and ``constant`` (P, A, 3) map the free parameters linearly:
    ``(ln E, ln g, ln φ)[a] = constant[:, a] + matrix[a] @ x``. A layout with a prior
    (the hierarchical gain series) overrides :meth:`log_prior`.

    Attributes
    ----------
    parameters : list of Parameter
        The free parameters (F).
    lower, upper : ndarray, shape (F,)
        Bounds on ``x``.
    """

    parameters: list[Parameter]
    lower: np.ndarray
    upper: np.ndarray
    matrix: np.ndarray
    constant: np.ndarray
    #: False where the likelihood ripples (a photoelectron comb's aliases, 1/E apart in
    #: ln φ): a kept information, or a step taken unevaluated, could cross to another
    #: ripple. Such a layout, and one with a prior, steps by the outer product's
    #: information anew at every trial (:attr:`newton_steps`).
    smooth: bool = True

    def subset(self, idx):
        """The layout restricted to pixels ``idx`` (per-pixel constants follow them)."""
        return replace(self, constant=self.constant[idx])

    @property
    def n_free(self) -> int:
        return len(self.parameters)

    @property
    def names(self) -> list[str]:
        """The parameters' names (``ln_em_gain[1]`` …), for messages and tables."""
        return [p.name for p in self.parameters]

    def index(self, quantity: str, acquisition: int | None = None) -> int | None:
        """The free parameter that sets ``quantity`` of ``acquisition`` (own or shared),
        or, without an acquisition, the shared one; None where the layout fixes it."""
        if acquisition is None:
            return next(
                (j for j, p in enumerate(self.parameters) if p == Parameter(quantity)), None
            )
        moves = np.flatnonzero(self.matrix[acquisition, QUANTITIES.index(quantity)])
        return int(moves[0]) if moves.size == 1 else None

    def native(self, x):
        """Log-parameters (P, A, 3) and their Jacobian (P, A, 3, F)."""
        logs = self.constant + np.einsum("ajf,pf->paj", self.matrix, x)
        jac = np.broadcast_to(self.matrix, (x.shape[0],) + self.matrix.shape)
        return logs, jac

    @property
    def newton_steps(self) -> bool:
        """Whether :func:`fit` takes Newton's steps with a kept observed information:
        where the likelihood is :attr:`smooth` and the layout has no prior of its own
        (the hierarchical norm's curvature changes too fast near its kink)."""
        return self.smooth and type(self).log_prior is Layout.log_prior

    def log_prior(self, x):
        """Log prior density (P,), gradient (P, F) and Hessian (P, F, F); flat here."""
        P, F = x.shape
        return np.zeros(P), np.zeros((P, F)), np.zeros((P, F, F))


@dataclass
class FitResult:
    """Per-pixel outcome of :func:`fit`.

    Attributes
    ----------
    x : ndarray, shape (P, F)
        Free parameters at the optimum.
    cov : ndarray, shape (P, F, F)
        Covariance of ``x``: the inverse observed information (with a prior: the sandwich
        H⁻¹ I H⁻¹, or the layout's own ``estimator_covariance`` where it has one), plus
        what the errors of the offset and read-noise maps add where the blocks give their
        variances; NaN where the information is not positive definite.
    loglik : ndarray, shape (P,)
        Log-likelihood at the optimum, nats (without the prior).
    converged : ndarray of bool, shape (P,)
        Optimiser converged and the information is positive definite.
    iterations : ndarray of int, shape (P,)
    n_floored : ndarray of int, shape (P,)
        Frames whose probability was below the resolvable floor (outliers).
    loglik_per_acquisition : ndarray, shape (P, A)
    objective : ndarray, shape (P,)
        Log-likelihood plus log prior at the optimum (the maximised function), nats.
    """

    x: np.ndarray
    cov: np.ndarray
    loglik: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    n_floored: np.ndarray
    loglik_per_acquisition: np.ndarray = field(default=None)
    objective: np.ndarray = field(default=None)


class _ModelAtData:
    """The pmf of each pixel of a block at its histogram's values, with derivatives,
    computed in the namespace ``xp`` (its arrays; ``hopeless`` is NumPy's).

    Attributes
    ----------
    pv : array, shape (P, K)
        Probabilities at the values, floored at ``_FLOOR`` of the pixel's peak.
    scores : dict or None
        name -> (P, K) first derivatives of the probability at the values (None without
        ``score_windows``; in single precision with ``rough_scores``).
    first : dict
        name -> :class:`noise.Spectrum` of the first derivatives, where ``score_windows``
        is False or ``rough_scores`` True: their sums against weights
        (:meth:`spectral_sums`), exact.
    second : dict
        (name, name) -> :class:`noise.Spectrum` of the second derivatives (upper triangle).
    flat : array of int, shape (P·K,)
        Index of every value in the flattened (P, n) window.
    xp : namespace
        Where the windows were computed (``pv``, ``scores``, ``low`` are its arrays).
    n : int
        Window length.
    low : array of bool, shape (P, K)
        Values below the floor (no gradient there).
    hopeless : ndarray of bool, shape (P,)
        Pixels whose parameters are hopelessly far from their data.
    """

    def __init__(
        self,
        acq,
        rows,
        *,
        derivs=False,
        second=False,
        names=None,
        xp=None,
        score_windows=True,
        rough_scores=False,
    ):
        # The model's mass lies within [lo, hi] (eight SDs and the tails, outside of
        # which the pmf is below ~1e-15 of its peak).
        lo, hi = noise.window_extent(rows, acq.offset, acq.read_noise, width=8.0)
        # undefined parameters (a trial's NaN) hopeless by this test, not by a CPU's cast
        defined = np.isfinite(lo) & np.isfinite(hi)
        lo = np.floor(np.where(defined, lo, 0.0)).astype(np.int64)
        hi = np.ceil(np.where(defined, hi, 0.0)).astype(np.int64)
        first, last = acq.values[:, 0], acq.values.max(axis=1)
        # The FFT gives the pmf wrapped with period n: at a datum k, p(k) + Σ p(k ± jn).
        # Those aliases lie beyond [lo, hi] for every datum once n ≥ hi − first and
        # n ≥ last − lo, wherever the window starts: it starts at the first datum, which
        # makes n the data's span plus one margin, not plus the model's on both sides.
        start = first
        stop = first + np.maximum(last - first, np.maximum(hi - first, last - lo))
        # A trial step far from the data can ask for an enormous window; such parameters
        # are hopeless anyway: they get log-likelihood -inf (the step is refused) and a
        # window of bounded size.
        span = last - first + 1
        limit = first - 8 * span - 64 * np.ceil(acq.read_noise).astype(np.int64) - 64
        hopeless = ~defined | (np.minimum(first, lo) < limit)
        hopeless |= stop - start > 32 * span + 256 * np.ceil(acq.read_noise) + 512
        start = np.where(hopeless, limit, start)
        stop = np.where(hopeless, last + 8 * span + 64, stop)
        n = noise.fast_len(int((stop - start).max()) + 1)
        names = rows.names if names is None else names
        xp, dev = _xp.resolve("cpu") if xp is None else xp
        # an undefined row's window is NaN and unused (its likelihood −inf): no warning
        quiet = np.errstate(all="ignore") if not defined.all() else contextlib.nullcontext()
        with quiet:
            p, d1, d2 = noise.window(
                rows,
                acq.offset - start,
                acq.read_noise,
                n,
                derivs=derivs,
                second=second,
                names=names,
                xp=(xp, dev),
                first_spectra=rough_scores or not score_windows,
            )
        P, K = acq.values.shape
        # One flat gather per window (faster than take_along_axis, which rebuilds indices),
        # its index made where the data are: only the window starts (P,) move.
        values = acq.on_device(xp, dev, "values")
        origin = _xp.on(xp, dev, (np.arange(P) * n - start).astype(np.int64))
        self.flat = xp.reshape(values + origin[:, None], (-1,))

        def at_values(window):
            return xp.reshape(xp.take(xp.reshape(window, (-1,)), self.flat), (P, K))

        pv = at_values(p)
        floor = _FLOOR * xp.max(p, axis=1, keepdims=True)
        self.low = pv < floor
        self.pv = xp.where(self.low, floor, pv)
        windows = derivs and score_windows
        if windows and rough_scores:  # windows from the spectra, in single precision
            self.scores = {nm: at_values(d1[nm].window(single=True)) for nm in names}
        else:
            self.scores = {nm: at_values(d1[nm]) for nm in names} if windows else None
        self.first = d1 if derivs and (rough_scores or not score_windows) else {}
        self.second, self.n, self.hopeless, self.xp = d2, n, hopeless, xp

    def spectral_sums(self, weights):
        """``Σ_values weights · ∂p`` and ``Σ_values weights · ∂²p`` (P,) for every
        derivative held as a spectrum (``first`` by name, ``second`` by pair): one
        forward FFT of the weights placed on the window grid (values are distinct within
        a pixel; padding carries weight 0), then a dot with each spectrum (Parseval)."""
        spectra = {**self.first, **self.second}
        if not spectra:
            return {}
        xp = self.xp
        P = self.pv.shape[0]
        m = next(iter(spectra.values())).spectrum.shape[1]
        flat_weights = xp.reshape(weights, (-1,))
        hat = noise.Spectrum.weights_spectrum(self.flat, flat_weights, (P, self.n), m)
        return {key: spec.dot(hat) for key, spec in spectra.items()}


class _Terms(NamedTuple):
    """One acquisition's part of the log-likelihood (:func:`_acquisition_terms`), by the
    model's coordinates (U of them), per pixel (P)."""

    loglik: np.ndarray  # (P,)
    grad: np.ndarray | None = None  # (P, U), level ≥ 1
    #: (P, U, U): the outer product of the scores (BHHH) at level 1, None there without
    #: ``information``; the observed information at level 2
    info: np.ndarray | None = None
    n_floored: np.ndarray | None = None  # (P,)
    cross: np.ndarray | None = None  # (P, U, 2), with map_cross
    outer: np.ndarray | None = None  # (P, U, U): the outer product's, at level 2


def _acquisition_terms(
    acq, coords, level, map_cross=False, live=None, information=True, steps_only=False
):
    """Log-likelihood of one acquisition and its derivatives by its model coordinates.

    ``coords`` (U, P) are the logarithms of the model's own parameters
    (:func:`_native_to_model`): (ln E, ln scale) of the gamma and Poisson–normal models,
    (ln E, ln(1/φ), ln g) of the cascade. ``level`` 0: value only; 1: gradient and the
    outer-product (BHHH) information; 2: the observed information too. Without
    ``information`` (level 1) only the gradient, from the weights' spectrum (Parseval:
    one forward FFT instead of an inverse FFT per coordinate): for a step taken with an
    information already in hand. With ``map_cross`` (level ≥ 1) also the outer-product
    cross information of the coordinates with the (offset, read-noise) maps, (P, U, 2),
    for :func:`_map_covariance`, from the same windows. ``live`` (U,) says which
    coordinates the fit moves (default all): the others' derivatives, which the layout
    multiplies by zero (φ given in a gain series), are returned as zeros uncomputed,
    each one inverse FFT saved. With ``steps_only`` the information only steers an
    optimiser's steps (not an estimate's errors): its score windows are computed in
    single precision (about half the transforms' time; the information to about 1e-7),
    the gradient from the weights' spectrum, exact.
    Returns :class:`_Terms`.
    """
    values = [np.exp(c) for c in coords]
    U = len(values)
    rows = _register(acq).rows_at(values, acq.poisson_normal)
    kept = np.flatnonzero(np.ones(U, dtype=bool) if live is None else live)
    model_names = tuple(rows.names[i] for i in kept)
    names = model_names + (("offset", "read_noise") if map_cross else ())
    # The windows and their sums over the data run where the fit computes
    # (_xp.computing_on); what comes back is one number per pixel and sum.
    xp, dev = _xp.engine()
    windows = information or level >= 2
    rough = windows and steps_only and not map_cross
    model = _ModelAtData(
        acq,
        rows,
        derivs=level >= 1,
        second=level >= 2,
        names=names,
        xp=(xp, dev),
        score_windows=windows,
        rough_scores=rough,
    )
    pv, low = model.pv, model.low
    counts = acq.on_device(xp, dev, "counts")
    row_sum = lambda a: _xp.to_numpy(xp.sum(a, axis=1))  # noqa: E731
    loglik = np.where(model.hopeless, -np.inf, row_sum(counts * xp.log(pv)))
    n_floored = row_sum(xp.where(low, counts, 0.0)).astype(np.int64)
    if level == 0:
        return _Terms(loglik, None, None, n_floored)
    P, L = acq.values.shape[0], kept.size
    # (P, L) columns, also for L = 0 (a layout that moves none of this acquisition's)
    columns = lambda arrays: np.asarray(arrays, dtype=float).reshape(L, P).T  # noqa: E731
    factor = columns([values[i] for i in kept])  # d λ / d ln λ
    w = xp.where(low, 0.0, counts / pv)
    grad = np.zeros((P, U))
    # the sums of the derivatives held as spectra (the gradient's without score windows
    # or with rough ones, the second derivatives'): one forward FFT of the weights
    sums = {key: _xp.to_numpy(v) for key, v in model.spectral_sums(w).items()}
    if not windows:
        grad[:, kept] = columns([sums[nm] for nm in model_names]) * factor
        return _Terms(loglik, grad, None, n_floored)
    scores = [model.scores[nm] for nm in names]
    if rough:
        grad_k = columns([sums[nm] for nm in model_names]) * factor
    else:
        grad_k = columns([row_sum(w * s) for s in scores[:L]]) * factor
    # Outer products of the per-frame scores (BHHH): a positive semi-definite estimate of
    # the information from the data points alone, cheap because the histogram is short.
    ws = [w * s / pv for s in scores]
    outer = {(i, j): row_sum(ws[i] * scores[j]) for i in range(L) for j in range(i, len(names))}
    info_k = np.empty((P, L, L))
    for i in range(L):
        for j in range(i, L):
            info_k[:, i, j] = info_k[:, j, i] = outer[i, j] * factor[:, i] * factor[:, j]
    cross = None
    if map_cross:
        cross = np.zeros((P, U, 2))
        for i, u in enumerate(kept):
            cross[:, u] = np.stack([outer[i, L], outer[i, L + 1]], axis=1) * factor[:, i, None]
    grad[:, kept] = grad_k
    info = np.zeros((P, U, U))
    info[:, kept[:, None], kept[None, :]] = info_k
    if level < 2:
        return _Terms(loglik, grad, info, n_floored, cross)
    obs_k = np.empty((P, L, L))
    for i, a in enumerate(model_names):
        for j, b in enumerate(model_names[i:], start=i):
            h = (sums[(a, b)] - outer[i, j]) * factor[:, i] * factor[:, j]
            if i == j:  # d²/d(ln λ)² picks up λ · d/dλ
                h = h + grad_k[:, i]
            obs_k[:, i, j] = obs_k[:, j, i] = -h
    observed = np.zeros((P, U, U))
    observed[:, kept[:, None], kept[None, :]] = obs_k
    return _Terms(loglik, grad, observed, n_floored, cross, info)


def _register(acq):
    """The register model of an acquisition's rows (no multiplication at 1×)."""
    return acq.em_model.register.register_for(acq.poisson_normal)


def _native_to_model(logs, acq):
    """(ln E, ln g, ln φ) (P, 3) → the model's coordinates (U, P) and their matrix
    d coords / d(ln E, ln g, ln φ) (U, 3): linear for every model (the register's
    ``coordinates``)."""
    D = _register(acq).coordinates(acq.poisson_normal)
    return D @ logs.T, D


def _evaluate(layout, blocks, x, level, map_cross=False, information=True, steps_only=False):
    """Objective (log-likelihood + log prior), gradient and information in ``x``.

    Returns ``(objective, loglik, per_acq, grad, info, n_floored, cross, outer)``:
    ``info`` the observed information at level 2, the outer product's (BHHH) at level 1
    (None there without ``information``: the gradient alone); ``outer`` the outer
    product's at level 2 as well (else None); ``cross`` the list of each acquisition's
    map cross information (:func:`_acquisition_terms`), or None without ``map_cross``
    (only acquisitions whose maps have errors get one). ``steps_only``: the information
    is for an optimiser's steps only (:func:`_acquisition_terms`).
    """
    P, F = x.shape
    logs, jac = layout.native(x)
    total = np.zeros(P)
    per_acq = np.zeros((P, len(blocks)))
    grad = np.zeros((P, F))
    with_info = level >= 2 or (level == 1 and information)
    info = np.zeros((P, F, F)) if with_info else None
    outer = np.zeros((P, F, F)) if level >= 2 else None
    floored = np.zeros(P, dtype=np.int64)
    crosses = [] if map_cross else None
    for a, acq in enumerate(blocks):
        coords, D = _native_to_model(logs[:, a], acq)
        # u = the model's coordinates as a function of x through (ln E, ln g, ln φ);
        # those the layout holds fixed need no derivatives.
        j_u = _model_jacobian(jac, a, D)
        live = np.any(j_u != 0, axis=(0, 2))
        ll, g_u, i_u, nf, cross, outer_u = _acquisition_terms(
            acq, coords, level, map_cross and acq.has_map_errors, live, information, steps_only
        )
        per_acq[:, a] = ll
        total += ll
        floored += nf
        if map_cross:
            crosses.append(cross)
        if level == 0:
            continue
        grad += np.einsum("pu,puf->pf", g_u, j_u)
        if with_info:
            info += np.einsum("puf,puv,pvg->pfg", j_u, i_u, j_u)
        if outer is not None:
            outer += np.einsum("puf,puv,pvg->pfg", j_u, outer_u, j_u)
    lp, lp_grad, lp_hess = layout.log_prior(x)
    objective = total + lp
    if level >= 1:
        grad = grad + lp_grad
    if with_info:
        info = info - lp_hess
    if outer is not None:
        outer = outer - lp_hess
    return objective, total, per_acq, grad, info, floored, crosses, outer


def _model_jacobian(jac, a, D):
    """d(model coordinates)/dx (P, U, F) of acquisition ``a`` from the layout's Jacobian
    and the coordinates' matrix ``D`` (:func:`_native_to_model`)."""
    return np.einsum("uj,pjf->puf", D, jac[:, a])


def _map_covariance(layout, blocks, x, cov, crosses):
    """Covariance of ``x`` (P, F, F) caused by the errors of the offset and read-noise maps.

    The estimate moves with the maps by ``dx/dm = H⁻¹ ∂²ℓ/∂x∂m`` (implicit function theorem,
    ``H`` the observed information, ``cov = H⁻¹``); the cross term is estimated by the
    outer product of the per-frame scores, as the information is (``crosses``, from
    :func:`_evaluate` with ``map_cross``). Acquisitions that share a pair of maps
    (``map_group``) move together: their sensitivities add before squaring.
    """
    P, F = x.shape
    logs, jac = layout.native(x)
    groups: dict = {}
    for a, (acq, cross) in enumerate(zip(blocks, crosses)):
        if cross is None:
            continue
        j_u = _model_jacobian(jac, a, _native_to_model(logs[:, a], acq)[1])
        sens = np.einsum("pfg,pug,pum->pfm", cov, j_u, cross)  # dx/d(offset, read_noise)
        var = np.stack(
            [np.zeros(P) if v is None else v for v in (acq.offset_var, acq.read_noise_var)], axis=1
        )
        key = a if acq.map_group is None else acq.map_group
        total, _ = groups.get(key, (0.0, var))
        groups[key] = (total + sens, var)
    out = np.zeros((P, F, F))
    for sens, var in groups.values():
        out += np.einsum("pfm,pm,pgm->pfg", sens, var, sens)
    return out


def logpmf_at_values(layout, blocks, x):
    """ln p of every value each block holds (its counts unused) at ``x`` (P, F): a list
    of (P, K) arrays, one per acquisition, nats: the model the likelihood sums, at counts
    a fit has not seen (a parametric bootstrap's, :func:`emccdcal.fit.comb.bootstrap_errors`).
    """
    logs, _ = layout.native(x)
    out = []
    for a, acq in enumerate(blocks):
        coords, _ = _native_to_model(logs[:, a], acq)
        rows = _register(acq).rows_at([np.exp(c) for c in coords], acq.poisson_normal)
        out.append(np.log(_xp.to_numpy(_ModelAtData(acq, rows).pv)))
    return out


def objective(layout, blocks, x):
    """Log-likelihood plus the layout's log prior (P,) at ``x`` (P, F), nats: what
    :func:`fit` maximises."""
    return _evaluate(layout, blocks, x, 0)[0]


#: Nats: what the exact information's Newton step may still promise where single-precision
#: steps stopped (within 1.4e-5 SE of the optimum; exact steps land within ~1e-12).
LANDED = 1e-10


def fit(
    layout, blocks, x0, *, max_iter=100, tol=1e-7, progress=None, covariance=True, rough_steps=True
):
    """Maximise the likelihood (times the layout's prior) for every pixel of a block.

    Parameters
    ----------
    layout : Layout
        The method's parameter layout.
    blocks : list of AcquisitionBlock
        The acquisitions, each over the same P pixels.
    x0 : ndarray, shape (P, F)
        Starting values (e.g. from moments).
    max_iter : int
        Iteration limit; pixels still moving then are flagged not converged.
    tol : float
        Convergence when the predicted gain of the next step (Newton decrement ½ gᵀΔ) is
        below ``tol`` nats, or the step below 1e-10 in every free parameter.
    progress : callable, optional
        Called with the number of pixels that finished at each iteration.
    covariance : bool
        Compute the covariance, log-likelihoods and convergence at the optimum (the
        observed information); ``False`` returns the optimum ``x`` and the objective
        of the last point the optimiser evaluated (within ``tol`` of the optimum's
        with exact steps, ``rough_steps``), the other fields None: a starting point
        for another fit, or a profile's point, without the final evaluation.
    rough_steps : bool
        Steer Newton's steps by single-precision information (half the transforms'
        time). It is noise where data lie far in the model's tails (an outlier): a row
        the final, exact evaluation finds not converged, or not within :data:`LANDED`,
        is fitted again from ``x0`` with the exact information. Without ``covariance``
        nothing checks it: a caller whose objective must be the optimum's passes False.

    Returns
    -------
    FitResult
    """
    P = np.shape(x0)[0]
    # A library that compiles each array shape it meets (JAX) evaluates every row each
    # time (the rows that stopped at the last point tried for them): a few shapes
    # compiled once, not a set for every number of rows still moving.
    same_shapes = _xp.compiles_shapes(_xp.engine()[0])
    x_all = np.array(x0, dtype=float)

    # Newton's steps with the observed information, kept while the steps go well: from
    # the moments' start they converge in about two trials, where the outer product's
    # (BHHH) took four, and the trials between need the gradient alone. Where a prior's
    # curvature changes too fast to keep, or the likelihood ripples, a layout takes BHHH
    # steps with the information anew at every trial (Layout.newton_steps).
    newton = layout.newton_steps
    rough = newton and rough_steps

    def at_rows(rows, x, information):
        """(objective, gradient, information) of ``rows`` at ``x``. The information is
        the observed one where it is positive definite, else the outer product's (for a
        layout with a prior, always the outer product's); None without ``information``."""
        level = 2 if information and newton else 1
        # The information here only steers the steps (the final evaluation's is exact):
        # from single-precision windows where the steps are Newton's (their last one
        # lands on the optimum whichever path led there); not where the likelihood
        # ripples (single precision does not resolve its valleys), nor with a prior
        # (its outer-product steps stop where their path ends).
        how = dict(information=information, steps_only=rough)
        if rows.size == P:
            res = _evaluate(layout, blocks, x, level, **how)
        elif same_shapes:
            x_all[rows] = x
            whole = _evaluate(layout, blocks, x_all, level, **how)
            res = [r[rows] if isinstance(r, np.ndarray) else None for r in whole]
        else:
            part = [b.take(rows) for b in blocks]
            res = _evaluate(layout.subset(rows), part, x, level, **how)
        info = res[4]
        if level == 2:
            info = np.where(positive_definite(info)[:, None, None], info, res[7])
        return res[0], res[3], info

    def evaluate(rows, x, information=None):
        if information is None:  # a layout with a prior: every trial brings its own
            return at_rows(rows, x, True)
        if information.all() or not information.any() or same_shapes:
            return at_rows(rows, x, bool(information.any()))
        F = x.shape[1]
        obj, grad = np.empty(rows.size), np.empty((rows.size, F))
        info = np.full((rows.size, F, F), np.nan)  # only the rows asked for
        for part, with_info in ((information, True), (~information, False)):
            idx = np.flatnonzero(part)
            obj[idx], grad[idx], got = at_rows(rows[idx], x[idx], with_info)
            if with_info:
                info[idx] = got
        return obj, grad, info

    opt = maximize(
        evaluate,
        x0,
        lower=layout.lower,
        upper=layout.upper,
        tol=tol,
        max_iter=max_iter,
        progress=progress,
        keep_information=newton,
    )
    x = declined_step(opt, layout.lower, layout.upper) if newton else opt.x
    iterations = opt.iterations
    if not covariance:
        return FitResult(x, None, None, None, iterations, None, objective=opt.objective)
    map_errors = any(b.has_map_errors for b in blocks)
    # A pixel whose objective is not finite at its end (its data far from any model the
    # bounds allow, e.g. offsets above every count) has no information to compute: its
    # windows would be the largest of all, for a pixel that is not converged anyway.
    live = np.isfinite(opt.objective)
    if live.all():
        objective, loglik, per_acq, grad, obs, floored, crosses, _ = _evaluate(
            layout, blocks, x, 2, map_cross=map_errors
        )
    else:
        objective, loglik, per_acq, grad, obs, floored, crosses = _evaluate_rows(
            layout, blocks, x, live, map_errors
        )
    cov, pos_def = invert_information(obs)
    # With a prior (the hierarchical MAP) the frequentist covariance of the estimate is the
    # sandwich H⁻¹ I H⁻¹ of the penalised Hessian H and the likelihood's information I;
    # without one it is H⁻¹ itself.
    prior_hess = layout.log_prior(x)[2]
    h_inv = cov
    if hasattr(layout, "estimator_covariance"):  # a data-dependent prior knows its own
        cov = layout.estimator_covariance(blocks, x, np.nan_to_num(h_inv))
        cov[~pos_def] = np.nan
    elif np.any(prior_hess):
        cov = np.einsum("pfg,pgh,phk->pfk", cov, obs + prior_hess, cov)
    if map_errors and crosses is not None:
        cov = cov + _map_covariance(layout, blocks, x, np.nan_to_num(h_inv), crosses)
    gnorm = np.einsum("pf,pfg,pg->p", grad, np.nan_to_num(h_inv), grad)
    converged = opt.done & pos_def & (gnorm < 1e-4)
    if progress is not None:
        progress(int((~(opt.done | opt.stuck)).sum()))
    result = FitResult(x, cov, loglik, converged, iterations, floored, per_acq, objective)
    # Steered badly by single-precision information (hundreds of times too large where
    # data lie far in the tails): crawled, or stopped short; exact steps from the start.
    again = np.flatnonzero(live & (~converged | (0.5 * gnorm > LANDED)) & rough)
    if again.size:
        part, start = [b.take(again) for b in blocks], np.asarray(x0)[again]
        redo = fit(layout.subset(again), part, start, max_iter=max_iter, tol=tol, rough_steps=False)
        for name in ("x", "cov", "loglik", "converged", "n_floored", "objective"):
            getattr(result, name)[again] = getattr(redo, name)
        result.loglik_per_acquisition[again] = redo.loglik_per_acquisition
        result.iterations[again] += redo.iterations
    return result


def _evaluate_rows(layout, blocks, x, live, map_errors):
    """:func:`_evaluate` at level 2 of the rows ``live`` only; the others' values -inf,
    derivatives and information NaN, floored counts 0 (and no map cross information
    where no row is live)."""
    P, F = x.shape
    rows = np.flatnonzero(live)
    objective, loglik = np.full(P, -np.inf), np.full(P, -np.inf)
    per_acq = np.full((P, len(blocks)), -np.inf)
    grad, obs = np.full((P, F), np.nan), np.full((P, F, F), np.nan)
    floored = np.zeros(P, dtype=np.int64)
    crosses = None
    if rows.size:
        part = _evaluate(
            layout.subset(rows), [b.take(rows) for b in blocks], x[rows], 2, map_cross=map_errors
        )
        for whole, value in zip((objective, loglik, per_acq, grad, obs, floored), part):
            whole[rows] = value
        if part[6] is not None:
            crosses = []
            for c in part[6]:
                if c is None:
                    crosses.append(None)
                    continue
                full = np.full((P,) + c.shape[1:], np.nan)
                full[rows] = c
                crosses.append(full)
    return objective, loglik, per_acq, grad, obs, floored, crosses
