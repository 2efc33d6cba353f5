"""One optimizer: batched damped Newton (Levenberg–Marquardt) over independent rows.

Every fit of the package maximises a sum of per-row objectives (a pixel's likelihood, a
bead's, a frame's least squares), each row with its own few parameters. :func:`maximize`
takes them all at once: for every row still moving it solves ``(I + λ·diag I) Δ = ∇``
with the row's own information matrix I (observed, expected, or Gauss–Newton's JᵀJ) and
damping λ, clips the step to ±``max_step`` per parameter, keeps parameters at a bound
whose gradient points outwards where they are (an active-set step), and evaluates the
trial rows only. A trial that does not raise the objective is refused and its damping
raised tenfold; an accepted one lowers it tenfold. A row is done when its step promises
less than ``tol + rtol·|objective|`` (the Newton decrement ½∇ᵀΔ), when its step is below
1e-10 in every parameter, or when no damping up to ``max_damping`` finds a better point
(stuck, unless an undamped step would gain less than ``stuck_tol``).

Users: the likelihood engine (:mod:`emccdcal.fit.engine`), the dark fit
(:mod:`emccdcal.data.dark`), the bead fits (:mod:`emccdcal.beads.fit`, whose rows are
whole beads with an arrow-shaped information solved by their own ``step``) and COTS
(:mod:`emccdcal.beads.cots`).
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


def dense_step(info, grad, damping, held):
    """The damped Newton step ``(I + λ·diag I)⁻¹ ∇`` of every row.

    Parameters
    ----------
    info : ndarray, shape (n, F, F)
        Each row's information matrix.
    grad : ndarray, shape (n, F)
        Each row's gradient.
    damping : ndarray, shape (n,)
        Each row's λ.
    held : ndarray of bool, shape (n, F)
        Parameters that stay where they are (their step is 0).

    Returns
    -------
    ndarray, shape (n, F)
    """
    eye = np.eye(grad.shape[1])
    if held.any():
        free = ~held
        grad = np.where(held, 0.0, grad)
        info = info * free[:, :, None] * free[:, None, :] + held[:, :, None] * eye
    scale = np.sqrt(np.maximum(np.abs(np.einsum("pii->pi", info)), 1e-300))
    A = info + damping[:, None, None] * (scale[:, :, None] * scale[:, None, :]) * eye
    return solve(A, grad)


def maximize(evaluate, x0, *, lower, upper, tol, rtol=0.0, max_iter=100, max_step=1.0,
             accept_rtol=1e-12, max_damping=1e8, stuck_tol=0.0, step=dense_step,
             progress=None):
    """Maximise independent per-row objectives by damped Newton steps.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(rows, x)`` for row indices ``rows`` (n,) at parameters ``x`` (n, F):
        ``(objective (n,), grad (n, F), info)``; ``info`` is an array whose first axis
        is the rows, by default (n, F, F) positive semi-definite (observed, or the outer
        product of the scores; Gauss–Newton's JᵀJ for least squares).
    x0 : ndarray, shape (P, F)
        Start; clipped to the bounds. A row whose objective is not finite there is not
        moved (it is returned ``stuck``).
    lower, upper : array_like, shape (F,) or (P, F)
        Bounds of the parameters (±inf where there are none).
    tol, rtol : float
        A row is done when its next step promises less than ``tol + rtol·|objective|``
        (objective units; ``rtol`` for objectives without a natural unit, such as a sum
        of squares).
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
    stuck_tol : float
        A stuck row whose undamped step promises less than this is done all the same:
        at a maximum the objective's round-off cannot resolve. 0: never.
    step : callable
        ``step(info, grad, damping, held)`` → the damped step (n, F) of the rows:
        :func:`dense_step` by default; a fit whose information has a structure (a bead's
        shared and per-frame parameters) solves it its own way, with the same damping.
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
    obj, grad, info = evaluate(np.arange(P), x)
    stuck = ~np.isfinite(obj)
    done = stuck.copy()

    def held(rows, g):
        # A parameter at its bound whose gradient points outwards stays there, and the
        # step is solved in the others (an active-set step): clipping a full step would
        # leave them moving as though it had moved too, and stall on the bound.
        return (((x[rows] <= lower[rows]) & (g < 0))
                | ((x[rows] >= upper[rows]) & (g > 0)))

    for _ in range(max_iter):
        active = np.flatnonzero(~done)
        if active.size == 0:
            break
        g = grad[active]
        x_a, lo, hi = x[active], lower[active], upper[active]
        d = np.clip(step(info[active], g, damping[active], held(active, g)),
                    -max_step, max_step)
        x_new = np.clip(x_a + d, lo, hi)
        d = x_new - x_a
        # A step that promises less than the tolerance is not worth its evaluation (the
        # objective's round-off could even refuse it): the row is done.
        decrement = 0.5 * np.einsum("pf,pf->p", g, d)
        small = ((np.abs(decrement) < tol + rtol * np.abs(obj[active]))
                 | (np.max(np.abs(d), axis=1, initial=0.0) < 1e-10))
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
        if stuck_tol > 0 and hopeless.size:
            g = grad[hopeless]
            d = step(info[hopeless], g, np.zeros(hopeless.size), held(hopeless, g))
            stuck[hopeless[np.abs(0.5 * np.einsum("pf,pf->p", g, d)) < stuck_tol]] = False
        if progress is not None:
            progress(int(small.sum() + hopeless.size))
    return Optimum(x, obj, done & ~stuck, stuck, iterations)
