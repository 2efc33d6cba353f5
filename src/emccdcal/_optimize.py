"""One optimizer: batched damped Newton (Levenberg–Marquardt) over independent rows.

Every fit of the package maximises a sum of per-row objectives (a pixel's likelihood, a
bead's, a frame's least squares), each row with its own few parameters. :func:`maximize`
takes them all at once: for every row still moving it solves ``(I + λ·diag I) Δ = ∇``
with the row's own information matrix I (observed, expected, or Gauss–Newton's JᵀJ) and
damping λ, clips the step to ±``max_step`` per parameter, keeps parameters at a bound
whose gradient points outwards where they are (an active-set step), and evaluates the
trial rows only. A trial that does not raise the objective is refused and its damping
raised tenfold. An accepted one lowers it tenfold where it gained at least a quarter of
what the step's quadratic model promised (½∇ᵀΔ), and raises it tenfold where it gained
less: an information matrix that understates the curvature along a ridge makes undamped
steps overshoot back and forth, each gaining a little, and the row would never settle
(Marquardt's gain-ratio rule). A row is done when its step promises
less than ``tol + rtol·|objective|`` (the Newton decrement ½∇ᵀΔ), when its step is below
1e-10 in every parameter, or when no damping up to ``max_damping`` finds a better point
(stuck, unless an undamped step would gain less than ``stuck_tol``).

Users: the likelihood engine (:mod:`emccdcal.fit.engine`), the dark fit
(:mod:`emccdcal.data.dark`), the bead fits (:mod:`emccdcal.beads.fit`), COTS
(:mod:`emccdcal.beads.cots`) and the gain from dark frames
(:mod:`emccdcal.fit.darkgain`). A row made of many parts that share a few parameters (a
bead's frames sharing its position and width; a sensor's pixels sharing the register's
gain) has an arrow-shaped information: :class:`ArrowLayout` packs it and solves its step
through the Schur complement (:func:`schur`).
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
    grad, info : ndarray, shapes (P, F) and evaluate's info
        The gradient at ``x`` and the information the last step was solved with.
    """

    x: np.ndarray
    objective: np.ndarray
    done: np.ndarray
    stuck: np.ndarray
    iterations: np.ndarray
    grad: np.ndarray | None = None
    info: np.ndarray | None = None


def solve(A, b):
    """``A⁻¹ b`` for a stack of matrices; a singular one by least squares."""
    try:
        return np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.zeros_like(b)
        for i in range(A.shape[0]):  # rare: only when a matrix in the stack is singular
            out[i] = np.linalg.lstsq(A[i], b[i], rcond=None)[0]
        return out


def positive_definite(H):
    """Whether each matrix of a stack (P, F, F) is finite and positive definite."""
    ok = np.all(np.isfinite(H), axis=(1, 2))
    pos = np.zeros(H.shape[0], dtype=bool)
    if ok.any():
        pos[ok] = np.all(np.linalg.eigvalsh(H[ok]) > 0, axis=1)
    return pos


def invert_information(H):
    """Inverse of a stack of information matrices and whether each is positive definite."""
    P, F, _ = H.shape
    cov = np.full((P, F, F), np.nan)
    pos = positive_definite(H)
    if pos.any():
        try:  # the whole stack at once
            cov[pos] = np.linalg.inv(H[pos])
        except np.linalg.LinAlgError:  # one numerically singular matrix fails it whole
            for i in np.flatnonzero(pos):
                try:
                    cov[i] = np.linalg.inv(H[i])
                except np.linalg.LinAlgError:  # positive eigenvalues, yet singular
                    pos[i] = False
    return cov, pos


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


