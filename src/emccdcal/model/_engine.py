"""The window engine: the pmf of a count from its cumulant generating function, for any
register model.

The count is ``S = S0 + X + ε``: an offset, the register's output ``X`` in ADU and a
Gaussian read-out ``ε ~ N(0, σ²)``. Its cumulant generating function is

    K(s) = s·S0 + σ²s²/2 + K_X(s),

and everything here is written in terms of that sum: the register model supplies only
``K_X`` (its *rows*, below); the offset, the read noise, the windows, the tilts, the FFTs
and the bookkeeping of which count is done live here, once.

A register's rows
-----------------
A register model hands the engine an object holding one parameter set per row (a
pixel, or a pixel and a trial intensity) with these pieces (see :mod:`._gamma` and
:mod:`._exact`; docs/architecture.md lists them for whoever adds a model):

``names``
    The native parameters of ``K_X`` it differentiates by, in order.
``pn``
    Rows without multiplication (Poisson–normal: a lattice, no exponential tail).
``trusted``
    A window value is trusted where it is at least this fraction of its window's peak.
``take(index)``
    The rows at ``index``.
``cgf(s, order, names)``
    ``K_X(s)`` at complex ``s`` (P, M) and its first and second derivatives by
    ``names`` (dicts; second derivatives keyed by ordered pairs, zeros omitted).
``real(t)``
    ``K_X``, ``K_X'``, ``K_X''`` at real tilts t (P,), and the tilted distribution's
    photoelectron mean and single-electron output (ADU), which set window sizes.
``band(E_t, theta_t, sigma, n)``
    DFT bins of a length-``n`` window beyond which the tilted transform is negligible
    (the engine widens it where the transform has not died out at its edge).
``saddlepoint(k, S0, sigma)``
    A tilt that centres the window on count k.
``direct_tail(sigma)``, ``tail(k, S0, sigma, grad)``
    Rows whose tail the register evaluates itself after the first window, and that
    evaluation (quadrature, a saddlepoint approximation) for queries beyond any window.
"""

from __future__ import annotations

import numpy as np

from .. import _xp
from .adc import cgf as rounding_cgf
from .adc import real_cgf as rounding_real_cgf
from .adc import rounds

#: Native parameters the engine itself adds to every register's: the Gaussian read-out's.
READOUT = ("offset", "read_noise")

#: A window's band ends where the tilted transform is below this (its values beyond are
#: below the FFT's round-off of ~1e-16 of the peak); a register's band that leaves more
#: at its edge is widened.
_EDGE = float(np.exp(-40.0))
#: Longest tilted window (counts) before the register's own tail evaluation takes over.
_MAX_WINDOW = 2**20


def cgf(rows, s, shift, sigma, order=0, names=(), same_rows=False):
    """K(s) of the count (P, M) relative to the window start, and its derivatives by
    ``names`` (the register's and :data:`READOUT`): ``(K, first, second)``. With
    ``same_rows`` every row of ``s`` is the same (an untilted window's frequencies)."""
    Ke, first, second = rows.cgf(s, order, tuple(n for n in names if n not in READOUT))
    rounding = rounds(rows.pn, sigma)
    shift, sigma = _xp.like(s, shift, sigma)
    K = s * shift[:, None] + 0.5 * (sigma[:, None] * s) ** 2 + Ke
    if rounding.any():  # the ADC's rounding: a parameter-free term (docs of :mod:`.adc`)
        # a function of the frequency alone: once for all rows where they share theirs
        K = K + _where_rows(s, rounding, rounding_cgf(s[:1] if same_rows else s))
    if order >= 1:
        first = {**first, "offset": s, "read_noise": sigma[:, None] * s * s}
    if order >= 2:
        second = {**second, ("read_noise", "read_noise"): s * s}
    return K, first, second


def _where_rows(s, rows, values):
    """``values`` (P, M), or (1, M) for every row, at the rows flagged in ``rows`` (P,), 0
    elsewhere."""
    xp = _xp.namespace(s)
    return xp.where(_xp.like(s, rows)[:, None], values, 0.0 + 0j)


