"""Calibration methods as parameter layouts over the one likelihood engine (paper Table 2).

=================  ===========================  ==================  ==================
method             photoelectrons E             EM gain g           e_per_adu φ
=================  ===========================  ==================  ==================
``is-adu``         one per level                1 (1× data only)    shared, free
``is-gain``        one per level                shared, free        fixed (input)
``gs``             one, shared                  one per set-point   fixed (input)
``gs-no1x``        one, shared (no 1× data)     one per set-point   fixed (input)
``gs-hierarchical`` E_i = μ + z_i σ_E (MAP)      one per set-point   fixed (input)
=================  ===========================  ==================  ==================

The 1× acquisition always uses the Poisson–normal model with g = 1. Every free parameter
is optimised in log space (μ of the hierarchical layout in photoelectrons), within wide
physical bounds (:data:`BOUNDS`). Starting values come from the moments of each pixel.
The mean–variance methods ``mv-adu`` and ``mv-gain`` are moment fits (:mod:`emccdcal.fit.mv`)
and do not use the engine.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import _roots, defaults
from .._util import weighted_gram
from ..model import adc
from ..errors import MethodError, OptionError
from . import comb, engine, profile, scores
from .engine import Layout, Parameter

__all__ = [
    "LIKELIHOOD_METHODS",
    "BOUNDS",
    "MethodError",
    "Series",
    "select_acquisitions",
    "check_options",
    "build_layout",
    "acquisition_estimates",
    "acquisition_bounds",
    "unpooled_bounds",
]

LIKELIHOOD_METHODS = defaults.LIKELIHOOD_METHODS

#: Bounds of the free parameters (photoelectrons e⁻, EM gain, e⁻/ADU).
BOUNDS = {
    "photoelectrons": (1e-3, 1e7),
    "em_gain": (1.0 + 1e-6, 1e5),
    "e_per_adu": (1e-3, 1e3),
}

#: Hyperprior of the hierarchical gain series: scales (photoelectrons) as the authors';
#: the centre of μ's prior is the shared-E (``gs``) estimate, or ``"setpoint"`` for theirs.
#: The authors' scales are absolute: 25 e⁻ is 7 % of their 370 e⁻ illumination, but 42 %
#: of a 60 e⁻ one, where the prior hardly pools (docs/validation.md); scale them with E.
HIERARCHICAL_DEFAULTS = {"mu_sd": 25.0, "sigma_sd": 25.0, "centre": "gs"}


@dataclass
class Series:
    """The acquisitions a method uses, for one block of P pixels.

    Attributes
    ----------
    blocks : list of AcquisitionBlock
    setpoints : ndarray, shape (A,)
        EM-gain set-point of each acquisition.
    e_per_adu : ndarray, shape (P,) or None
        Fixed ADU conversion factor (e⁻/ADU) where the method needs it.
    """

    blocks: list
    setpoints: np.ndarray
    e_per_adu: np.ndarray | None = None


def select_acquisitions(method, setpoints, levels, has_e_per_adu):
    """Indices of the acquisitions a method uses, in fitting order, or a clear error.

    Parameters
    ----------
    method : str
    setpoints : sequence of float
        Set-point of every acquisition of the manifest.
    levels : sequence of str or None
    has_e_per_adu : bool
        Whether the manifest (or the caller) gives φ.
    """
    sp = np.asarray(setpoints, dtype=float)
    idx = np.arange(sp.size)
    if method == "mv-adu":  # the mean–variance methods: their own rules
        if np.any(sp != 1):
            raise MethodError("mv-adu needs 1x (EM gain off) data only")
        return idx
    if method == "mv-gain":
        if not has_e_per_adu:
            raise MethodError(
                "mv-gain needs e_per_adu (e-/ADU): set it in the manifest or give it "
                "(e_per_adu=, --e-per-adu)"
            )
        return np.argsort(sp, kind="stable")
    if method not in LIKELIHOOD_METHODS:
        raise MethodError(
            f"unknown method {method!r}; choose one of {', '.join(LIKELIHOOD_METHODS)}, "
            "mv-adu, mv-gain"
        )
    if method == "is-adu":
        if np.any(sp != 1):
            bad = sorted({float(v) for v in sp[sp != 1]})
            raise MethodError(
                f"is-adu needs 1x (EM gain off) data only; the manifest has set-points {_fmt(bad)}"
            )
        return idx
    if not has_e_per_adu:
        levels = method.startswith("gs") and sp.size > 1 and np.all(sp == 1)
        raise MethodError(
            f"{method} is for a gain series, and this manifest is an intensity series at "
            "1x: calibrate phi from it with --method is-adu"
            if levels
            else f"{method} needs e_per_adu (e-/ADU): set it in the manifest or give it "
            "(e_per_adu=, --e-per-adu): an is-adu result, say"
        )
    if method == "is-gain":
        gains = np.unique(sp)
        if gains.size != 1 or gains[0] == 1:
            raise MethodError(
                "is-gain needs an intensity series at one EM-gain set-point above 1x; "
                f"the manifest has set-points {_fmt(gains)}"
            )
        return idx
    # gain series
    if method == "gs-no1x":
        idx = idx[sp != 1]
    uniq, counts = np.unique(sp[idx], return_counts=True)
    if np.any(counts > 1):
        raise MethodError(
            f"{method} needs one acquisition per set-point; set-point(s) "
            f"{_fmt(uniq[counts > 1])} appear more than once"
        )
    if method in ("gs", "gs-hierarchical") and 1.0 not in uniq:
        raise MethodError(f"{method} needs a 1x acquisition; use gs-no1x for a series without it")
    if uniq.size < 2:
        raise MethodError(
            f"{method} needs at least two set-points"
            + (" above 1x" if method == "gs-no1x" else "")
            + f"; the manifest has {_fmt(uniq)}"
        )
    return idx[np.argsort(sp[idx], kind="stable")]


def check_options(method, options):
    """The method options, checked, with defaults filled in; a clear error otherwise.

    Only ``gs-hierarchical`` takes options: ``mu_sd`` and ``sigma_sd`` (photoelectrons,
    positive: the scales of μ's normal prior and σ_E's half-normal one) and ``centre``
    (``"gs"`` or ``"setpoint"``, the centre of μ's prior).
    """
    options = dict(options or {})
    if method != "gs-hierarchical":
        if options:
            raise MethodError(
                f"{method} takes no options (given: {', '.join(map(str, options))}); "
                "only gs-hierarchical does"
            )
        return options
    unknown = sorted(set(options) - set(HIERARCHICAL_DEFAULTS))
    if unknown:
        raise MethodError(
            f"unknown gs-hierarchical option(s) {', '.join(map(repr, unknown))}; "
            f"known: {', '.join(HIERARCHICAL_DEFAULTS)}"
        )
    out = {**HIERARCHICAL_DEFAULTS, **options}
    for key in ("mu_sd", "sigma_sd"):
        try:
            out[key] = float(out[key])
        except (TypeError, ValueError):
            out[key] = float("nan")
        if not (np.isfinite(out[key]) and out[key] > 0):
            raise MethodError(
                f"gs-hierarchical option {key} must be a positive number of "
                f"photoelectrons (e-); got {options[key]!r}"
            )
    if out["centre"] not in ("gs", "setpoint"):
        raise MethodError(f"unknown hierarchical centre {out['centre']!r}; use 'gs' or 'setpoint'")
    return out


def _fmt(values):
    return ", ".join(f"{float(v):g}x" for v in values) or "none"


# --------------------------------------------------------------------------------------
# Starting values from moments
# --------------------------------------------------------------------------------------
def read_out_variance(acq):
    """The variance (ADU²) the read-out adds to the counts: σ², and the ADC's 1/12 where
    the model rounds (there ``read_noise`` is the analog σ, :mod:`emccdcal.model.adc`)."""
    return adc.count_variance(acq.read_noise, acq.poisson_normal)


def _signal(acq):
    """Offset-subtracted mean (ADU), at least a tiny positive value."""
    return np.maximum(acq.mean - acq.offset, 1e-6)


def _shape_photoelectrons(acq, phi):
    """E from one EM acquisition's shape, 2⟨S⟩²/(Var − σ²) (gamma model, F² = 2), at
    most ⟨S⟩·φ/1.1: where sampling leaves the excess variance below what a gain of 1
    gives (or negative), the start is at a gain of 1.1, not at E's bound, where the
    model cannot reach the data."""
    excess = np.maximum(acq.var - acq.read_noise**2, 2.2 * _signal(acq) / phi)
    return 2.0 * _signal(acq) ** 2 / excess


def _clip_log(value, name):
    lo, hi = BOUNDS[name]
    v = np.where(np.isfinite(value), value, np.sqrt(lo * hi))
    return np.log(np.clip(v, lo * 1.01, hi / 1.01))


# --------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------
def _intensity_layout(shared, A, const):
    """Layout of an intensity series: one ``shared`` parameter (``e_per_adu`` or
    ``em_gain``) and one E per level; ``x = [ln shared, ln E_1 … ln E_A]``; ``const``
    (P, A, 3) the fixed log-parameters."""
    col = {"em_gain": 1, "e_per_adu": 2}[shared]
    M = np.zeros((A, 3, 1 + A))
    M[:, col, 0] = 1.0
    M[np.arange(A), 0, 1 + np.arange(A)] = 1.0
    params = [Parameter(shared)] + [Parameter("photoelectrons", a) for a in range(A)]
    lo_e, hi_e = np.log(BOUNDS["photoelectrons"])
    lower = np.r_[np.log(BOUNDS[shared][0]), np.full(A, lo_e)]
    upper = np.r_[np.log(BOUNDS[shared][1]), np.full(A, hi_e)]
    return Layout(params, lower, upper, M, const)


def _gain_series_layout(setpoints, const):
    """Layout of a gain series with one E: ``x = [ln E, ln g_a of the EM acquisitions]``."""
    em = np.flatnonzero(setpoints != 1)
    A, F = setpoints.size, 1 + em.size
    M = np.zeros((A, 3, F))
    M[:, 0, 0] = 1.0
    M[em, 1, 1 + np.arange(em.size)] = 1.0
    params = [Parameter("photoelectrons")] + [Parameter("em_gain", a) for a in em]
    log_b = {k: np.log(v) for k, v in BOUNDS.items()}
    lower = np.r_[log_b["photoelectrons"][0], np.full(em.size, log_b["em_gain"][0])]
    upper = np.r_[log_b["photoelectrons"][1], np.full(em.size, log_b["em_gain"][1])]
    return Layout(params, lower, upper, M, const)


def layout_of(method, setpoints, e_per_adu, n_pixels):
    """The parameter layout of a method for ``n_pixels`` pixels, without data (φ (P,) in
    e⁻/ADU where the method holds it fixed). The hierarchical gain series, whose prior
    is centred on its data, has none without them (:func:`build_layout`)."""
    sp = np.asarray(setpoints, dtype=float)
    const = np.zeros((n_pixels, sp.size, 3))
    if method != "is-adu":
        const[:, :, 2] = np.log(e_per_adu)[:, None]
    if method in ("is-adu", "is-gain"):
        return _intensity_layout("e_per_adu" if method == "is-adu" else "em_gain", sp.size, const)
    if method in ("gs", "gs-no1x"):
        return _gain_series_layout(sp, const)
    raise MethodError(f"method {method!r} has no layout without its data")


def build_layout(method, series, options=None):
    """The parameter layout and per-pixel starting values of a method.

    Returns
    -------
    layout : Layout
    x0 : ndarray, shape (P, F)
    """
    options = check_options(method, options)
    blocks, sp = series.blocks, np.asarray(series.setpoints, dtype=float)
    A = len(blocks)
    P = blocks[0].values.shape[0]
    log_b = {k: np.log(v) for k, v in BOUNDS.items()}
    phi = series.e_per_adu

    if method == "is-adu":
        signal = np.stack([_signal(b) for b in blocks])
        excess = np.stack([np.maximum(b.var - read_out_variance(b), 1e-6) for b in blocks])
        phi0 = signal.sum(axis=0) / excess.sum(axis=0)  # photon transfer through origin
        x0 = np.column_stack(
            [_clip_log(phi0, "e_per_adu")] + [_clip_log(e, "photoelectrons") for e in signal * phi0]
        )
        return comb.profile_start(layout_of(method, sp, phi, P), blocks, x0, read_out_variance)

    if method == "is-gain":
        theta = np.stack(
            [np.maximum(b.var - b.read_noise**2, 1e-6) / (2.0 * _signal(b)) for b in blocks]
        )
        g0 = np.exp(np.median(np.log(theta), axis=0)) * phi
        E0 = np.stack([_signal(b) * phi / g0 for b in blocks])
        x0 = np.column_stack(
            [_clip_log(g0, "em_gain")] + [_clip_log(e, "photoelectrons") for e in E0]
        )
        return layout_of(method, sp, phi, P), x0

    # Gain series: E from the 1× acquisition where there is one, else from the shapes.
    em = np.flatnonzero(sp != 1)
    if sp[0] == 1:
        E0 = _signal(blocks[0]) * phi
    else:
        E0 = np.exp(np.median(np.log([_shape_photoelectrons(blocks[a], phi) for a in em]), axis=0))
    g0 = [_signal(blocks[a]) * phi / E0 for a in em]

    if method in ("gs", "gs-no1x"):
        x0 = np.column_stack(
            [_clip_log(E0, "photoelectrons")] + [_clip_log(g, "em_gain") for g in g0]
        )
        return layout_of(method, sp, phi, P), x0

    if method == "gs-hierarchical":
        mu_sd, sigma_sd = options["mu_sd"], options["sigma_sd"]
        own = np.array([_signal(blocks[a]) * phi / sp[a] for a in range(A)])
        own = np.clip(own, *BOUNDS["photoelectrons"])
        # Warm start from the shared-E gain series, the MAP's limit of strong pooling:
        # moments alone can start far off when the 1× anchor is weak (few e⁻, big φ).
        gs_layout, gs_x0 = build_layout("gs" if sp[0] == 1 else "gs-no1x", series)
        gs_fit = engine.fit(gs_layout, blocks, gs_x0)
        shared = gs_fit.x
        mu0 = np.exp(shared[:, 0])
        centre_rule = options["centre"]
        if centre_rule == "gs":
            centre = mu0  # the shared-E maximum-likelihood estimate, per pixel
        elif centre_rule == "setpoint":
            # The authors': mean over acquisitions of (⟨S⟩ − S0)·φ/set-point (they used
            # pixel (0,0)'s for every pixel; this is per pixel). Biased where the true
            # gains differ from the set-points, which they do (docs/validation.md).
            centre = own.mean(axis=0)
        # x = [ln E_1 … ln E_A, ln g_a for the EM acquisitions]; μ is profiled out.
        F = A + em.size
        M = np.zeros((A, 3, F))
        M[np.arange(A), 0, np.arange(A)] = 1.0
        M[em, 1, A + np.arange(em.size)] = 1.0
        const = np.zeros((P, A, 3))
        const[:, :, 2] = np.log(phi)[:, None]
        layout = HierarchicalLayout(
            parameters=[Parameter("photoelectrons", a) for a in range(A)]
            + [Parameter("em_gain", a) for a in em],
            lower=np.r_[
                np.full(A, log_b["photoelectrons"][0]), np.full(em.size, log_b["em_gain"][0])
            ],
            upper=np.r_[
                np.full(A, log_b["photoelectrons"][1]), np.full(em.size, log_b["em_gain"][1])
            ],
            matrix=M,
            constant=const,
            centre=centre,
            mu_sd=mu_sd,
            sigma_sd=sigma_sd,
            centre_fit=(gs_layout, gs_fit) if centre_rule == "gs" else None,
        )
        E_start = mu0[:, None] * np.exp(0.01 * np.sign(own.T - mu0[:, None]))  # off the kink
        x0 = np.column_stack([np.log(E_start), shared[:, 1:]])
        return layout, x0
    raise MethodError(f"unknown method {method!r}")


@dataclass
class HierarchicalLayout(Layout):
    """Non-centred hierarchical gain series (docs/methods.md), fitted for the MAP.

    The authors' model: E_i = μ + z_i σ_E with μ ~ N(centre, mu_sd), σ_E ~ HalfNormal
    (sigma_sd), z_i ~ N(0, 1), maximised without Jacobian terms (PyMC3 ``find_MAP``).
    With d_i = E_i − μ, the maximum over (σ_E, z) for given d is attained at
    σ_E² = sigma_sd·‖d‖ and equals −‖d‖/sigma_sd, so the same MAP is

        max over (E, g):  Σ_i ln L_i(E_i, g_i) + max over μ of
                          [−(μ − centre)²/(2 mu_sd²) − ‖E − μ‖/sigma_sd],

    where the inner maximum over μ (one-dimensional, concave) is solved exactly at every
    evaluation: the (σ_E, z) coordinates have a saddle at σ_E → 0 and μ alone a nearly
    flat valley, both of which stall an optimiser. ``x = [ln E_1 … ln E_A, ln g_i (EM
    acquisitions)]``, an ordinary linear layout for the likelihood; ‖·‖ is smoothed by
    1 e⁻ at 0 (worth at most 1/sigma_sd nats; it keeps the problem well conditioned
    where E_i = μ). μ, σ_E and z are recovered from the optimum.
    """

    centre: np.ndarray = None
    mu_sd: float = 25.0
    sigma_sd: float = 25.0
    smoothing: float = 1.0
    #: (layout, FitResult) of the shared-E fit whose E is the prior's centre, or None
    #: for a centre fixed in advance.
    centre_fit: tuple | None = None

    def subset(self, idx):
        centre_fit = None
        if self.centre_fit is not None:
            lay, res = self.centre_fit
            centre_fit = (
                lay.subset(idx),
                engine.FitResult(
                    res.x[idx],
                    res.cov[idx],
                    res.loglik[idx],
                    res.converged[idx],
                    res.iterations[idx],
                    res.n_floored[idx],
                ),
            )
        return replace(
            self, constant=self.constant[idx], centre=self.centre[idx], centre_fit=centre_fit
        )

    def estimator_covariance(self, blocks, x, h_inv):
        """Covariance of the MAP as a function of the data, the prior's centre included.

        With the centre c = Ê of a shared-E fit to the same frames, the MAP moves with
        every frame both directly and through c. Stacking the two estimating equations,
        each frame's influence on x is ``H⁻¹ (s + b · c · [I_c⁻¹ s_c]_E)``: s and s_c its
        scores in the two models, ``b = ∂²Q/∂x∂c`` and ``I_c⁻¹`` the centre fit's
        covariance. The covariance is the sum over frames of the influences' outer
        products. With a centre fixed in advance (``centre="setpoint"``) only the direct
        term remains: the sandwich H⁻¹ I H⁻¹, I by outer products of the scores. (That
        sandwich, applied to the gs-centred MAP, treats c as fixed and over-covers.)
        """
        P, F = x.shape
        A = self.constant.shape[1]
        b_vec = np.zeros((P, F))
        if self.centre_fit is not None:
            E = np.exp(x[:, :A])
            mu, d, r, _ = self._penalty(E)
            M = (
                np.eye(A)[None] / r[:, None, None]
                - np.einsum("pa,pb->pab", d, d) / r[:, None, None] ** 3
            ) / self.sigma_sd
            q_mumu = -1.0 / self.mu_sd**2 - M.sum(axis=(1, 2))
            dmu_dc = (1.0 / self.mu_sd**2) / -q_mumu  # the profiled μ follows its centre
            b_vec[:, :A] = M.sum(axis=2) * dmu_dc[:, None] * E  # ∂(∂Q/∂ln E)/∂c
            c_layout, c_fit = self.centre_fit
            c_scores = scores.value_scores(c_layout, blocks, c_fit.x)
            c_row = np.nan_to_num(c_fit.cov[:, 0, :]) * self.centre[:, None]  # dc per score
        cov = np.zeros((P, F, F))
        for a, (per_value, counts) in enumerate(scores.value_scores(self, blocks, x)):
            infl = per_value
            if self.centre_fit is not None:
                dc = np.einsum("pf,pkf->pk", c_row, c_scores[a][0])
                infl = per_value + b_vec[:, None, :] * dc[..., None]
            infl = infl @ np.swapaxes(h_inv, 1, 2)  # Σ_g H⁻¹_fg · infl_kg
            cov += weighted_gram(counts, infl)
        return cov

    def _penalty(self, E):
        """μ* and the prior terms' value, gradient and Hessian by (μ, d) at μ*."""
        a2, b = self.mu_sd**2, self.sigma_sd
        # ∂/∂μ of the concave 1-D objective decreases in μ: bisection is exact and safe
        # (Newton overshoots where the norm is nearly linear).
        lo = np.minimum(self.centre, E.min(axis=1)) - 10.0 * self.mu_sd
        hi = np.maximum(self.centre, E.max(axis=1)) + 10.0 * self.mu_sd

        def root_below(mu):
            d = E - mu[:, None]
            r = np.sqrt(np.sum(d * d, axis=1) + self.smoothing**2)
            return ~(-(mu - self.centre) / a2 + np.sum(d, axis=1) / (b * r) > 0)

        lo, hi = _roots.bisect(root_below, lo, hi, 100)
        mu = 0.5 * (lo + hi)
        d = E - mu[:, None]
        r = np.sqrt(np.sum(d * d, axis=1) + self.smoothing**2)
        value = -0.5 * (mu - self.centre) ** 2 / a2 - r / b
        return mu, d, r, value

    def log_prior(self, x):
        P, F = x.shape
        A = self.constant.shape[1]
        E = np.exp(x[:, :A])
        mu, d, r, value = self._penalty(E)
        a2, b = self.mu_sd**2, self.sigma_sd
        # Second derivatives of Q(μ, E) = −(μ−c)²/2a² − ‖E − μ‖/b.
        M = (
            np.eye(A)[None] / r[:, None, None]
            - np.einsum("pa,pb->pab", d, d) / r[:, None, None] ** 3
        ) / b
        Q_E = -d / (b * r[:, None])
        Q_EE = -M
        Q_Emu = M.sum(axis=2)  # ∂²Q/∂E∂μ
        Q_mumu = -1.0 / a2 - M.sum(axis=(1, 2))
        # Profile over μ: Hessian is the Schur complement (envelope theorem for the gradient).
        H_E = Q_EE - np.einsum("pa,pb->pab", Q_Emu, Q_Emu) / Q_mumu[:, None, None]
        # Chain rule to y = ln E.
        grad = np.zeros((P, F))
        hess = np.zeros((P, F, F))
        grad[:, :A] = Q_E * E
        hess[:, :A, :A] = H_E * E[:, :, None] * E[:, None, :]
        hess[:, np.arange(A), np.arange(A)] += Q_E * E
        return value, grad, hess

    def hyperparameters(self, x):
        """μ and σ_E = sqrt(sigma_sd ‖E − μ‖) (photoelectrons) of the authors' model."""
        A = self.constant.shape[1]
        mu, d, _, _ = self._penalty(np.exp(x[:, :A]))
        return mu, np.sqrt(self.sigma_sd * np.sqrt(np.sum(d * d, axis=1)))


def acquisition_estimates(layout, x, cov):
    """E, g and φ of every acquisition with delta-method standard errors.

    Returns
    -------
    dict
        ``photoelectrons``, ``em_gain``, ``e_per_adu`` (P, A) and ``<name>_se`` (P, A);
        an SE is 0 where the parameter is fixed by the layout.
    """
    logs, jac = layout.native(x)
    out = {}
    for j, name in enumerate(("photoelectrons", "em_gain", "e_per_adu")):
        value = np.exp(logs[:, :, j])
        J = jac[:, :, j, :]
        var_log = np.einsum("paf,pfg,pag->pa", J, cov, J)
        fixed = np.all(J == 0, axis=2)
        se = np.where(fixed, 0.0, value * np.sqrt(np.maximum(var_log, 0.0)))
        out[name] = value
        out[f"{name}_se"] = se
    return out


def acquisition_bounds(layout, blocks, fit, level=0.95):
    """Profile-likelihood bounds of E, g and φ per acquisition (:func:`emccdcal.fit.profile.profile_bounds`).

    Returns
    -------
    dict
        ``<name>_lower`` and ``<name>_upper`` (P, A) for ``photoelectrons``, ``em_gain``
        and ``e_per_adu``; NaN where the quantity is fixed by the layout.
    """
    bounds = [
        profile.profile_bounds(layout, blocks, fit, j, level=level) for j in range(layout.n_free)
    ]
    return _bounds_of_x(layout, *(np.column_stack(b) for b in zip(*bounds)))


def unpooled_bounds(layout, blocks, fit, level=0.95, weak_se=0.1):
    """Intervals of a hierarchical fit's E and g from the same model without its prior.

    The hierarchical MAP shrinks every set-point's E towards a shared one, so no interval
    centred on it has its nominal coverage both where the true E is shared (it
    over-covers) and where it is not (it under-covers). These intervals are those of the
    unpenalised ("unpooled") fit of the same layout, each set-point with its own E and
    g, started from the MAP: Wald on the log scale, and profile-likelihood bounds where
    the Wald one is unreliable (``SE(ln θ) > weak_se``, or the fit did not converge,
    as where a set-point's own data barely see E and its gain runs to 1). Measured
    coverage: 94.3–95.7 % for every E and g on both known-truth cameras, with the same
    and with differing illumination (docs/validation.md).

    Returns
    -------
    dict
        ``<name>_lower`` and ``<name>_upper`` (P, A) as :func:`acquisition_bounds`.
    """
    from scipy import special

    z = special.ndtri(0.5 + level / 2)  # norm.ppf, without importing scipy.stats
    P, F = fit.x.shape
    lower, upper = np.full((P, F), np.nan), np.full((P, F), np.nan)
    # Without the prior the acquisitions separate: fit each alone, on its own parameters.
    for a, block in enumerate(blocks):
        own = np.flatnonzero(np.any(layout.matrix[a] != 0, axis=0))
        if np.any(np.delete(layout.matrix, a, axis=0)[:, :, own]):
            raise OptionError("unpooled bounds need parameters of one acquisition each")
        alone = Layout(
            [layout.parameters[f] for f in own],
            layout.lower[own],
            layout.upper[own],
            layout.matrix[a : a + 1][:, :, own],
            layout.constant[:, a : a + 1],
        )
        free = engine.fit(alone, [block], fit.x[:, own])
        se = np.sqrt(np.einsum("pff->pf", free.cov))
        lower[:, own] = np.clip(free.x - z * se, alone.lower, alone.upper)
        upper[:, own] = np.clip(free.x + z * se, alone.lower, alone.upper)
        weak = ~free.converged[:, None] | ~(se <= weak_se)
        for k, f in enumerate(own):
            rows = np.flatnonzero(weak[:, k])
            if rows.size:
                start = engine.FitResult(
                    free.x[rows],
                    free.cov[rows],
                    free.loglik[rows],
                    free.converged[rows],
                    free.iterations[rows],
                    free.n_floored[rows],
                    objective=free.objective[rows],
                )
                lower[rows, f], upper[rows, f] = profile.profile_bounds(
                    alone.subset(rows), [block.take(rows)], start, k, level=level
                )
    return _bounds_of_x(layout, lower, upper)


def _bounds_of_x(layout, lower, upper):
    """Bounds on the free parameters (P, F) as bounds of every quantity that is one of
    them alone (a unit row of the layout's matrix): ``<name>_lower/_upper`` (P, A)."""
    P, A = lower.shape[0], layout.matrix.shape[0]
    out = {
        f"{n}_{s}": np.full((P, A), np.nan)
        for n in ("photoelectrons", "em_gain", "e_per_adu")
        for s in ("lower", "upper")
    }
    for j in range(layout.n_free):
        for a, k in zip(*np.nonzero(layout.matrix[:, :, j] == 1.0)):
            if np.count_nonzero(layout.matrix[a, k]) != 1:
                continue
            name = ("photoelectrons", "em_gain", "e_per_adu")[k]
            out[f"{name}_lower"][:, a] = np.exp(layout.constant[:, a, k] + lower[:, j])
            out[f"{name}_upper"][:, a] = np.exp(layout.constant[:, a, k] + upper[:, j])
    return out
