"""The EM multiplication register as a Bernoulli cascade (docs/simulation.md).

A real EM register has ``stages`` = N stages. In each stage every electron independently
creates one extra electron with probability p (impact ionisation), so an input of n
electrons becomes ``n + Binomial(n, p)`` and the mean gain of the register is
``g = (1 + p)**N``. The paper's noise model (:mod:`emccdcal.model.noise`) replaces the register
by its gamma approximation, ``X | n ~ Gamma(shape n, scale g)``, whose excess-noise factor
is 2 at every gain; the cascade's is :func:`excess_noise_factor`, noticeably below 2 at low
gain (1.795 at g = 5, N = 536), which is what biases shape-based gain estimates at 5×.

This module gives

* the algebra: :func:`excess_noise_factor`, :func:`stage_probability`, :func:`mean_gain`,
  :func:`single_electron_variance`;
* two samplers of the register's output electrons for an array of input electrons:
  :func:`sample_cascade` (exact; the Bernoulli cascade) and :func:`sample_gamma` (the
  gamma approximation of the paper's model, the fast path);
* :func:`output_pmf`, the exact distribution of the output of m input electrons.

Two exact samplers
------------------
``sample_cascade(..., method="stages")`` is the definition run literally: N stages, one
``rng.binomial(n, p)`` over the whole (flattened, non-zero) array per stage. Its cost is
N binomial draws per element, 30–80 ns each with NumPy: about 15 min for a paper-size gain
series (4 set-points × 5000 frames × 32×32 px × 536 stages = 1.1e10 draws).

``sample_cascade(..., method="pmf")`` (the default) draws from the same distribution with
a few table look-ups per element. The output of n electrons is the sum of n independent
single-electron outputs. The probability generating function (PGF) of one stage is
``f(z) = (1 − p)·z + p·z²``, that of the register ``G = f∘f∘…∘f`` (N times), and
that of n electrons ``G(z)**n``. We evaluate G stage by stage on the unit circle
``z_k = exp(−2πik/M)`` (written as ``w = z − 1``, which is iterated as
``w ← w·(1 + p + p·w)`` for full relative accuracy near z = 1), raise it to the power m
and invert it with one real FFT: that is the exact pmf of the output of m electrons,
on a grid of M integers chosen, by a Chernoff bound on the upper tail, so that the mass
beyond the grid (which the FFT would alias) is below 1e-18. Sampling is by inversion of
the cumulative distribution with one uniform per draw (an indexed search: a guide table
gives the starting point, so a draw costs a couple of look-ups). An input of n electrons
is split into its binary digits, ``n = Σ_j b_j 2**j``, and the output is the sum of
independent draws from the tables of 2**j electrons (at most ``log2(n) + 1`` draws,
usually about half that); inputs beyond the largest table that fits in memory
(grid ≤ 2**22) add whole blocks of that table. Tables are cached per (p, N, block), up to
256 MiB in all. A paper-size gain series takes about 5 s this way.

Both are exact in law; they differ only by floating-point round-off (the pmf tables are
accurate to about 1e-13 absolute, the binomial sampler uses floating point as well), and
their outputs for the same seed differ draw by draw. ``tests/test_cascade.py`` checks
the tables against a direct stage-by-stage recursion of the pmf and both samplers
against each other and against the moments above (docs/simulation.md).

Threads do not help on the 2-core machine we measured (``docs/benchmarks.md``): two
threads with independent generators ran NumPy's binomial sampler only ~1.1× faster than
one (and no faster for other GIL-releasing calls), although two processes do run in
parallel there; so both samplers are single-threaded, and their draws depend only on
the seed, never on the machine.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import operator
import threading
from collections import OrderedDict

import numpy as np

from .. import _chebyshev, _roots, _xp, defaults
from ..errors import OptionError

__all__ = [
    "excess_noise_factor",
    "gain_from_gain_f2",
    "stage_probability",
    "mean_gain",
    "single_electron_variance",
    "single_electron_moments",
    "output_pmf",
    "sample_cascade",
    "sample_register_cic",
    "sample_gamma",
    "register_transform",
    "DEFAULT_STAGES",
    "KNOWN_REGISTERS",
    "known_stages",
]

#: Stages of the register used by default (declared in :mod:`emccdcal.defaults`).
DEFAULT_STAGES = defaults.DEFAULT_STAGES

#: Register lengths that a public source states, by what a camera's files record as its
#: model: ``(key, stages, source)``, the key matched in the model's name without case,
#: spaces, hyphens or underscores. A sensor or camera not here gets ``DEFAULT_STAGES``.
KNOWN_REGISTERS = (
    (
        "ccd201",
        604,
        "Teledyne e2v CCD201-20, as in the emccd-detect simulator of the Roman Coronagraph",
    ),
    ("ixonultra888", 604, "Andor iXon Ultra 888, a CCD201-20 sensor"),
    ("ixon888", 604, "Andor iXon 888, a CCD201-20 sensor"),
    ("du888", 604, "Andor DU-888 (iXon 888), a CCD201-20 sensor"),
    ("ccd65", 591, "e2v CCD65, R. N. Tubbs, PhD thesis, University of Cambridge (2003)"),
)


def known_stages(camera_model) -> tuple[int, str] | None:
    """``(stages, source)`` of a camera model in :data:`KNOWN_REGISTERS`, or None.

    Examples
    --------
    >>> known_stages("iXon Ultra 888")
    (604, 'Andor iXon Ultra 888, a CCD201-20 sensor')
    >>> known_stages("ProEM 512B") is None
    True
    """
    if not camera_model:
        return None
    name = "".join(ch for ch in str(camera_model).lower() if ch.isalnum())
    for key, stages, source in KNOWN_REGISTERS:
        if key in name:
            return stages, source
    return None


#: Largest FFT grid (integers) of one pmf table; larger inputs add whole blocks.
_MAX_GRID = 2**22
#: Upper bound on the probability mass beyond a table's grid (aliased by the FFT).
_TAIL_MASS = 1e-18


# --------------------------------------------------------------------------------------
# Checking
# --------------------------------------------------------------------------------------
def _check_gain(em_gain, *, scalar: bool = False):
    try:
        g = np.asarray(em_gain, dtype=float)
    except (TypeError, ValueError):
        raise OptionError(f"em_gain must be a number >= 1, got {em_gain!r}") from None
    if scalar and g.ndim != 0:
        raise OptionError(f"em_gain must be a single number, got shape {g.shape}")
    if not np.all(np.isfinite(g)) or np.any(g < 1):
        raise OptionError(f"em_gain must be finite and >= 1, got {em_gain!r}")
    return g


def _check_reachable(g, stages) -> None:
    """A register of N stages can multiply by at most 2**N (p ≤ 1)."""
    if np.any(np.log2(g) > stages * (1 + 1e-15)):
        raise OptionError(
            f"em_gain must be <= 2**stages (p <= 1), got em_gain={g!r} with stages={stages!r}"
        )


def _check_stages(stages):
    """Stages as a positive Python int (an array of them where broadcasting is allowed)."""
    if isinstance(stages, (bool, np.bool_)):
        raise OptionError(f"stages must be a positive integer, got {stages!r}")
    arr = np.asarray(stages)
    if arr.ndim == 0:
        try:
            n = operator.index(stages)
        except TypeError:
            if isinstance(stages, (float, np.floating)) and float(stages).is_integer():
                n = int(stages)
            else:
                raise OptionError(f"stages must be a positive integer, got {stages!r}") from None
        if n < 1:
            raise OptionError(f"stages must be a positive integer, got {stages!r}")
        return n
    if arr.dtype.kind not in "iuf" or np.any(arr < 1) or np.any(arr != np.round(arr)):
        raise OptionError(f"stages must be positive integers, got {stages!r}")
    return arr.astype(np.int64)


def _check_electrons(electrons) -> np.ndarray:
    arr = np.asarray(electrons)
    if arr.dtype.kind in "iu":
        values = arr.astype(np.int64, copy=False)
    elif arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise OptionError("electrons must be non-negative integers")
        values = arr.astype(np.int64)
    else:
        raise OptionError(
            f"electrons must be an array of non-negative integers, got dtype {arr.dtype}"
        )
    if values.size and values.min() < 0:
        raise OptionError("electrons must be non-negative integers")
    return values


# --------------------------------------------------------------------------------------
# Algebra
# --------------------------------------------------------------------------------------
def stage_probability(em_gain, stages=DEFAULT_STAGES):
    """Per-stage multiplication probability p of a register of mean gain g.

    ``p = g**(1/N) − 1``, computed as ``expm1(log(g)/N)`` for accuracy near g = 1.

    Parameters
    ----------
    em_gain : array_like
        g, mean EM gain of the register (dimensionless, ≥ 1).
    stages : int or array_like of int, optional
        N, number of multiplication stages (default 536).

    Returns
    -------
    ndarray or float
        p, the probability (dimensionless) that an electron creates a second electron
        in one stage.

    Examples
    --------
    >>> f"{stage_probability(5.0, 536):.6e}"
    '3.007195e-03'
    """
    g = _check_gain(em_gain)
    n = _check_stages(stages)
    _check_reachable(g, n)
    return np.expm1(np.log(g) / n)[()]


def mean_gain(p, stages=DEFAULT_STAGES):
    """Mean gain ``(1 + p)**N`` of a register of N stages with per-stage probability p.

    Parameters
    ----------
    p : array_like
        Per-stage multiplication probability, in [0, 1].
    stages : int or array_like of int, optional
        N, number of stages (default 536).

    Returns
    -------
    ndarray or float
        g, mean EM gain (dimensionless).

    Examples
    --------
    >>> round(float(mean_gain(stage_probability(300.0, 536), 536)), 9)
    300.0
    """
    prob = np.asarray(p, dtype=float)
    if not np.all(np.isfinite(prob)) or np.any(prob < 0) or np.any(prob > 1):
        raise OptionError(f"p must be a probability in [0, 1], got {p!r}")
    n = _check_stages(stages)
    return np.exp(n * np.log1p(prob))[()]


def single_electron_variance(em_gain, stages=DEFAULT_STAGES):
    """Variance of the register's output for one input electron, electrons².

    ``Var₁ = g(g − 1)(1 − p)/(1 + p)`` with ``p = g**(1/N) − 1`` (the Galton–Watson
    variance of the binary-splitting cascade, docs/simulation.md).

    Parameters
    ----------
    em_gain : array_like
        g, mean EM gain (dimensionless, ≥ 1).
    stages : int or array_like of int, optional
        N, number of stages (default 536).

    Returns
    -------
    ndarray or float
        Var₁ in electrons² (0 at g = 1).

    Examples
    --------
    >>> round(float(single_electron_variance(5.0, 536)), 6)
    19.880073
    """
    g = _check_gain(em_gain)
    p = np.asarray(stage_probability(g, stages))
    return (g * (g - 1.0) * (1.0 - p) / (1.0 + p))[()]


def single_electron_moments(em_gain, stages=DEFAULT_STAGES):
    """Raw moments E[X^k], k = 1…4, of the register's output X for one input electron.

    The cumulants of the output after n + 1 stages follow from those after n by the
    composition of cumulant generating functions ``K_{n+1}(t) = K_n(K_ξ(t))``, ξ the
    output of one stage for one electron (1 or 2, with P(2) = p; Faà di Bruno to fourth
    order); N steps from one electron, then cumulants to raw moments. Compound-Poisson
    input of mean λ has the k-th cumulant ``λ·E[X^k]``: what the third and fourth
    cumulants of a pixel need (COTS's bias correction).

    Parameters
    ----------
    em_gain : float
        g, mean EM gain (dimensionless, ≥ 1).
    stages : int, optional
        N, number of stages (default 536).

    Returns
    -------
    ndarray, shape (4,)
        E[X], E[X²], E[X³], E[X⁴] in electrons^k (E[X] = g).

    Examples
    --------
    >>> m = single_electron_moments(5.0, 536)
    >>> round(float(m[0]), 9), round(float(m[1] - m[0]**2), 6)  # g and Var₁
    (5.0, 19.880073)
    """
    p = float(stage_probability(float(_check_gain(em_gain, scalar=True)), stages))
    q = 1.0 - p
    a1, a2, a3, a4 = 1.0 + p, p * q, p * q * (q - p), p * q * (1.0 - 6.0 * p * q)
    k1, k2, k3, k4 = 1.0, 0.0, 0.0, 0.0  # one electron in
    for _ in range(int(_check_stages(stages))):
        k1, k2, k3, k4 = (
            k1 * a1,
            k2 * a1**2 + k1 * a2,
            k3 * a1**3 + 3.0 * k2 * a1 * a2 + k1 * a3,
            k4 * a1**4 + 6.0 * k3 * a1**2 * a2 + k2 * (3.0 * a2**2 + 4.0 * a1 * a3) + k1 * a4,
        )
    return np.array(
        [
            k1,
            k2 + k1**2,
            k3 + 3 * k2 * k1 + k1**3,
            k4 + 4 * k3 * k1 + 3 * k2**2 + 6 * k2 * k1**2 + k1**4,
        ]
    )


def excess_noise_factor(em_gain, stages=DEFAULT_STAGES):
    """Excess-noise factor F² of a Bernoulli-cascade register, for Poisson input.

    ``F² = Var(X)/(g²E) = 1 + Var₁/g² = 2(g − 1)·g**(−(N+1)/N) + 1/g``
    (docs/simulation.md): 1 at g = 1, below 2 at every finite N (1.795 at g = 5, N = 536),
    against exactly 2 for the gamma model of :mod:`emccdcal.model.noise`.

    Parameters
    ----------
    em_gain : array_like
        g, mean EM gain (dimensionless, ≥ 1).
    stages : int or array_like of int, optional
        N, number of stages (default 536). Broadcasts with ``em_gain``.

    Returns
    -------
    ndarray or float
        F², dimensionless.

    Examples
    --------
    >>> [round(float(excess_noise_factor(g, 536)), 6) for g in (1.0, 5.0, 300.0)]
    [1.0, 1.795203, 1.975567]
    >>> round(float(excess_noise_factor(25.0, 604)), 6)
    1.949795
    """
    g = _check_gain(em_gain)
    n = _check_stages(stages)
    _check_reachable(g, n)
    return (2.0 * (g - 1.0) * g ** (-(n + 1.0) / n) + 1.0 / g)[()]


# --------------------------------------------------------------------------------------
# The register's transform, with derivatives: what the likelihood needs
# --------------------------------------------------------------------------------------
def gain_from_gain_f2(gain_times_f2, stages=DEFAULT_STAGES):
    """The gain g of a Bernoulli-cascade register of N stages with ``g·F²(g, N)`` given.

    ``g·F² = 1 + 2(g − 1)·g^{−1/N}`` (:func:`excess_noise_factor`)
    rises monotonically with g; it is solved by Newton's method from the gamma model's
    ``g = y/2``. Returns g and the slope ``d(g F²)/dg`` there (for standard errors).
    NaN in, NaN out; values below 1 (no multiplication) give NaN.

    Examples
    --------
    >>> g, _ = gain_from_gain_f2(5.0 * excess_noise_factor(5.0, 536), 536)
    >>> round(float(g), 9)
    5.0
    """
    y = np.asarray(gain_times_f2, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(y >= 1.0, np.maximum(y / 2.0, 1.0), np.nan)

        def residual(g):
            root = g ** (-1.0 / stages)
            return (1.0 + 2.0 * (g - 1.0) * root - y, 2.0 * root * (1.0 - (g - 1.0) / (stages * g)))

        g = _roots.newton(residual, g, floor=1.0, rtol=1e-13, max_iter=50)
        root = g ** (-1.0 / stages)
        slope = 2.0 * root * (1.0 - (g - 1.0) / (stages * g))
    return g, slope


def register_transform(u, em_gain, stages=DEFAULT_STAGES, *, order=1, cic=False, by_u=True):
    """``G_N(e^u) − 1`` of one input electron, and its derivatives by u and ln g.

    ``G_N`` is the register's probability generating function, so ``G_N(e^u)`` is the
    moment generating function of one electron's output (electrons) at u; with
    ``u = s/φ`` it is that of the output in ADU at s. It is computed by the recursion
    ``v_{m+1} = v_m·(1 + p + p·v_m)`` from ``v_0 = e^u − 1``, which iterates G − 1
    rather than G, so that it keeps full relative accuracy where G is close to 1
    (low frequencies), and whose derivatives follow the same recursion (forward mode).

    Parameters
    ----------
    u : ndarray, complex or real, shape (P, ...) or (P,)
        The argument, 1/electron: ``s/φ`` for the count's transform at s (1/ADU).
    em_gain : ndarray, shape (P,)
        g of each row (mean gain, ≥ 1).
    stages : int
        N.
    order : {0, 1, 2}
        Highest order of the derivatives returned.
    cic : bool
        Also return the same quantities for an electron entering the register at a
        uniformly random stage (register clock-induced charge): the mean of
        ``v_m``, m = 0 … N − 1.
    by_u : bool
        Also the derivatives by u (default); without them (a fit that holds φ fixed)
        each stage costs fewer operations.

    Returns
    -------
    dict of ndarray
        ``"v"`` and, by order, ``"u"``, ``"g"`` (∂/∂u, ∂/∂ln g), ``"uu"``, ``"ug"``,
        ``"gg"``; with ``cic`` the same names prefixed ``"cic_"`` (``"cic_v"`` …).

    Examples
    --------
    The mean output of one electron is g, its second moment ``g²F²`` at u = 0:

    >>> t = register_transform(np.zeros(1), np.array([5.0]), 536, order=2)
    >>> round(float(t["u"][0]), 9), round(float(t["uu"][0] / 25), 6)
    (5.0, 1.795203)
    """
    xp, (u, g) = _xp.asarrays(u, em_gain)
    g = xp.astype(g, xp.float64)
    if (
        u.ndim == 2
        and _xp.is_complex(xp, u)
        and g.shape == u.shape[:1]
        and not bool(xp.any(xp.real(u) != 0.0))
    ):
        table = _tabulated(xp, xp.imag(u), g, stages, order, cic, by_u)
        if table is not None:
            return table
    if u.ndim == 0 or u.size <= _CHUNK or g.shape != u.shape[:1]:
        return _register_transform(xp, u, g, stages, order, cic, by_u)
    # The recursion runs N times over every element: in pieces that stay in the CPU's
    # cache it runs about three times faster than over the whole array at once (it is
    # elementwise, so the values are the same to the bit).
    rows = xp.reshape(u, (u.shape[0], -1))
    step_rows = max(1, _CHUNK // rows.shape[1])
    step_cols = min(rows.shape[1], _CHUNK)
    out = None
    for r in range(0, rows.shape[0], step_rows):
        for c in range(0, rows.shape[1], step_cols):
            piece = _register_transform(
                xp,
                rows[r : r + step_rows, c : c + step_cols],
                g[r : r + step_rows],
                stages,
                order,
                cic,
                by_u,
            )
            if out is None:
                out = {
                    k: xp.empty(rows.shape, dtype=v.dtype, device=_xp.device(u))
                    for k, v in piece.items()
                }
            for k, v in piece.items():
                out[k][r : r + step_rows, c : c + step_cols] = v
    return {k: xp.reshape(v, u.shape) for k, v in out.items()}


#: Elements of the register's recursion computed at a time (about 256 KiB of complex
#: numbers per array: the recursion's dozen arrays stay in a core's cache).
_CHUNK = 16384


#: A table's interpolant is resolved once its last coefficients are this many times the
#: recursion's own round-off (about ``N·ε`` of the largest value) or less.
_TABLE_TOLERANCE = 1.0

#: Lobatto points of a table along (ln g, g·θ) at the first try; each refinement of an
#: axis doubles its intervals (the points nest, so only the new ones are computed).
_TABLE_START = (9, 33)

#: A table's polynomial costs a few operations per point of each axis at every element,
#: the recursion about ten per stage: a table whose axes hold more than a quarter of N
#: points in all saves nothing (nor one of many stretched frequencies, e.g. of a
#: hopeless trial step's enormous window), and the recursion runs instead.
_TABLE_POINTS_PER_STAGE = 0.25

#: A table kept for reuse (:func:`transform_tables`) spans the rectangle asked for
#: widened by this fraction of its sides (the gains move as a fit goes on), and at least
#: this much in ln g.
_TABLE_MARGIN = (0.25, 0.02)

#: Tables kept at once in a :func:`transform_tables` scope (oldest dropped first).
_TABLES_KEPT = 16

_SCOPE: contextvars.ContextVar = contextvars.ContextVar("transform_tables", default=None)


@contextlib.contextmanager
def transform_tables():
    """Within this block (on this thread), :func:`register_transform` keeps the tables it
    builds and reuses them for later calls whose gains and frequencies they cover.

    A fit evaluates the transform of the same pixels over and over with gains that move a
    little: one table serves most of its iterations. The scope is what makes that
    deterministic: a fit's values depend on its own calls only, never on what another
    fit (another thread, another block) tabulated before.
    """
    if _SCOPE.get() is not None:  # within an enclosing scope: its tables
        yield
        return
    token = _SCOPE.set([])
    try:
        yield
    finally:
        _SCOPE.reset(token)


class _Table:
    """The transform's Chebyshev coefficients over a rectangle of (ln g, g·θ), kept as
    NumPy arrays (a few hundred numbers) and given to each caller in its own namespace:
    the same table serves a fit on a device and its checks on the host."""

    def __init__(self, stages, x_range, z_range, coef):
        self.stages, self.x_range, self.z_range = stages, x_range, z_range
        self.coef = {k: _xp.to_numpy(c) for k, c in coef.items()}

    def covers(self, stages, x_range, z_range, keys) -> bool:
        return (
            stages == self.stages
            and keys <= self.coef.keys()
            and self.x_range[0] <= x_range[0]
            and x_range[1] <= self.x_range[1]
            and self.z_range[0] <= z_range[0]
            and z_range[1] <= self.z_range[1]
        )

    def evaluate(self, keys, x, z):
        return {
            k: _chebyshev.evaluate_rows(_xp.like(x, self.coef[k]), self.x_range, self.z_range, x, z)
            for k in keys
        }


def _derivative_names(order, by_u) -> tuple[str, ...]:
    """The transform and the derivatives :func:`_register_transform` computes."""
    names = ("v", "u", "g", "uu", "ug", "gg")[: (1, 3, 6)[order]]
    return names if by_u else tuple(n for n in names if "u" not in n)


def _transform_keys(order, cic, by_u) -> frozenset:
    """The names :func:`_register_transform` returns for these options."""
    names = _derivative_names(order, by_u)
    return frozenset(names + (tuple("cic_" + n for n in names) if cic else ()))


def _tabulated(xp, theta, g, stages, order, cic, by_u):
    """:func:`register_transform` at ``u = iθ`` (P, M) for rows of gains g (P,), from a
    Chebyshev table (:mod:`emccdcal._chebyshev`) over a rectangle in ``(ln g, g·θ)``
    holding the rows; None where a table would cost about as much as the rows.

    The recursion costs N stages per element; a table costs N stages per node (a few
    hundred for a block of pixels at one set-point) and a short polynomial per element,
    and agrees with the recursion to about the recursion's own round-off (its last
    coefficients are below ``N·ε`` of its largest). In ``g·θ`` (the argument of the
    gamma approximation's transform) the gain changes the function's shape only, so few
    points span the gains of a block. Within :func:`transform_tables` tables are kept
    and reused; elsewhere each call builds its own, where it costs a quarter of the rows
    or less.
    """
    x = xp.log(g)
    z = theta * g[:, None]
    x_range = (float(xp.min(x)), float(xp.max(x)))
    z_range = (float(xp.min(z)), float(xp.max(z)))
    keys = _transform_keys(order, cic, by_u)
    kept = _SCOPE.get()
    if kept is None:
        table = _build_table(xp, theta, stages, x_range, z_range, order, cic, by_u, theta.size // 4)
    else:
        table = next((t for t in kept if t.covers(stages, x_range, z_range, keys)), None)
        if table is None:
            table = _build_table(
                xp,
                theta,
                stages,
                _widen(x_range, _TABLE_MARGIN[1]),
                _widen(z_range, 0.0),
                order,
                cic,
                by_u,
                theta.size,
            )
            if table is not None:
                kept.append(table)
                del kept[:-_TABLES_KEPT]
    if table is None:
        return None
    out = table.evaluate(keys, x, z)
    # At u = 0 the transform and its derivatives by ln g vanish exactly (one electron's
    # output is certain to be something): keep them exact there, where every window's
    # normalisation is.
    zero = theta == 0.0
    if bool(xp.any(zero)):
        for k, v in out.items():
            if "u" not in k.removeprefix("cic_"):
                v[zero] = 0.0
    return out


def _widen(bounds, at_least):
    """``bounds`` widened on each side by ``_TABLE_MARGIN[0]`` of its width (and at least
    ``at_least``); a lower bound of 0 stays (the zero frequency)."""
    lo, hi = bounds
    pad = max(_TABLE_MARGIN[0] * (hi - lo), at_least)
    return (lo - pad if lo != 0.0 else 0.0, hi + pad)


def _build_table(xp, like, stages, x_range, z_range, order, cic, by_u, budget):
    """The :class:`_Table` of the rectangle, refined until resolved, in namespace ``xp``
    on the device of ``like``; None once it would take more than ``budget`` nodes."""
    tol = _TABLE_TOLERANCE * stages * np.finfo(float).eps

    def at(xs, zs):  # the recursion on the grid xs × zs
        gs = np.exp(xs)
        u, g = _xp.like(like, 1j * zs[None, :] / gs[:, None], gs)
        return _register_transform(xp, u, g, stages, order, cic, by_u)

    n = [
        1 if x_range[0] == x_range[1] else _TABLE_START[0],
        1 if z_range[0] == z_range[1] else _TABLE_START[1],
    ]
    most_points = _TABLE_POINTS_PER_STAGE * stages
    spent = n[0] * n[1]
    if spent > budget or sum(n) > most_points:
        return None
    values = at(_chebyshev.lobatto(n[0], *x_range), _chebyshev.lobatto(n[1], *z_range))
    while True:
        coef = {k: _chebyshev.coefficients(v) for k, v in values.items()}
        done = [_chebyshev.resolved(c, tol) for c in coef.values()]
        refine = [axis for axis in (0, 1) if not all(d[axis] for d in done)]
        if not refine:
            return _Table(stages, x_range, z_range, coef)
        for axis in refine:
            n[axis] = 2 * n[axis] - 1
            nodes = [_chebyshev.lobatto(n[0], *x_range), _chebyshev.lobatto(n[1], *z_range)]
            nodes[axis] = nodes[axis][1::2]
            spent += nodes[0].size * nodes[1].size
            if spent > budget or sum(n) > most_points:
                return None
            new = at(*nodes)
            values = {k: _interleave(xp, v, new[k], axis) for k, v in values.items()}


def _interleave(xp, old, new, axis):
    """Values on a refined Lobatto grid: the old points at the even places of ``axis``,
    the new ones at the odd."""
    shape = list(old.shape)
    shape[axis] = old.shape[axis] + new.shape[axis]
    out = xp.empty(tuple(shape), dtype=old.dtype, device=_xp.device(old))
    even = [slice(None)] * old.ndim
    odd = list(even)
    even[axis], odd[axis] = slice(0, None, 2), slice(1, None, 2)
    out[tuple(even)] = old
    out[tuple(odd)] = new
    return out


def _register_transform(xp, u, g, stages, order, cic, by_u):
    """:func:`register_transform` of one piece of the arrays (namespace ``xp``)."""
    p_row = xp.reshape(xp.expm1(xp.log(g) / stages), g.shape + (1,) * (u.ndim - 1))
    # Coefficients spelled out to the arrays' full shape and type: in-place arithmetic is
    # fastest without broadcasting or casting (the loop runs N times).
    dtype = xp.result_type(u.dtype, xp.float64)
    full = lambda c: xp.astype(xp.broadcast_to(c, u.shape), dtype)  # noqa: E731
    p, a1, two_p = full(p_row), full(1.0 + p_row), full(2.0 * p_row)
    u = xp.astype(u, dtype)
    e_u = xp.exp(u)
    v = xp.where(abs(u) < 1e-3, xp.expm1(u), e_u - 1.0)  # e^u − 1 without cancellation
    out_names = _derivative_names(order, by_u)
    d = {"v": v}
    if order >= 1:
        d["g"] = xp.zeros_like(v)
        if by_u:
            d["u"] = xp.asarray(e_u, copy=True)
    if order >= 2:
        d["gg"] = xp.zeros_like(v)
        if by_u:
            d["uu"] = xp.asarray(e_u, copy=True)
            d["ug"] = xp.zeros_like(v)
    sums = {name: xp.zeros_like(v) for name in out_names} if cic else None
    for _ in range(stages):
        if cic:
            for name in out_names:
                sums[name] += d[name]
        # a = ∂v_{m+1}/∂v_m = 1 + p + 2p·v; the p-derivative of the map is v(1 + v).
        a = two_p * v
        a += a1
        if order >= 2:
            # second derivatives first: they need this stage's first derivatives
            vg = d["g"]
            if by_u:
                vu = d["u"]
                d["uu"] *= a  # + 2p·v_u²
                d["uu"] += (vu * vu) * two_p
            t = p * vg  # t = p·v_g
            w = v * 2.0
            w += 1.0
            w += t  # w = 1 + 2v + p·v_g
            d["gg"] *= a  # + 2·v_g·(1 + 2v + p·v_g)
            d["gg"] += (vg * w) * 2.0
            if by_u:
                w += t  # w = 1 + 2v + 2p·v_g
                d["ug"] *= a  # + v_u·(1 + 2v + 2p·v_g)
                d["ug"] += vu * w
        if order >= 1:
            d["g"] *= a
            d["g"] += (v + 1.0) * v
            if by_u:
                d["u"] *= a
        t = p * v
        t += a1
        v *= t
    # Derivatives by p → by ln g: dp/d ln g = (1 + p)/N, d²p/d(ln g)² = (1 + p)/N².
    dp = (1.0 + p_row) / stages
    for src in [d] + ([sums] if cic else []):
        if order >= 2:
            src["gg"] = src["gg"] * dp**2 + src["g"] * (dp / stages)
            if by_u:
                src["ug"] = src["ug"] * dp
        if order >= 1:
            src["g"] = src["g"] * dp
    if cic:
        d.update({"cic_" + name: value / stages for name, value in sums.items()})
    return d


# --------------------------------------------------------------------------------------
# Exact output distribution (PGF composition on an FFT grid)
# --------------------------------------------------------------------------------------
def _pgf_minus_one(w: np.ndarray, p: float, stages: int) -> np.ndarray:
    """``G(1 + w) − 1`` for the N-stage register, iterating ``w ← w(1 + p + pw)``."""
    w = np.array(w, copy=True)
    a = 1.0 + p
    for _ in range(stages):
        w *= a + p * w
    return w


@functools.lru_cache(maxsize=256)
def _grid_size(p: float, stages: int, m: int) -> int:
    """Power-of-two grid holding all but ``_TAIL_MASS`` of the output of m electrons.

    Chernoff: ``P(X ≥ M) ≤ G(t)**m / t**M`` for any real t > 1 where G(t) is finite.
    """
    g = (1.0 + p) ** stages
    w0 = np.geomspace(1e-4, 4.0, 240) / g
    with np.errstate(over="ignore", invalid="ignore"):
        w = _pgf_minus_one(w0, p, stages)
        ok = np.isfinite(w) & (w > 0)
        need = (m * np.log1p(w[ok]) - np.log(_TAIL_MASS)) / np.log1p(w0[ok])
    size = float(np.min(need)) + 1.0
    return 1 << max(4, int(np.ceil(np.log2(size))))


class _TableCache:
    """Least-recently-used cache of pmf tables, bounded by their total size in bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key, make):
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = make(*key)
        size = sum(a.nbytes for a in value[1:])
        with self._lock:
            if key not in self._items:
                self._items[key] = value
                self._bytes += size
                while self._bytes > self.max_bytes and len(self._items) > 1:
                    _, old = self._items.popitem(last=False)
                    self._bytes -= sum(a.nbytes for a in old[1:])
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