def real_cgf(rows, t, shift, sigma):
    """K(t), K'(t), K''(t) of the count at real tilts t (P,), and the tilted photoelectron
    mean and single-electron output (ADU), per row."""
    Ke, dKe, d2Ke, E_t, theta_t = rows.real(t)
    rounding = rounds(rows.pn, sigma)
    if rounding.any():
        Ku, dKu, d2Ku = (np.where(rounding, v, 0.0) for v in rounding_real_cgf(t))
        Ke, dKe, d2Ke = Ke + Ku, dKe + dKu, d2Ke + d2Ku
    return (
        t * shift + 0.5 * (sigma * t) ** 2 + Ke,
        shift + sigma**2 * t + dKe,
        sigma**2 + d2Ke,
        E_t,
        theta_t,
    )


def extent(rows, shift, sigma, tilt=None, width=12.0):
    """Window [lo, hi] (ADU, relative to ``shift``'s origin) outside which the (tilted)
    distribution's mass is negligible.

    ``width`` standard deviations either side of the mean; below 80 photoelectrons also
    ``width`` read-noise widths around the zero-electron peak (which carries e^-E) and,
    where the rows multiply, forty single-electron outputs more on the right for the
    exponential tail.
    """
    t = np.zeros(shift.shape) if tilt is None else tilt
    _, mu, var, E_t, theta_t = real_cgf(rows, t, shift, sigma)
    sd = np.sqrt(var)
    few = E_t < 80.0
    lo = np.where(
        few, np.minimum(mu - width * sd, shift + sigma**2 * t - width * sigma), mu - width * sd
    )
    lo = lo - rounds(rows.pn, sigma)  # a rounded row's bin reaches ½ below its value
    hi = mu + width * sd + np.where(few & ~rows.pn, 40.0, width) * theta_t + 1.0
    return lo, hi


def window_start(rows, S0, sigma, tilt=None):
    """Integer start and length of the window covering each row's distribution (ADU)."""
    lo, hi = extent(rows, S0, sigma, tilt)
    start = np.floor(lo).astype(np.int64)
    return start, np.ceil(hi).astype(np.int64) - start + 1


def alias_count(sigma_min):
    """Aliases ±J of the characteristic function needed for read noise ``sigma_min`` (ADU).

    The density at the integers has the DTFT Σ_j Φ(ω + 2πj) (Poisson summation); alias j
    is bounded by exp(−σ²(2π|j| − π)²/2) and dropped once that is below e^-46.
    """
    return int(np.floor((np.sqrt(92.0) / sigma_min + np.pi) / (2.0 * np.pi)))


