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
* the transform of one electron's output with its derivatives
  (:func:`register_transform`), which the likelihood uses.

Sampling the register's output and its exact distribution are
:mod:`emccdcal.model.cascade_sampling`'s.

"""

from __future__ import annotations

import collections
import contextlib
import contextvars
import math
import operator
import threading

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
    if not _xp.is_numpy_namespace(xp) or u.ndim == 0 or u.size <= _CHUNK or g.shape != u.shape[:1]:
        return _register_transform(xp, u, g, stages, order, cic, by_u)
    # The recursion runs N times over every element: in pieces that stay in the CPU's
    # cache it runs about three times faster than over the whole array at once (it is
    # elementwise, so the values are the same to the bit). NumPy's only: a GPU runs the
    # whole array at once, and JAX's arrays are not written into.
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

#: A table kept for reuse (:func:`transform_tables`) spans a rectangle of a fixed grid
#: that holds the one asked for: whole cells of this width in ln g, and in g·θ bounds at
#: whole quarter-octaves (0 stays 0). Which table serves a call then depends on the
#: call's own gains and frequencies only, whoever built it and whenever.
_TABLE_CELL = 1.0 / 32.0

#: Tables kept by a process (the least recently used dropped first): a few thousand
#: numbers each.
_TABLES_KEPT = 64

#: Nodes of a kept table at most (its build is paid once per process, not per call).
_KEPT_TABLE_NODES = 2**16

_SCOPE: contextvars.ContextVar = contextvars.ContextVar("transform_tables", default=False)
_KEPT: collections.OrderedDict = collections.OrderedDict()
_KEPT_LOCK = threading.Lock()


@contextlib.contextmanager
def transform_tables():
    """Within this block (on this thread), :func:`register_transform` takes its tables
    from those the process keeps, over rectangles of a fixed grid of (ln g, g·θ), and
    keeps those it builds.

    A fit evaluates the transform of the same pixels over and over with gains that move a
    little, and the next block of pixels has gains like this one's: one table serves
    many iterations and many blocks. The grid is what keeps that deterministic: the table
    a call uses is the one of the grid's rectangle that holds its gains and frequencies,
    the same whichever fit (thread, block, tile) built it first.
    """
    if _SCOPE.get():  # within an enclosing scope
        yield
        return
    token = _SCOPE.set(True)
    try:
        yield
    finally:
        _SCOPE.reset(token)


def _on_grid(x_range, z_range):
    """The rectangle of the tables' grid that holds ``x_range`` (ln g; a single gain
    stays one) and ``z_range`` (g·θ)."""
    lo, hi = x_range
    if hi > lo:
        lo = math.floor(lo / _TABLE_CELL) * _TABLE_CELL
        hi = max(math.ceil(hi / _TABLE_CELL) * _TABLE_CELL, lo + _TABLE_CELL)

    def quarter_octave(v, up):  # the grid's bound at or beyond v, away from v's inside
        if v == 0.0:
            return 0.0
        e = 4.0 * math.log2(abs(v))
        e = math.ceil(e) if (v > 0) == up else math.floor(e)
        return math.copysign(2.0 ** (e / 4.0), v)

    return (lo, hi), (quarter_octave(z_range[0], False), quarter_octave(z_range[1], True))


def _kept_table(key, build):
    """The process's table of ``key``, built by ``build()`` the first time (None too is
    kept: a rectangle too costly to tabulate stays so)."""
    with _KEPT_LOCK:
        if key in _KEPT:
            _KEPT.move_to_end(key)
            return _KEPT[key]
    table = build()  # outside the lock: another thread may build the same, equal table
    with _KEPT_LOCK:
        _KEPT[key] = table
        if len(_KEPT) > _TABLES_KEPT:
            _KEPT.popitem(last=False)
    return table


class _Table:
    """The transform's Chebyshev coefficients over a rectangle of (ln g, g·θ), kept as
    NumPy arrays (a few hundred numbers) and given to each caller in its own namespace:
    the same table serves a fit on a device and its checks on the host."""

    def __init__(self, x_range, z_range, coef):
        self.x_range, self.z_range = x_range, z_range
        self.coef = {k: _xp.to_numpy(c) for k, c in coef.items()}

    def evaluate(self, keys, x, z):
        keys = sorted(keys)
        stack = _xp.like(x, np.stack([self.coef[k] for k in keys], axis=-1))
        values = _chebyshev.evaluate_rows(stack, self.x_range, self.z_range, x, z)
        return {k: values[:, :, i] for i, k in enumerate(keys)}


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
    points span the gains of a block. Within :func:`transform_tables` the table is the
    process's over the fixed grid's rectangle that holds the rows (built the first
    time); elsewhere each call builds its own, where it costs a quarter of the rows or
    less.
    """
    x = xp.log(g)
    z = theta * g[:, None]
    x_range = (float(xp.min(x)), float(xp.max(x)))
    z_range = (float(xp.min(z)), float(xp.max(z)))
    keys = _transform_keys(order, cic, by_u)
    if not _SCOPE.get():
        table = _build_table(xp, theta, stages, x_range, z_range, order, cic, by_u, theta.size // 4)
    else:
        x_grid, z_grid = _on_grid(x_range, z_range)
        key = (xp.__name__, str(_xp.device(theta)), stages, x_grid, z_grid, keys)
        table = _kept_table(
            key,
            lambda: _build_table(
                xp, theta, stages, x_grid, z_grid, order, cic, by_u, _KEPT_TABLE_NODES
            ),
        )
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
                out[k] = xp.where(zero, xp.zeros_like(v), v)
    return out


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
            return _Table(x_range, z_range, coef)
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
    n_old, n_new = old.shape[axis], new.shape[axis]
    order = np.empty(n_old + n_new, dtype=np.int64)  # place i takes element order[i]
    order[0::2], order[1::2] = np.arange(n_old), n_old + np.arange(n_new)
    # a gather, not writes into a new array: JAX's arrays are immutable
    both = xp.concat([old, new], axis=axis)
    return xp.take(both, _xp.like(both, order), axis=axis)


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
    v = _xp.expm1(xp, u, e_u)  # e^u − 1 without cancellation
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
    # (in place for NumPy; a new array where arrays are immutable, as JAX's)
    d["v"] = v
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
