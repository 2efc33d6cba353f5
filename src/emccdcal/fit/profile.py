"""How an estimate moves with what the fit holds fixed: a given φ's sensitivity
(:func:`e_per_adu_sensitivity`) and profile-likelihood bounds (:func:`profile_bounds`),
each a layout of the engine (:mod:`emccdcal.fit.engine`) with one parameter freed or
pinned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._optimize import invert_information, solve
from .engine import Layout, _evaluate, fit

__all__ = ["e_per_adu_sensitivity", "profile_bounds", "with_phi_error"]


@dataclass
class _PhiFree:
    """A layout with one more free parameter (last): a shift of ln φ in every acquisition."""

    base: object

    def subset(self, idx):
        return _PhiFree(self.base.subset(idx))

    def native(self, x):
        logs, jac = self.base.native(x[:, :-1])
        logs = logs.copy()
        logs[:, :, 2] += x[:, -1:]
        shift = np.zeros(jac.shape[:-1] + (1,))
        shift[:, :, 2, 0] = 1.0
        return logs, np.concatenate([jac, shift], axis=-1)

    @property
    def newton_steps(self):
        return self.base.newton_steps

    def log_prior(self, x):
        value, grad, hess = self.base.log_prior(x[:, :-1])
        P, F = x.shape
        grad_full, hess_full = np.zeros((P, F)), np.zeros((P, F, F))
        grad_full[:, :-1], hess_full[:, :-1, :-1] = grad, hess
        return value, grad_full, hess_full


def e_per_adu_sensitivity(layout, blocks, x):
    """How the estimate moves with a fixed φ: d x̂ / d ln φ (P, F), at the estimate ``x``.

    The estimate solves ∂ℓ/∂x = 0 at the given φ, so by the implicit function theorem
    d x̂/d ln φ = −(∂²ℓ/∂x²)⁻¹ ∂²ℓ/∂x ∂ln φ: both from the observed information of the
    layout with ln φ freed as one more parameter. An error of ln φ of variance v then adds
    ``v · J Jᵀ`` to the covariance of x̂: it moves every E and g of a pixel together.
    """
    info = _evaluate(_PhiFree(layout), blocks, np.column_stack([x, np.zeros(len(x))]), 2)[4]
    return -solve(info[:, :-1, :-1], info[:, :-1, -1])


def with_phi_error(cov, sens, rel_se):
    """The covariance (P, F, F) of the estimates with the error of a given φ added: its
    relative SE ``rel_se`` (P,) moves every E and g of a pixel together by the
    sensitivity ``sens`` (P, F) (:func:`e_per_adu_sensitivity`), adding
    ``rel_se²·J Jᵀ``."""
    rel_var = np.asarray(rel_se, dtype=float) ** 2
    return cov + rel_var[:, None, None] * sens[:, :, None] * sens[:, None, :]


@dataclass
class _Pinned:
    """A layout with its free parameter ``j`` held at per-pixel values (P,)."""

    base: Layout
    j: int
    value: np.ndarray

    @property
    def lower(self):
        return np.delete(self.base.lower, self.j)

    @property
    def upper(self):
        return np.delete(self.base.upper, self.j)

    def subset(self, idx):
        return _Pinned(self.base.subset(idx), self.j, self.value[idx])

    def _full(self, x):
        return np.insert(x, self.j, self.value, axis=1)

    def native(self, x):
        logs, jac = self.base.native(self._full(x))
        return logs, np.delete(jac, self.j, axis=-1)

    @property
    def newton_steps(self):
        return self.base.newton_steps

    def log_prior(self, x):
        value, grad, hess = self.base.log_prior(self._full(x))
        return value, np.delete(grad, self.j, 1), np.delete(np.delete(hess, self.j, 1), self.j, 2)


def profile_bounds(
    layout, blocks, result, j, *, level=0.95, tol=0.005, xtol=1e-4, max_steps=20, first_step=1.0
):
    """Profile-likelihood interval of the free parameter ``x[:, j]`` for every pixel.

    The bounds are where the profile deviance ``2 (ℓ̂ − max ℓ | x_j)`` (with a prior: of
    the penalised objective) reaches the χ²₁ quantile of ``level``. They follow the
    likelihood where it is skewed, unlike the Wald interval ``x̂ ± z·SE``. The likelihood
    is conditional on the offset and read-noise maps: where ``result.cov`` includes the
    maps' errors (and there is no prior), the target grows by the ratio of that variance
    of ``x_j`` to the inverse observed information's, which widens a Gaussian profile to
    exactly ``± z·SE`` and keeps a skewed one's shape. Each side is
    searched on the signed root deviance r, which is close to linear in x_j, by Newton's
    steps from the Wald bound: r's slope at each refit comes free of another fit, since
    the profile's derivative is ∂ℓ/∂x_j where the other parameters are at their optimum
    (the envelope theorem). A step stays within a bracket every refit narrows (before r
    passes its target: at most four times as far out as the farthest point inside) and
    must halve r's miss, or the bracket's middle is taken. Every step refits the other
    parameters, warm-started from the farthest point found inside.

    Parameters
    ----------
    layout, blocks : as for :func:`fit`.
    result : FitResult
        The unconstrained fit (its ``x``, ``cov`` and ``objective``; a pixel whose ``cov``
        is NaN, such as one stopped at a bound, is searched from ``first_step``).
    j : int
        Index of the free parameter.
    level : float
        Confidence level of the interval.
    tol : float
        Accept a bound when the signed root deviance is within ``tol`` of its target.
    xtol : float
        ... or when it is bracketed within ``xtol`` in ``x_j`` (where the deviance rises
        too steeply for ``tol``: a parameter pushed against another one's bound).
    max_steps : int
        Refits per side; pixels whose bound is not found then get NaN.
    first_step : float
        Largest first step from the optimum in ``x_j`` (where the SE is large because the
        information is nearly singular, the Wald bound can be far beyond the model's
        reach).

    Returns
    -------
    lower, upper : ndarray, shape (P,)
        Bounds on ``x[:, j]`` (the free parameter's own scale, e.g. a logarithm); the
        layout's bound where the deviance stays below the quantile up to it. NaN where
        not found.
    """
    from scipy import special

    x_hat, P = result.x, result.x.shape[0]
    se = np.sqrt(np.abs(result.cov[:, j, j]))
    target = np.full(P, np.sqrt(special.chdtri(1, 1 - level)))  # chi2.ppf(level, 1)
    if not hasattr(layout, "estimator_covariance") and not np.any(layout.log_prior(x_hat)[2]):
        conditional, pos_def = invert_information(_evaluate(layout, blocks, x_hat, 2)[4])
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = result.cov[:, j, j] / conditional[:, j, j]
        target *= np.sqrt(np.where(pos_def & np.isfinite(ratio) & (ratio > 1), ratio, 1.0))
    out = []
    for side in (-1.0, 1.0):
        bound = np.full(P, np.nan)
        edge = layout.lower[j] if side < 0 else layout.upper[j]
        room = side * (edge - x_hat[:, j])  # distance to the layout's bound, ≥ 0
        ok = np.isfinite(result.objective)
        bound[ok & (room <= 0)] = edge
        active = np.flatnonzero(ok & (room > 0))
        z = target[active]
        # |t| = distance from the optimum; the bracket (t_in: farthest point with r below
        # its target; t_out: nearest beyond it, NaN until found). The first step: z·SE, at
        # most first_step (also where the SE is NaN).
        t = np.minimum(np.fmin(z * np.maximum(se[active], 1e-6), first_step), room[active])
        t_in, t_out = np.zeros(active.size), np.full(active.size, np.nan)
        miss_before = np.full(active.size, np.inf)
        start = np.delete(x_hat[active], j, axis=1)
        for _ in range(max_steps):
            if active.size == 0:
                break
            value = x_hat[active, j] + side * t
            # exact steps: single-precision ones can crawl short of a pixel's optimum
            # (an outlier in its tail), and the deviance would read that shortfall
            fitted = fit(
                _Pinned(layout.subset(active), j, value), [b.take(active) for b in blocks],
                start, max_iter=50, covariance=False, rough_steps=False,
            )  # fmt: skip
            r = np.sqrt(np.maximum(2.0 * (result.objective[active] - fitted.objective), 0.0))
            miss = np.abs(r - z)
            done = (miss < tol) | ((t >= room[active]) & (r < z))
            bound[active[done]] = value[done]
            inside = r < z
            t_in, t_out = np.where(inside, t, t_in), np.where(inside, t_out, t)
            narrow = ~done & (t_out - t_in < xtol)  # False while t_out is NaN
            bound[active[narrow]] = x_hat[active[narrow], j] + side * 0.5 * (
                t_in[narrow] + t_out[narrow]
            )
            done |= narrow
            keep = ~done
            # Warm start from the farthest point inside: one beyond the target can be far
            # off, with nuisance parameters from which the next fit does not recover.
            start = np.where(inside[:, None], fitted.x, start)
            active, z, r, t, t_in, t_out, miss, miss_before, start = (
                a[keep] for a in (active, z, r, t, t_in, t_out, miss, miss_before, start)
            )
            if active.size == 0:
                break
            # dr/dt = −(dℓ/dt)/r, and dℓ/dt = ±∂ℓ/∂x_j at the pinned optimum
            at = np.insert(fitted.x[keep], j, value[keep], axis=1)
            grad = _evaluate(
                layout.subset(active), [b.take(active) for b in blocks], at, 1, information=False
            )[3][:, j]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                step = t + (z - r) * r / (-side * grad)
            bracketed = np.isfinite(t_out)
            reach = np.where(bracketed, t_out, np.minimum(4.0 * t_in, room[active]))
            newton = np.isfinite(step) & (step > t_in) & (miss < 0.5 * miss_before)
            # Newton's step where it stays inside and halves the miss; else the bracket's
            # middle, or before a bracket the reach (also where Newton's passes it)
            t = np.where(
                newton & (step < reach), step, np.where(bracketed, 0.5 * (t_in + t_out), reach)
            )
            miss_before = miss
        out.append(bound)
    return out[0], out[1]