def window(
    rows,
    shift,
    sigma,
    n,
    *,
    tilt=None,
    derivs=False,
    second=False,
    names=None,
    band=None,
    xp=None,
    first_spectra=False,
):
    """Tilted pmf of the counts 0 … n−1 relative to the window start, and derivatives.

    Parameters
    ----------
    rows
        The register's parameter rows (P of them; module docstring).
    shift, sigma : ndarray, shape (P,)
        Offset relative to the window start (ADU) and read noise (ADU).
    n : int
        Window length; the distribution's mass outside the window must be negligible
        (it wraps around).
    tilt : ndarray, shape (P,), optional
        Exponential tilt t per row (1/ADU); ``None`` means 0.
    derivs, second : bool
        Also return first (and second) derivatives of the tilted density by the native
        parameters ``names``, on the same tilted scale.
    names : tuple of str, optional
        Which native parameters (the register's and :data:`READOUT`) to differentiate
        by (each costs one inverse FFT); default all.
    band : int, optional
        DFT bins to evaluate (default: the register's, widened until the transform has
        died out at the edge).
    xp : (namespace, device), optional
        Where the transforms and FFTs run (:func:`emccdcal._xp.engine`); the windows
        are that namespace's arrays. Default: NumPy.
    first_spectra : bool
        Return the first derivatives as :class:`Spectrum` too, untransformed: for sums
        against weights at the data only (a gradient), one forward FFT of the weights
        instead of an inverse FFT per derivative.

    Returns
    -------
    p : ndarray, shape (P, n)
        ``f(y)·exp(t·y − K(t))``: the density at the integers y, tilted. Round-off is
        about 1e-16 of ``p.max(axis=1)``.
    d1 : dict
        name -> (P, n) first derivatives (same tilted scale; divide by ``p`` for the
        derivative of log f); :class:`Spectrum` with ``first_spectra``.
    d2 : dict
        (name, name) -> second derivatives of f, upper triangle, as :class:`Spectrum`:
        not transformed, because they are only ever summed against weights at the data
        (:meth:`Spectrum.dot`), which costs one forward FFT for all pairs instead of an
        inverse FFT for each.
    """
    names = rows.names + READOUT if names is None else tuple(names)
    xp, dev = _xp.resolve("cpu") if xp is None else xp
    P = shift.shape[0]
    t = np.zeros(P) if tilt is None else tilt
    J = alias_count(float(sigma.min()))
    K_t, _, _, E_t, theta_t = real_cgf(rows, t, shift, sigma)
    full = n // 2 + 1
    if band is not None:
        m_hi = int(band)
    else:
        m_hi = full if J else min(full, rows.band(E_t, theta_t, sigma, n))
    order = 2 if second else 1 if derivs else 0
    phi = 0.0
    d1 = {name: 0.0 for name in names} if derivs else {}
    d2 = {}
    # The grid of s = t + iω is made where the transforms run: only t and K(t) (P,) move.
    K_t_dev, t_dev = _xp.on(xp, dev, K_t, np.asarray(t, dtype=float))
    K_t_dev = K_t_dev[:, None]
    t_dev = xp.astype(t_dev, xp.complex128)[:, None]
    # (real arithmetic first: a complex division rounds otherwise, by its reciprocal)
    omega = xp.arange(m_hi, dtype=xp.float64, device=dev) * (2.0 * np.pi) / n
    untilted = not np.any(t)
    for j in range(-J, J + 1):
        s = t_dev + 1j * xp.astype(omega + 2.0 * np.pi * j, xp.complex128)[None, :]
        K, first, sec = cgf(rows, s, shift, sigma, order, names, same_rows=untilted)
        cf = xp.exp(K - K_t_dev)
        phi = phi + cf
        if derivs:
            for name in names:
                d1[name] = d1[name] + first[name] * cf
            if second:
                for a_i, a in enumerate(names):
                    for b in names[a_i:]:
                        term = first[a] * first[b] + sec.get((a, b), 0.0)
                        d2[(a, b)] = d2.get((a, b), 0.0) + term * cf
    if m_hi < full and bool(xp.any(abs(phi[:, -1]) > _EDGE)):
        # The band was a bound's guess: where the transform has not died out at its edge
        # (a tilted window's wide electron distribution), widen it and start again.
        return window(
            rows,
            shift,
            sigma,
            n,
            tilt=tilt,
            derivs=derivs,
            second=second,
            names=names,
            band=min(full, 2 * m_hi),
            xp=(xp, dev),
            first_spectra=first_spectra,
        )
    p = irfft(phi, n)
    d1 = {name: Spectrum(v, n) if first_spectra else irfft(v, n) for name, v in d1.items()}
    d2 = {key: Spectrum(v, n) for key, v in d2.items()}
    return p, d1, d2