#: pmf tables kept between calls (a paper-size series needs about 40 tables, 30 MB).
_TABLES = _TableCache(max_bytes=256 * 2**20)


def _block_table(p: float, stages: int, m: int):
    """Exact output law of m input electrons: ``(lo, pmf, cdf, guide)`` (cached).

    ``P(X = lo + i) = pmf[i]``, ``P(X ≤ lo + i) = cdf[i]`` with ``lo = m``, and ``guide``
    the start indices of :func:`_invert`.
    """
    return _TABLES.get((p, stages, m), _make_block_table)


def _make_block_table(p: float, stages: int, m: int):
    size = _grid_size(p, stages, m)
    theta = -2.0 * np.pi * np.arange(size // 2 + 1) / size
    # z − 1 = e^{iθ} − 1, accurate for small θ.
    w = (-2.0 * np.sin(theta / 2) ** 2) + 1j * np.sin(theta)
    w = _pgf_minus_one(w, p, stages)
    with np.errstate(divide="ignore", invalid="ignore", under="ignore"):
        transform = np.exp(m * np.log1p(w))
    transform[~np.isfinite(transform)] = 0.0
    pmf = np.fft.irfft(transform, n=size)
    pmf[:m] = 0.0  # m electrons never give fewer than m
    np.clip(pmf, 0.0, None, out=pmf)
    pmf /= np.sum(pmf)  # pairwise summation
    # Accurate at both ends: the running sum below the median, one minus the (reverse)
    # running sum of the upper tail above it, so that tail probabilities far below the
    # accumulated round-off of a single running sum are kept.
    lower = np.cumsum(pmf)
    upper = 1.0 - np.concatenate((np.cumsum(pmf[::-1])[::-1][1:], [0.0]))
    cdf = np.where(lower < 0.5, lower, upper)
    np.maximum.accumulate(cdf, out=cdf)
    np.clip(cdf, 0.0, 1.0, out=cdf)
    # Beyond the first index where the cdf reaches 1.0 nothing can be drawn (u < 1).
    hi = int(np.searchsorted(cdf, 1.0, side="left"))
    cdf = cdf[m : hi + 1].copy()
    cdf[-1] = 1.0
    pmf = pmf[m : hi + 1].copy()
    # Guide table (indexed search): guide[k] is the first index with cdf > k/K, the
    # start of the search for any u in [k/K, (k+1)/K).
    guide = np.searchsorted(cdf, np.arange(cdf.size) / cdf.size, side="right").astype(np.int32)
    for a in (pmf, cdf, guide):
        a.setflags(write=False)
    return m, pmf, cdf, guide


@functools.lru_cache(maxsize=64)
def _max_block_exponent(p: float, stages: int) -> int:
    """Largest j whose table of 2**j electrons fits in ``_MAX_GRID``."""
    j = 0
    while j < 62 and _grid_size(p, stages, 1 << (j + 1)) <= _MAX_GRID:
        j += 1
    return j


def output_pmf(electrons, em_gain, stages=DEFAULT_STAGES):
    """Exact distribution of the register's output for a fixed number of input electrons.

    Parameters
    ----------
    electrons : int
        m ≥ 1, the number of electrons entering the register.
    em_gain : float
        g, mean EM gain (dimensionless, > 1).
    stages : int, optional
        N, number of stages (default 536).

    Returns
    -------
    values : ndarray of int64
        Output electron numbers ``m, m+1, …`` covering all but < 1e-16 of the mass.
    pmf : ndarray of float64
        Their probabilities (absolute accuracy about 1e-13; sums to 1).

    Examples
    --------
    >>> x, p = output_pmf(1, 5.0, 536)
    >>> round(float((x * p).sum()), 9), round(float((x**2 * p).sum() - 25), 4)
    (5.0, 19.8801)
    """
    m = operator.index(electrons)
    if m < 1:
        raise OptionError(f"electrons must be >= 1, got {electrons!r}")
    g = float(_check_gain(em_gain, scalar=True))
    if g == 1.0:
        raise OptionError("em_gain must be > 1 (at 1 the output equals the input)")
    n = _check_stages(stages)
    if not isinstance(n, int):
        raise OptionError("stages must be a single positive integer")
    if _grid_size(float(stage_probability(g, n)), n, m) > _MAX_GRID:
        raise OptionError(f"electrons × em_gain too large for one table ({m} × {g})")
    lo, pmf, _, _ = _block_table(float(stage_probability(g, n)), n, m)
    return lo + np.arange(pmf.size, dtype=np.int64), pmf.copy()


def _invert(cdf: np.ndarray, guide: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``np.searchsorted(cdf, u, side="right")`` (the first index with cdf > u), faster.

    Starts at the guide entry of u's bucket and steps forward; the few draws still
    short after three steps are finished by binary search. Same result, exactly.
    """
    idx = guide[(u * guide.size).astype(np.intp)].astype(np.intp)
    todo = np.flatnonzero(cdf[idx] <= u)
    for _ in range(3):
        if not todo.size:
            return idx
        idx[todo] += 1
        todo = todo[cdf[idx[todo]] <= u[todo]]
    if todo.size:
        idx[todo] = np.searchsorted(cdf, u[todo], side="right")
    return idx


def _draw_block(p: float, stages: int, m: int, rng: np.random.Generator, size: int):
    lo, _, cdf, guide = _block_table(p, stages, m)
    return lo + _invert(cdf, guide, rng.random(size))


def _sample_pmf(n: np.ndarray, p: float, stages: int, rng: np.random.Generator) -> np.ndarray:
    """Output for the 1-D array n of positive inputs, by binary blocks."""
    out = np.zeros_like(n)
    top = _max_block_exponent(p, stages)
    nbits = int(n.max()).bit_length()
    for j in range(min(top, nbits)):
        sel = np.flatnonzero((n >> j) & 1)
        if sel.size:
            out[sel] += _draw_block(p, stages, 1 << j, rng, sel.size)
    blocks = n >> top
    big = np.flatnonzero(blocks)
    if big.size:
        reps = blocks[big]
        draws = _draw_block(p, stages, 1 << top, rng, int(reps.sum()))
        starts = np.concatenate(([0], np.cumsum(reps)[:-1]))
        out[big] += np.add.reduceat(draws, starts)
    return out


def _sample_stages(n: np.ndarray, p: float, stages: int, rng: np.random.Generator) -> np.ndarray:
    x = n.copy()
    for _ in range(stages):
        x += rng.binomial(x, p)
    return x


def sample_cascade(electrons, em_gain, stages=DEFAULT_STAGES, rng=None, *, method="pmf"):
    """Output electrons of a Bernoulli-cascade EM register, exactly.

    Each input electron passes ``stages`` stages; in each, every electron present
    creates one more with probability ``p = em_gain**(1/stages) − 1``.

    Parameters
    ----------
    electrons : array_like of int, any shape
        Electrons entering the register (non-negative integers), one per element.
    em_gain : float
        g, mean gain of the register (dimensionless, ≥ 1; 1 returns the input).
    stages : int, optional
        N, number of stages (default 536).
    rng : numpy.random.Generator or seed, optional
        Source of randomness; anything :func:`numpy.random.default_rng` accepts.
    method : {"pmf", "stages"}, optional
        ``"stages"``: N stages of ``n += rng.binomial(n, p)`` over the flat array of
        non-zero entries (the definition; ~N binomial draws per element).
        ``"pmf"`` (default): the same distribution, drawn by inversion from exact pmf
        tables (module docstring); a few table look-ups per element. Both are exact;
        for the same seed they give different draws.

    Returns
    -------
    ndarray of int64, same shape as ``electrons``
        Output electrons; 0 where the input is 0.

    Examples
    --------
    >>> x = sample_cascade(np.full(20000, 20), 5.0, 536, rng=1)
    >>> bool(abs(x.mean() / 100 - 1) < 0.01)
    True
    """
    n = _check_electrons(electrons)
    g = float(_check_gain(em_gain, scalar=True))
    n_stages = _check_stages(stages)
    if not isinstance(n_stages, int):
        raise OptionError("stages must be a single positive integer")
    if method not in ("pmf", "stages"):
        raise OptionError(f"method must be 'pmf' or 'stages', got {method!r}")
    rng = np.random.default_rng(rng)
    out = np.array(n, dtype=np.int64, copy=True)
    if g == 1.0 or out.size == 0:
        return out
    p = float(stage_probability(g, n_stages))
    flat = out.reshape(-1)
    nz = np.flatnonzero(flat)
    if nz.size:
        sampler = _sample_pmf if method == "pmf" else _sample_stages
        flat[nz] = sampler(flat[nz], p, n_stages, rng)
    return out


def sample_register_cic(count, em_gain, stages=DEFAULT_STAGES, rng=None):
    """Output electrons of clock-induced charge made inside the register, exactly.

    Each of ``count`` electrons is made at a uniformly random stage and passes the
    stages after it: m ~ U{0, …, N−1} of them (the convention of
    :func:`register_transform`'s ``cic``), each making one more electron with
    probability p = g^(1/N) − 1, as in :func:`sample_cascade`'s ``"stages"`` method.

    Parameters
    ----------
    count : int
        Electrons made inside the register.
    em_gain : float
        g, the register's mean gain (≥ 1).
    stages : int
        N.
    rng : numpy.random.Generator or seed, optional

    Returns
    -------
    ndarray of int64, shape (count,)
        Each electron's output (≥ 1).

    Examples
    --------
    >>> x = sample_register_cic(50000, 100.0, 536, rng=1)
    >>> bool(abs(x.mean() / float(np.mean(100.0 ** (np.arange(536) / 536))) - 1) < 0.03)
    True
    """
    n_stages = _check_stages(stages)
    g = float(_check_gain(em_gain, scalar=True))
    rng = np.random.default_rng(rng)
    passes = np.sort(rng.integers(0, n_stages, size=int(count)))[::-1]
    out = np.ones(passes.size, dtype=np.int64)
    p = float(stage_probability(g, n_stages))
    # electrons sorted by the stages they pass: those still in the register are a prefix
    active = passes.size
    for s in range(n_stages):
        while active and passes[active - 1] <= s:
            active -= 1
        if not active:
            break
        out[:active] += rng.binomial(out[:active], p)
    return rng.permutation(out)


def sample_gamma(electrons, em_gain, rng=None):
    """Output of the gamma model of the EM register (the paper's, fast).

    ``X | n ~ Gamma(shape n, scale g)``, ``X = 0`` for n = 0: mean ``g·n`` as the
    cascade, variance ``g²·n`` (excess-noise factor 2 at every gain). At
    ``em_gain == 1`` there is no multiplication and the input is returned (as float).

    Parameters
    ----------
    electrons : array_like of int, any shape
        Electrons entering the register (non-negative integers).
    em_gain : float
        g, mean EM gain (dimensionless, ≥ 1).
    rng : numpy.random.Generator or seed, optional
        Source of randomness; anything :func:`numpy.random.default_rng` accepts.

    Returns
    -------
    ndarray of float64, same shape as ``electrons``
        Output in electrons (continuous).

    Examples
    --------
    >>> x = sample_gamma(np.array([0, 0, 10]), 25.0, rng=0)
    >>> x[:2].tolist(), bool(x[2] > 0)
    ([0.0, 0.0], True)
    """
    n = _check_electrons(electrons)
    g = float(_check_gain(em_gain, scalar=True))
    if g == 1.0:
        return n.astype(float)
    rng = np.random.default_rng(rng)
    out = np.zeros(n.shape, dtype=float)
    flat_n = n.reshape(-1)
    nz = np.flatnonzero(flat_n)
    if nz.size:
        out.reshape(-1)[nz] = rng.gamma(flat_n[nz], g)
    return out
