"""One optimizer: batched damped Newton (Levenberg–Marquardt) over independent rows.

Every fit of the package maximises a sum of per-row objectives (a pixel's likelihood, a
bead's), each row with its own few parameters. :func:`maximize` takes them all at once:
for every row still moving it solves ``(I + λ·diag I) Δ = ∇`` with the row's own
information matrix I (observed, or the outer product of the scores) and damping λ,
clips the step to ±``max_step`` per parameter, keeps parameters at a bound whose
gradient points outwards where they are (an active-set step), and evaluates the trial
rows only. A trial that does not lower the objective is refused and its damping raised
tenfold; an accepted one lowers it tenfold. A row is done when its step promises less
than ``tol`` (the Newton decrement ½∇ᵀΔ), when its step is below 1e-10 in every
parameter, or when no damping up to ``max_damping`` finds a better point (at a maximum
the objective cannot resolve).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Optimum:
    """Outcome of :func:`maximize`, per row.

    Attributes
    ----------
    x : ndarray, shape (P, F)
        The parameters at the optimum.
    objective : ndarray, shape (P,)
        The objective there.
    done : ndarray of bool, shape (P,)
        Stopped by the decrement or the step size (not by ``max_iter``).
    stuck : ndarray of bool, shape (P,)
        Stopped because no damped step improved the objective.
    iterations : ndarray of int, shape (P,)
        Trial evaluations made for the row.
    """

    x: np.ndarray
    objective: np.ndarray
    done: np.ndarray
    stuck: np.ndarray
    iterations: np.ndarray


def solve(A, b):
    """``A⁻¹ b`` for a stack of matrices; a singular one by least squares."""
    try:
        return np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.zeros_like(b)
        for i in range(A.shape[0]):  # rare: only when a matrix in the stack is singular
            out[i] = np.linalg.lstsq(A[i], b[i], rcond=None)[0]
        return out


def maximize(evaluate, x0, *, lower, upper, tol, max_iter=100, max_step=1.0,
             accept_rtol=1e-12, max_damping=1e8, progress=None):
    """Maximise independent per-row objectives by damped Newton steps.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(rows, x)`` for row indices ``rows`` (n,) at parameters ``x`` (n, F):
        ``(objective (n,), grad (n, F), info (n, F, F))``, ``info`` positive
        semi-definite (observed, or the outer product of the scores).
    x0 : ndarray, shape (P, F)
        Start; clipped to the bounds.
    lower, upper : array_like, shape (F,) or (P, F)
        Bounds of the parameters (±inf where there are none).
    tol : float
        A row is done when its next step promises less than this (objective units).
    max_iter : int
        Iteration limit.
    max_step : float
        Largest change of a parameter in one step (for log-parameters 1: a factor e).
    accept_rtol : float
        A trial is accepted when its objective is at least the current one less this
        fraction of its size (the objective's round-off must not refuse a step to an
        equally good point).
    max_damping : float
        A row whose damping exceeds this is stuck (no step improves it).
    progress : callable, optional
        Called with the number of rows that finished at each iteration.

    Returns
    -------
    Optimum
    """
    x = np.array(x0, dtype=float)
    P, F = x.shape
    lower = np.broadcast_to(np.asarray(lower, dtype=float), (P, F))
    upper = np.broadcast_to(np.asarray(upper, dtype=float), (P, F))
    x = np.clip(x, lower, upper)
    damping = np.full(P, 1e-3)
    iterations = np.zeros(P, dtype=int)
    done = np.zeros(P, dtype=bool)
    stuck = np.zeros(P, dtype=bool)
    obj, grad, info = evaluate(np.arange(P), x)
    eye = np.eye(F)
    for _ in range(max_iter):
        active = np.flatnonzero(~done)
        if active.size == 0:
            break
        g, I = grad[active], info[active]
        # A parameter at its bound whose gradient points outwards stays there, and the
        # step is solved in the others (an active-set step): clipping a full step would
        # leave them moving as though it had moved too, and stall on the bound.
        x_a, lo, hi = x[active], lower[active], upper[active]
        held = ((x_a <= lo) & (g < 0)) | ((x_a >= hi) & (g > 0))
        if held.any():
            free = ~held
            g = np.where(held, 0.0, g)
            I = I * free[:, :, None] * free[:, None, :] + held[:, :, None] * eye
        scale = np.sqrt(np.maximum(np.abs(np.einsum("pii->pi", I)), 1e-300))
        A = I + damping[active, None, None] * (scale[:, :, None] * scale[:, None, :]) * eye
        step = np.clip(solve(A, g), -max_step, max_step)
        x_new = np.clip(x_a + step, lo, hi)
        step = x_new - x_a
        # A step that promises less than ``tol`` is not worth its evaluation (the
        # objective's round-off could even refuse it): the row is done.
        decrement = 0.5 * np.einsum("pf,pf->p", g, step)
        small = (np.abs(decrement) < tol) | (np.max(np.abs(step), axis=1, initial=0.0) < 1e-10)
        done[active[small]] = True
        move = ~small
        active, x_new = active[move], x_new[move]
        if active.size:
            res = evaluate(active, x_new)
            better = res[0] >= obj[active] - accept_rtol * np.abs(obj[active])
            idx = active[better]
            x[idx] = x_new[better]
            obj[idx] = res[0][better]
            grad[idx], info[idx] = res[1][better], res[2][better]
            damping[idx] = np.maximum(damping[idx] / 10.0, 1e-12)
            damping[active[~better]] *= 10.0
            iterations[active] += 1
        hopeless = active[damping[active] > max_damping]
        done[hopeless] = True
        stuck[hopeless] = True
        if progress is not None:
            progress(int(small.sum() + hopeless.size))
    return Optimum(x, obj, done & ~stuck, stuck, iterations)