class Spectrum:
    """The first ``m`` DFT bins (P, m) of a real window of length ``n``, as :func:`window`
    builds them (the characteristic function at ω = 2πk/n; the window is its inverse).

    Summing a window against weights needs no inverse FFT: by Parseval,
    ``Σ_y w(y) f(y) = (1/n) Σ_k c_k Re(F_k Ŵ_k)`` with ``Ŵ = rfft(w)``, ``c_0 = 1``,
    ``c_k = 2`` for the bins that stand for a conjugate pair, and 1 at Nyquist.
    """

    def __init__(self, spectrum, n):
        self.spectrum, self.n = spectrum, n

    def window(self, single=False):
        """The window itself (P, n); with ``single``, in single precision."""
        return irfft(self.spectrum, self.n, single=single)

    @staticmethod
    def weights_spectrum(index, weights, shape, m):
        """``rfft`` of a weight grid of ``shape`` (P, n), zero but for ``weights`` at the
        flat positions ``index`` (non-zero ones distinct), its first ``m`` bins: shared
        by every dot."""
        xp = _xp.namespace(weights)
        return _xp.scattered_rfft(xp, index, weights, shape, m, _xp.fft_workers())

    def dot(self, weights_hat):
        """``Σ_y w(y) f(y)`` per row, from ``weights_spectrum(w, m)`` (P, m)."""
        xp = _xp.namespace(self.spectrum)
        m, n = self.spectrum.shape[1], self.n
        c = np.full(m, 2.0)
        c[0] = 1.0
        if n % 2 == 0 and m == n // 2 + 1:
            c[-1] = 1.0
        return (xp.real(self.spectrum * weights_hat) @ _xp.like(self.spectrum, c)) / n


def irfft(spectrum, n, single=False):
    """The window (P, n) of the first DFT bins (P, m) of the density (m ≤ n//2 + 1), in
    single precision with ``single``.

    The density's DFT is the characteristic function at −ω, the conjugate of the one
    evaluated at +ω; the bins beyond ``m`` are zero (irfft pads them).
    """
    xp = _xp.namespace(spectrum)
    return _xp.irfft(xp, spectrum, n, _xp.fft_workers(), conjugate=True, single=single)


def fast_len(n):
    """A length ≥ n for which a real FFT is fast."""
    from scipy import fft

    return fft.next_fast_len(int(n), real=True)


def log_normaliser(rows, S0, sigma, derivs=False):
    """log Σ_k f(k) per row (and its native derivatives): 0 unless read noise < ~3 ADU.

    By Poisson summation Σ_k f(k) = Σ_j Φ(2πj) = 1 + 2 Σ_{j≥1} Re Φ(2πj).
    """
    U = S0.shape[0]
    J = alias_count(float(sigma.min())) + 1
    names = rows.names + READOUT
    grads = {name: np.zeros(U) for name in names}
    if J <= 1 and float(sigma.min()) > 3.1:
        return np.zeros(U), grads
    s = 2j * np.pi * np.arange(1, J + 1)[None, :] * np.ones((U, 1))
    # Only the fractional part of the offset matters at the frequencies 2πj.
    frac = S0 - np.floor(S0)
    K, first, _ = cgf(rows, s, frac, sigma, int(derivs), names)
    # Rounded rows' probabilities sum to one: their transform is zero at 2πj.
    cf = np.where(rounds(rows.pn, sigma)[:, None], 0.0, np.exp(K))
    Z = 1.0 + 2.0 * cf.real.sum(axis=1)
    if derivs:
        grads = {name: 2.0 * (first[name] * cf).real.sum(axis=1) / Z for name in names}
    return np.log(Z), grads


