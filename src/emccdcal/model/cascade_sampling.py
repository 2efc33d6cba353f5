"""Sampling the exact Bernoulli-cascade register (docs/simulation.md), and the exact
distribution of its output.

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

import functools
import operator
import threading
from collections import OrderedDict

import numpy as np

from ..errors import OptionError
from .cascade import (
    DEFAULT_STAGES,
    _check_electrons,
    _check_gain,
    _check_stages,
    stage_probability,
)

__all__ = ["output_pmf", "sample_cascade", "sample_register_cic", "sample_gamma"]

#: Largest FFT grid (integers) of one pmf table; larger inputs add whole blocks.
_MAX_GRID = 2**22
#: Upper bound on the probability mass beyond a table's grid (aliased by the FFT).
_TAIL_MASS = 1e-18


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
