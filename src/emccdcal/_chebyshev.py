"""Chebyshev interpolation on a rectangle: tabulate a costly smooth function once, then
evaluate it anywhere inside for the price of a short polynomial.

A function f(x, y) analytic near the rectangle [x0, x1] × [y0, y1] is sampled on the
tensor grid of Chebyshev–Lobatto points (``cos(πj/(n − 1))``, mapped to each side); the
interpolant's coefficients come from one cosine transform per axis (a small matrix
product), and it is evaluated by Clenshaw's recurrence. Its error falls geometrically
with the number of points, at a rate set by how far from the rectangle f's nearest
singularity lies, and is about the size of the last coefficients: :func:`resolved`
tells when those are below a tolerance (L. N. Trefethen, *Approximation Theory and
Approximation Practice*, SIAM 2013, chapters 2–3 and 8).

The caller chooses where the function is worth tabulating; the first user is the exact
register's transform (:func:`emccdcal.model.cascade.register_transform`), a recursion
of hundreds of stages per element, tabulated over (ln g, frequency) once per call.
"""

from __future__ import annotations

import functools

import numpy as np

from . import _xp

__all__ = ["lobatto", "coefficients", "resolved", "evaluate_rows"]


def lobatto(n: int, lo: float, hi: float) -> np.ndarray:
    """The n Chebyshev–Lobatto points of [lo, hi], from hi down to lo (one point, the
    centre, for n = 1).

    >>> lobatto(3, 0.0, 2.0)
    array([2., 1., 0.])
    """
    if n == 1:
        return np.array([0.5 * (lo + hi)])
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(np.pi * np.arange(n) / (n - 1))


@functools.lru_cache(maxsize=32)
def _transform_matrix(n: int) -> np.ndarray:
    """(n, n) matrix taking values at the n Lobatto points to Chebyshev coefficients
    (read-only: shared by every table of n points)."""
    if n == 1:
        return np.ones((1, 1))
    j = np.arange(n)
    m = np.cos(np.pi * np.outer(j, j) / (n - 1)) * (2.0 / (n - 1))
    m[:, 0] *= 0.5  # the end points count half (the trapezoidal rule of the cosine sum)
    m[:, -1] *= 0.5
    m[0] *= 0.5  # and so do the first and last coefficients
    m[-1] *= 0.5
    m.flags.writeable = False
    return m


def coefficients(values):
    """Chebyshev coefficients (n_x, n_y) of values on the Lobatto grid (n_x, n_y) (axis 0
    along x, axis 1 along y, each from its upper end down); any array namespace."""
    xp = _xp.namespace(values)
    cx, cy = _xp.like(
        values, _transform_matrix(values.shape[0]), _transform_matrix(values.shape[1]).T
    )
    dtype = values.dtype
    return xp.astype(cx, dtype) @ values @ xp.astype(cy, dtype)


def resolved(coef, tol: float) -> tuple[bool, bool]:
    """Whether the interpolant (n_x, n_y) has converged along x and along y: its last
    two coefficients (each axis, every other index) are within ``tol`` times the largest
    one. An axis of one or two points (a constant or a line) counts as resolved."""
    xp = _xp.namespace(coef)
    size = abs(coef)
    bound = tol * float(xp.max(size))
    along_x = coef.shape[0] <= 2 or float(xp.max(size[-2:, :])) <= bound
    along_y = coef.shape[1] <= 2 or float(xp.max(size[:, -2:])) <= bound
    return along_x, along_y


def _clenshaw(xp, c, t):
    """Σ_k c[k]·T_k(t) for coefficients c (n, ...) broadcast against t."""
    shape = np.broadcast_shapes(tuple(c.shape[1:]), tuple(t.shape))
    dtype = xp.result_type(c.dtype, t.dtype)
    if _xp.is_numpy_namespace(xp) and c.shape[0] > 2:
        # In place, into three buffers (NumPy's only: JAX's arrays are not written
        # into): 2.6 times faster over a bead fit's long rows, the same sums.
        b1, b2, new = np.zeros(shape, dtype), np.zeros(shape, dtype), np.empty(shape, dtype)
        two_t = np.asarray(2.0 * t, dtype=dtype)  # a complex product without casting
        for k in range(c.shape[0] - 1, 0, -1):
            np.multiply(two_t, b1, out=new)
            new += c[k, ...]
            new -= b2
            b1, b2, new = new, b1, b2
        return c[0, ...] + t * b1 - b2
    b1 = xp.zeros(shape, dtype=dtype, device=_xp.device(c))
    b2 = b1
    two_t = 2.0 * t
    for k in range(c.shape[0] - 1, 0, -1):
        b1, b2 = c[k, ...] + two_t * b1 - b2, b1
    return c[0, ...] + t * b1 - b2


def _unit(z, lo, hi):
    """z mapped from [lo, hi] to [−1, 1] (0 where the interval is a point)."""
    if hi == lo:
        return 0.0 * z
    return (2.0 * z - (lo + hi)) / (hi - lo)


def evaluate_rows(coef, x_range, y_range, x, y):
    """The interpolant at rows of points that share their x (any array namespace).

    Parameters
    ----------
    coef : array, shape (n_x, n_y) or (n_x, n_y, k)
        From :func:`coefficients`; k interpolants on the same grid at once.
    x_range, y_range : (float, float)
        The rectangle's sides.
    x : array, shape (P,)
        Each row's x.
    y : array, shape (P, M)
        Each row's points along y.

    Returns
    -------
    array, shape (P, M), or (P, M, k)
    """
    xp = _xp.namespace(coef, x, y)
    stack = coef if coef.ndim == 3 else coef[:, :, None]
    # Along x once per row (the rows' own coefficients in y), then along y.
    by_row = _clenshaw(xp, stack[:, :, :, None], _unit(x, *x_range))  # (n_y, k, P)
    t = _unit(y, *y_range)
    if stack.shape[2] == 1:
        # One interpolant: Clenshaw along y too, never holding the (P, M, n_y) basis
        # (hundreds of MB for a bead fit's long rows; a third of the time).
        c = xp.permute_dims(by_row, (0, 2, 1))[:, :, None, :]  # (n_y, P, 1, 1)
        values = _clenshaw(xp, c, t[:, :, None])
    else:
        # Several: the Chebyshev polynomials at every point once, shared by all k
        # interpolants through one product.
        basis = [xp.ones_like(t), t][: stack.shape[1]]
        for _k in range(2, stack.shape[1]):  # T_k = 2t·T_(k−1) − T_(k−2)
            basis.append(2.0 * t * basis[-1] - basis[-2])
        basis = xp.astype(xp.stack(basis, axis=-1), by_row.dtype)  # (P, M, n_y)
        values = basis @ xp.permute_dims(by_row, (2, 0, 1))  # (P, M, k)
    return values if coef.ndim == 3 else values[:, :, 0]