def evaluate(rows, S0, sigma, row, k, grad=False):
    """log p(k) (and native gradients) for queries ``k`` of parameter rows ``row``.

    Each row's distribution is evaluated on one window around its mean; the queries the
    window resolves (values above ``rows.trusted`` of its peak) are done. For the rest,
    one at a time per row, nearest the mean first, a window tilted to centre on it
    (:func:`window` with the register's saddlepoint). Queries the register evaluates
    better itself (its ``direct_tail`` rows, and those whose tilted window would exceed
    :data:`_MAX_WINDOW` counts) go to its ``tail``.

    Parameters
    ----------
    rows
        The register's parameter rows (U of them; module docstring).
    S0, sigma : ndarray, shape (U,)
        Offset and read noise of each row (ADU).
    row : ndarray of int, shape (Q,)
        Row of each query.
    k : ndarray of int64, shape (Q,)
        Counts (ADU).
    grad : bool
        Also return the derivatives of log p by the native parameters
        (``rows.names`` and :data:`READOUT`).
    """
    Q = k.shape[0]
    logp = np.full(Q, np.nan)
    names = rows.names + READOUT
    grads = {name: np.full(Q, np.nan) for name in names} if grad else {}
    todo = np.ones(Q, dtype=bool)
    tilt_u = np.zeros(S0.shape[0])
    mean_u = real_cgf(rows, tilt_u, S0, sigma)[1]
    to_tail = rows.direct_tail(sigma)
    first_round = True
    rounds = 0
    while todo.any():
        rounds += 1
        if rounds > 20000:  # pragma: no cover - a safeguard, never a silent NaN
            raise RuntimeError("noise model: tail evaluation did not finish")
        if first_round:
            live = np.unique(row)
            targets = None
        elif to_tail.any():
            # Every remaining query of these rows, by the register's own tail evaluation.
            q = np.flatnonzero(todo & to_tail[row])
            for chunk in np.array_split(q, max(1, q.size // 4096)):
                r = row[chunk]
                lf, dq = rows.take(r).tail(k[chunk].astype(float), S0[r], sigma[r], grad)
                logp[chunk] = lf
                for name in grads:
                    grads[name][chunk] = dq[name]
            todo[q] = False
            to_tail[:] = False
            continue
        else:
            # Next target of each row: its unfinished query nearest to the mean.
            q = np.flatnonzero(todo)
            order = np.lexsort((np.abs(k[q] - mean_u[row[q]]), row[q]))
            live, first = np.unique(row[q[order]], return_index=True)
            targets = q[order[first]]
            tilt_u[live] = rows.take(live).saddlepoint(
                k[targets].astype(float), S0[live], sigma[live]
            )
        t = tilt_u[live]
        start, length = window_start(rows.take(live), S0[live], sigma[live], t)
        if targets is not None:
            huge = ~rows.pn[live] & (length > _MAX_WINDOW)
            if huge.any():
                # Far out the tilted window grows without bound: the register's tail.
                to_tail[live[huge]] = True
                keep = ~huge
                live, t, start, length = live[keep], t[keep], start[keep], length[keep]
                if live.size == 0:
                    continue
        # Rows of similar window length share one batched FFT.
        group = np.ceil(np.log2(np.maximum(length, 2))).astype(int)
        for gval in np.unique(group):
            sel = group == gval
            r = live[sel]
            n = fast_len(int(length[sel].max()))
            shift = S0[r] - start[sel]
            part = rows.take(r)
            p, d1, _ = window(part, shift, sigma[r], n, tilt=t[sel], derivs=grad, names=names)
            K_t = real_cgf(part, t[sel], shift, sigma[r])[0]
            # Queries of these rows that fall in the window.
            local = np.full(S0.shape[0], -1)
            local[r] = np.arange(r.size)
            qi = np.flatnonzero(todo & (local[row] >= 0))
            li = local[row[qi]]
            y = k[qi] - start[sel][li]
            inside = (y >= 0) & (y < n)
            qi, li, y = qi[inside], li[inside], y[inside]
            pv = p[li, y]
            ok = pv >= rows.trusted * p.max(axis=1)[li]
            if targets is not None:
                ok |= np.isin(qi, targets)
            qi, li, y, pv = qi[ok], li[ok], y[ok], pv[ok]
            # A forced target can still sit in an unresolvable valley (a Poisson–normal
            # comb with read noise below the electron spacing, far out): its value is
            # below round-off, reported as probability 0 rather than a wrong number.
            pv = np.where(pv > 0, pv, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                logp[qi] = np.log(pv) + K_t[li] - t[sel][li] * y
                for name in grads:
                    grads[name][qi] = np.where(pv > 0, d1[name][li, y] / pv, 0.0)
            todo[qi] = False
        first_round = False
    logZ, dlogZ = log_normaliser(rows, S0, sigma, derivs=grad)
    logp -= logZ[row]
    for name in grads:
        grads[name] -= dlogZ[name][row]
    return logp, grads
