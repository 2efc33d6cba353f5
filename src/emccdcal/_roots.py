"""One place for the package's root finders: vectorised, one root per element.

The optimizer (:mod:`emccdcal._optimize`) maximises objectives; these solve equations
that are no objective's gradient: a saddlepoint ``K'(t) = k`` of the window engine, the
hierarchical layout's profiled μ, the cascade's gain from ``g·F²``, the planner's
brightest light. Every element keeps its own bracket or iterate, and the arrays are
updated together (a loop over steps, never over elements).

* :func:`bisect`: halve brackets a fixed number of times (exact and safe where a
  Newton step would overshoot);
* :func:`newton_in_bracket`: Newton's steps where they stay inside a bracket that every
  evaluation narrows and the residual keeps falling, bisection otherwise;
* :func:`newton`: plain Newton's steps, kept above a floor, to a relative step size.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["bisect", "newton_in_bracket", "newton"]


def bisect(root_below, lo, hi, iterations, *, geometric=False):
    """The bracket [lo, hi] after ``iterations`` halvings: ``(lo, hi)``.

    Parameters
    ----------
    root_below : callable
        ``root_below(x)`` → bool array: the root lies below x (x becomes the upper end).
    lo, hi : ndarray or float
        The bracket, same shape (or scalars, with a ``root_below`` that returns a bool).
    iterations : int
        Halvings (each costs one evaluation; 60 reach the last bit of a double).
    geometric : bool
        Halve on a logarithmic scale (``x = √(lo·hi)``, for a positive bracket spanning
        decades).

    Examples
    --------
    >>> lo, hi = bisect(lambda x: x * x > 2.0, 1.0, 2.0, 60)
    >>> lo <= 2.0**0.5 <= hi, hi - lo < 1e-15
    (True, True)
    """
    mid = _geometric_mid if geometric else _mid
    for _ in range(iterations):
        x = mid(lo, hi)
        below = root_below(x)
        if np.ndim(below) == 0:
            lo, hi = (lo, x) if below else (x, hi)
        else:
            hi = np.where(below, x, hi)
            lo = np.where(below, lo, x)
    return lo, hi


def _mid(lo, hi):
    return 0.5 * (lo + hi)


def _geometric_mid(lo, hi):
    return np.sqrt(lo * hi) if np.ndim(lo) else math.sqrt(lo * hi)


def newton_in_bracket(residual, lo, hi, x, *, close, max_iter=100):
    """A root of an increasing function in [lo, hi], safeguarded Newton.

    Every evaluation narrows the bracket (a residual above zero, or not finite, makes x
    its upper end). The next iterate is Newton's where that stays strictly inside the
    bracket and the residual fell by half since the step before; the bracket's midpoint
    otherwise. An element stops moving once ``close`` says so.

    Parameters
    ----------
    residual : callable
        ``residual(x)`` → ``(r, slope)``: the function minus its target, and its
        derivative (arrays of x's shape).
    lo, hi, x : ndarray
        The bracket and the start inside it.
    close : callable
        ``close(abs_r, slope)`` → bool array: the element is solved.
    max_iter : int
        Evaluations at most.

    Examples
    --------
    >>> r = newton_in_bracket(lambda x: (x**3 - 8.0, 3 * x**2), np.array([0.0]),
    ...                       np.array([10.0]), np.array([1.0]),
    ...                       close=lambda miss, slope: miss < 1e-12)
    >>> float(r[0])
    2.0
    """
    previous = np.full(np.shape(x), np.inf)  # |r| of the step before
    for _ in range(max_iter):
        with np.errstate(over="ignore", invalid="ignore"):
            r, slope = residual(x)
        bad = ~np.isfinite(r) | ~np.isfinite(slope)
        above = bad | (r > 0)
        hi = np.where(above, x, hi)
        lo = np.where(above, lo, x)
        miss = np.abs(r)
        done = ~bad & close(miss, slope)
        if np.all(done):
            break
        with np.errstate(divide="ignore", invalid="ignore"):
            step = x - r / slope
        slow = ~(miss < 0.5 * previous)
        previous = np.where(bad, np.inf, miss)
        inside = ~bad & ~slow & (step > lo) & (step < hi)
        x = np.where(done, x, np.where(inside, step, 0.5 * (lo + hi)))
    return x


def newton(residual, x, *, floor=-np.inf, rtol=1e-13, max_iter=50):
    """Newton's steps from ``x``, each iterate kept at or above ``floor``, until every
    finite step is within ``rtol`` of its iterate.

    Parameters
    ----------
    residual : callable
        ``residual(x)`` → ``(r, slope)`` as in :func:`newton_in_bracket`.
    x : ndarray
        The start (NaN stays NaN).

    Examples
    --------
    >>> x = newton(lambda x: (x * x - 2.0, 2.0 * x), np.array([1.0]), floor=0.0)
    >>> bool(abs(x[0] - 2.0**0.5) < 1e-15)
    True
    """
    for _ in range(max_iter):
        r, slope = residual(x)
        step = r / slope
        x = np.maximum(x - step, floor)
        if np.all(~np.isfinite(step) | (np.abs(step) <= rtol * x)):
            break
    return x