def maximize(
    evaluate,
    x0,
    *,
    lower,
    upper,
    tol,
    rtol=0.0,
    max_iter=100,
    max_step=1.0,
    accept_rtol=1e-12,
    max_damping=1e8,
    stuck_tol=0.0,
    step=dense_step,
    decrement=None,
    progress=None,
    keep_information=False,
):
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
    decrement : callable, optional
        ``decrement(grad, step)`` → what the step promises per row (n,), compared with
        the tolerance: by default the Newton decrement ½∇ᵀΔ. A row of many parts (an
        :class:`ArrowLayout`'s) may weigh its parts: :meth:`ArrowLayout.decrement`.
        Called with the number of rows that finished at each iteration.
    keep_information : bool
        ``evaluate(rows, x, information)`` takes a third argument, a boolean (n,) of the
        rows whose information it must return (the others' may be anything, or all of
        it None where none is asked for; their cost is the objective and gradient
        alone). A row keeps the information of the last point where it got one while
        its steps gain what they promised, within half of it (the information is then
        within a factor 2 of the curvature along the step, and so is the decrement that
        stops the row), and gets it anew with its next trial after one that did not:
        an information that stays right (the observed one, near the optimum) spares its
        cost at the other trials.

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
    # rows whose next trial brings its information (keep_information)
    fresh = np.zeros(P, dtype=bool)
    if keep_information:
        obj, grad, info = evaluate(np.arange(P), x, np.ones(P, dtype=bool))
    else:
        obj, grad, info = evaluate(np.arange(P), x)
    stuck = ~np.isfinite(obj)
    done = stuck.copy()

    def held(rows, g):
        # A parameter at its bound whose gradient points outwards stays there, and the
        # step is solved in the others (an active-set step): clipping a full step would
        # leave them moving as though it had moved too, and stall on the bound.
        return ((x[rows] <= lower[rows]) & (g < 0)) | ((x[rows] >= upper[rows]) & (g > 0))

    for _ in range(max_iter):
        active = np.flatnonzero(~done)
        if active.size == 0:
            break
        g = grad[active]
        x_a, lo, hi = x[active], lower[active], upper[active]
        d = np.clip(step(info[active], g, damping[active], held(active, g)), -max_step, max_step)
        x_new = np.clip(x_a + d, lo, hi)
        d = x_new - x_a
        # A step that promises less than the tolerance is not worth its evaluation (the
        # objective's round-off could even refuse it): the row is done.
        promise = 0.5 * np.einsum("pf,pf->p", g, d) if decrement is None else decrement(g, d)
        small = (np.abs(promise) < tol + rtol * np.abs(obj[active])) | (
            np.max(np.abs(d), axis=1, initial=0.0) < 1e-10
        )
        done[active[small]] = True
        move = ~small
        active, x_new = active[move], x_new[move]
        if active.size:
            if keep_information:
                res = evaluate(active, x_new, fresh[active])
                informed = fresh[active]
            else:
                res = evaluate(active, x_new)
                informed = np.ones(active.size, dtype=bool)
            better = res[0] >= obj[active] - accept_rtol * np.abs(obj[active])
            # what the step gained against what its quadratic model promised
            model = 0.5 * np.einsum("pf,pf->p", g[move], d[move])
            with np.errstate(invalid="ignore"):  # −inf (no likelihood) over no promise
                ratio = (res[0] - obj[active]) / np.where(model > 0, model, np.inf)
            idx = active[better]
            x[idx] = x_new[better]
            obj[idx] = res[0][better]
            grad[idx] = res[1][better]
            if res[2] is not None:  # None: no row asked for it
                info[active[better & informed]] = res[2][better & informed]
            good = better & (ratio >= 0.25)
            # The information was right along the step where it gained what it promised:
            # the ratio is 2 - 1/c for an information c times the curvature.
            fresh[active] = keep_information & ~(better & (np.abs(ratio - 1.0) <= 0.5))
            damping[active[good]] = np.maximum(damping[active[good]] / 10.0, 1e-12)
            damping[active[~good]] *= 10.0
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
    return Optimum(x, obj, done & ~stuck, stuck, iterations, grad, info)


def declined_step(opt, lower, upper, step=dense_step, largest=1e-3):
    """``opt.x`` with the undamped step each finished row declined (it promised less than
    the tolerance), not evaluated: the objective gains below the tolerance by it, but
    with an exact information (Newton's) it lands far nearer the optimum than the point
    where the decrement stopped the row. Stuck rows stay where they are, and so do rows
    whose step exceeds ``largest`` in a parameter: a tiny promise with a large step is a
    flat direction, where an unevaluated step is a guess."""
    x = opt.x.copy()
    rows = np.flatnonzero(opt.done)
    if rows.size == 0:
        return x
    P, F = x.shape
    lower = np.broadcast_to(np.asarray(lower, dtype=float), (P, F))[rows]
    upper = np.broadcast_to(np.asarray(upper, dtype=float), (P, F))[rows]
    g, xr = opt.grad[rows], x[rows]
    held = ((xr <= lower) & (g < 0)) | ((xr >= upper) & (g > 0))
    d = step(opt.info[rows], g, np.zeros(rows.size), held)
    small = np.all(np.isfinite(d) & (np.abs(d) <= largest), axis=1)
    x[rows] = np.clip(xr + np.where(small[:, None], d, 0.0), lower, upper)
    return x


# --------------------------------------------------------------------------------------
# Arrow-shaped information: many parts sharing a few parameters
# --------------------------------------------------------------------------------------
def diagonal_damped(H, damping):
    """``H + λ·diag H`` for a stack of square matrices and one λ per leading index."""
    d = np.einsum("...ii->...i", H)
    return H + (damping.reshape(damping.shape + (1,) * (d.ndim - damping.ndim)) * d)[
        ..., None
    ] * np.eye(H.shape[-1])


def schur(H, shared, own, damping=None, free_s=None, free_o=None):
    """An arrow-shaped information reduced to its shared parameters.

    A row's objective is a sum over its F parts (a bead's frames, a sensor's pixels);
    each part has parameters of its own (the columns ``own``) and all share ``shared``.
    The information is an arrow: eliminating the parts' blocks leaves the Schur
    complement ``S = H_ss − Σ_f H_sf H_ff⁻¹ H_fs``.

    Parameters
    ----------
    H : ndarray, shape (b, F, D, D)
        Each part's information in all of its D columns.
    shared, own : sequence of int
        The columns shared by the parts, and each part's own.
    damping : ndarray, shape (b,), optional
        Levenberg–Marquardt λ of each row: ``λ·diag`` added to both blocks.
    free_s, free_o : ndarray of bool, shapes (b, k) and (b, F, f), optional
        Parameters not held at a bound (a held one leaves the system).

    Returns
    -------
    S : (b, k, k), H_ff⁻¹ : (b, F, f, f), H_sf : (b, F, k, f)
    """
    fr, k = list(own), len(shared)
    eye_f, eye_k = np.eye(len(fr)), np.eye(k)
    Hff = H[..., fr, :][..., fr]
    Hss = H[..., shared, :][..., shared].sum(axis=1)
    Hsf = H[..., shared, :][..., fr]
    if damping is not None:
        Hff, Hss = diagonal_damped(Hff, damping), diagonal_damped(Hss, damping)
    if free_o is not None:
        fixed = ~free_o
        Hff = (
            np.where(fixed[..., :, None] | fixed[..., None, :], 0.0, Hff)
            + fixed[..., :, None] * eye_f
        )
        Hsf = np.where(free_o[..., None, :], Hsf, 0.0)
    Hff = Hff + 1e-12 * (1.0 + np.abs(Hff).max(axis=(-1, -2), keepdims=True)) * eye_f
    Hff_inv = np.linalg.inv(Hff)
    S = Hss - np.einsum("bfkj,bflj->bkl", Hsf @ Hff_inv, Hsf)
    if free_s is not None:
        fixed_s = ~free_s
        S = (
            np.where(fixed_s[:, :, None] | fixed_s[:, None, :], 0.0, S)
            + fixed_s[:, :, None] * eye_k
        )
    S = S + 1e-12 * (1.0 + np.abs(S).max(axis=(-1, -2), keepdims=True)) * eye_k
    return S, Hff_inv, Hsf


class ArrowLayout:
    """Rows of :func:`maximize` made of F parts with D columns each: the ``shared``
    columns once per row, then each part's ``own`` columns; any other column stays as
    the template has it. Its :meth:`step` solves the arrow through :func:`schur`."""

    def __init__(self, F, D, shared, own, lower, upper):
        self.F, self.D, self.shared, self.own = F, D, list(shared), list(own)
        lower, upper = np.broadcast_to(lower, (D,)), np.broadcast_to(upper, (D,))
        self.lower = np.concatenate([lower[self.shared], np.tile(lower[self.own], F)])
        self.upper = np.concatenate([upper[self.shared], np.tile(upper[self.own], F)])

    def pack(self, p):
        """(b·F, D) part rows → (b, k + F·f) rows (shared columns from part 0)."""
        pb = p.reshape(-1, self.F, self.D)
        return np.concatenate(
            [pb[:, 0, self.shared], pb[..., self.own].reshape(len(pb), -1)], axis=1
        )

    def unpack(self, x, template):
        """(b, k + F·f) rows into a copy of the (b·F, D) part rows ``template``."""
        k, p = len(self.shared), template.copy()
        p[:, self.shared] = np.repeat(x[:, :k], self.F, axis=0)
        p[:, self.own] = x[:, k:].reshape(len(p), len(self.own))
        return p

    def gradient(self, grad):
        """(b·F, D) part gradients → (b, k + F·f)."""
        gb = grad.reshape(-1, self.F, self.D)
        return np.concatenate(
            [gb[..., self.shared].sum(axis=1), gb[..., self.own].reshape(len(gb), -1)], axis=1
        )

    def decrement(self, grad, step):
        """What a step promises (:func:`maximize`'s ``decrement``): the shared
        parameters' part of the Newton decrement plus the parts' own, averaged over the
        parts, so that a row of many parts stops when the shared parameters and a typical
        part are each within the tolerance (their sum over thousands of parts would ask
        every part for far more)."""
        k = len(self.shared)
        shared = 0.5 * np.einsum("pf,pf->p", grad[:, :k], step[:, :k])
        own = 0.5 * np.einsum("pf,pf->p", grad[:, k:], step[:, k:])
        return shared + own / self.F

    def step(self, info, grad, damping, held):
        """The damped Newton step of whole rows (:func:`maximize`'s ``step``): the arrow
        system solved through its Schur complement, ``info`` each part's (b, F, D, D)."""
        k, n, f = len(self.shared), len(grad), len(self.own)
        held_f = held[:, k:].reshape(n, self.F, f)
        gs = np.where(held[:, :k], 0.0, grad[:, :k])
        gf = np.where(held_f, 0.0, grad[:, k:].reshape(n, self.F, f))
        S, Hff_inv, Hsf = schur(info, self.shared, self.own, damping, ~held[:, :k], ~held_f)
        # a held shared parameter does not move: the parts' steps see none of it
        Hsf = np.where(held[:, None, :k, None], 0.0, Hsf)
        r = gs - np.einsum("bfkj,bfj->bk", Hsf @ Hff_inv, gf)
        ds = np.linalg.solve(S, r[..., None])[..., 0]
        df = np.einsum("bfij,bfj->bfi", Hff_inv, gf - np.einsum("bfkj,bk->bfj", Hsf, ds))
        return np.concatenate([ds, df.reshape(n, -1)], axis=1)
