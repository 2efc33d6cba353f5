"""COTS's bias and covariance of the per-frame (G, H) of one spot (Mortensen and
Flyvbjerg's moment method as the paper extends it): the hat matrix's moments, the noise's
cumulants under a register model, the pseudo-true point, the small-sample bias and the
covariance (docs/cots.md)."""

from __future__ import annotations

import numpy as np

from .._util import weighted_gram


#: (c3, c4) of the gamma register (:func:`register_cumulants`), COTS as published.
GAMMA_CUMULANTS = (3.0, 12.0)


def _inv2(a):
    """Inverse of a stack of 2×2 matrices, shape (..., 2, 2)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    inv = np.empty_like(a)
    inv[..., 0, 0] = a[..., 1, 1]
    inv[..., 1, 1] = a[..., 0, 0]
    inv[..., 0, 1] = -a[..., 0, 1]
    inv[..., 1, 0] = -a[..., 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return inv / det[..., None, None]


# --------------------------------------------------------------------------------------
# 3. Bias and covariance of the per-frame (G, H)
# --------------------------------------------------------------------------------------
#: Frames whose (n × n) hat matrices are held at once.
_CHUNK = 128


def _thin_q(jacobian):
    """Orthonormal basis (F, n, p) of the columns of J: the hat matrix is Q Qᵀ."""
    j = np.asarray(jacobian, float)
    return np.linalg.qr(j.reshape(j.shape[0], -1, j.shape[-1]))[0]


def _hat_moments(expected, hat, read_var):
    """The parts of the noise moments that depend on the hat matrix only, per frame.

    With M = I − f, the moments of the residuals r = M ε and of the fitted values' error
    δ = f ε are linear in the pixel variances v, and v = 2 (G E − H) is linear in (G, H):
    ``X @ v = 2 G (X @ E) − 2 H (X @ 1)`` for X = M∘M, f∘f, M∘f, M∘M∘f. Those eight
    (F, n) arrays, the read-noise variance σ² (ADU², ``read_var``) and ``(M∘M∘f) @ σ²``
    (the third cumulant is the register's alone: read noise has none) are all the bias
    needs, at any (G, H).
    """
    e = np.asarray(expected, float)
    n = e.shape[1]
    m_mat = np.eye(n)[None] - hat
    out = {"read_var": np.broadcast_to(read_var, e.shape).astype(float)}
    for name, x in (("mm", m_mat**2), ("ff", hat**2), ("mf", m_mat * hat), ("mmf", m_mat**2 * hat)):
        out[name + "_e"] = np.einsum("fij,fj->fi", x, e)
        out[name + "_1"] = x.sum(axis=2)
    out["mmf_s"] = np.einsum("fij,fj->fi", m_mat**2 * hat, out["read_var"])
    return out


def _noise_moments(mom, e, alpha, cumulants):
    """Per pixel: v, E r², E δ², E r δ, E r² δ, E r² δ² at true (G, H) = alpha."""
    g, hh = alpha[:, :1], alpha[:, 1:]

    def lin(name):
        return 2 * g * mom[name + "_e"] - 2 * hh * mom[name + "_1"]

    v = 2.0 * (g * e - hh)
    m, d, c = lin("mm"), lin("ff"), lin("mf")
    t = cumulants[0] * g * (lin("mmf") - mom["mmf_s"])  # κ3 = c3 G (v − σ²)
    return v, m, d, t, m * d + 2.0 * c**2


def _uu(w, e):
    """Σ_i w_i u_i u_iᵀ per frame for u_i = ∂v_i/∂(G, H) = (2 E_i, −2): shape (F, 2, 2)."""
    out = np.empty((len(e), 2, 2))
    out[:, 0, 0] = 4 * np.sum(w * e * e, axis=1)
    out[:, 0, 1] = out[:, 1, 0] = -4 * np.sum(w * e, axis=1)
    out[:, 1, 1] = 4 * np.sum(w, axis=1)
    return out


def _quad(c, e):
    """u_iᵀ C u_i per pixel for a per-frame 2×2 C, shape (F, n)."""
    return 4 * (c[:, :1, 0] * e * e - 2 * c[:, :1, 1] * e + c[:, 1:, 1])


def _expected_score(ast, e, moments):
    """E ψ(α*) of the variance fit at (G*, H*) = ast, and its Jacobian by α*.

    ψ = ∂L/∂(G, H) with the fitted E_i; expanded to second order in δ = f ε.
    """
    _, m, d, t, erd = moments
    gs = ast[:, :1]
    iv = 1.0 / (2.0 * (gs * e - ast[:, 1:]))
    iv2 = iv * iv
    iv3 = iv2 * iv
    iv4 = iv2 * iv2
    s_u = iv - m * iv2 + 4 * gs * t * iv3 + 4 * gs**2 * (d * iv3 - 3 * erd * iv4)
    s_e1 = -2 * t * iv2 + 4 * gs * (-d * iv2 + 2 * erd * iv3)
    score = np.stack(
        [2 * np.sum(s_u * e, axis=1) + s_e1.sum(axis=1), -2 * np.sum(s_u, axis=1)], axis=1
    )
    # derivatives by v* (which moves with α* as ∂v*/∂α* = (2E, −2)) and by G* itself
    du_dv = 2 * m * iv3 - iv2 - 12 * gs * t * iv4 + 4 * gs**2 * (-3 * d * iv4 + 12 * erd * iv4 * iv)
    du_dg = 4 * t * iv3 + 8 * gs * (d * iv3 - 3 * erd * iv4)
    de_dv = 4 * t * iv3 + 4 * gs * (2 * d * iv3 - 6 * erd * iv4)
    de_dg = 4 * (-d * iv2 + 2 * erd * iv3)
    ddv = du_dv * 2 * e + du_dg  # ∂s_u/∂G*
    jac = np.empty((len(e), 2, 2))
    jac[:, 0, 0] = np.sum(2 * e * ddv + de_dv * 2 * e + de_dg, axis=1)
    jac[:, 0, 1] = -2 * np.sum(2 * e * du_dv + de_dv, axis=1)
    jac[:, 1, 0] = -2 * np.sum(ddv, axis=1)
    jac[:, 1, 1] = 4 * np.sum(du_dv, axis=1)
    return score, jac


def _fourth_cumulant(g, v, read_var, cumulants):
    """κ4 = c4 G² (v − σ²) per pixel: the register's; read noise (Gaussian) has none."""
    return cumulants[1] * g**2 * np.maximum(v - read_var, 0.0)


def _small_sample_bias(e, alpha, read_var, cumulants):
    """O(1/n) bias of the variance fit with E_i known (second-order M-estimator expansion).

    Zero for Gaussian noise; not zero for the register's heavy-tailed noise (κ4).
    """
    g = alpha[:, :1]
    v = 2.0 * (g * e - alpha[:, 1:])
    iv2 = 1.0 / v**2
    wv = 2 * v**2 + _fourth_cumulant(g, v, read_var, cumulants)  # Var ε_i²
    a_inv = _inv2(_uu(iv2, e))
    c0 = a_inv @ _uu(wv * iv2 * iv2, e) @ a_inv
    coef = (2 * _quad(c0, e) - 2 * wv * iv2 * _quad(a_inv, e)) * iv2 / v
    inner = np.stack([2 * np.sum(coef * e, axis=1), -2 * np.sum(coef, axis=1)], axis=1)
    return np.einsum("fjk,fk->fj", a_inv, inner)


def _pseudo_true(mom, e, alpha, cumulants, start=None, max_iter=50):
    """Where each frame's variance fit lands on average when the truth is ``alpha``.

    Solves E ψ_f(α*) = 0 (Newton from ``start``, default ``alpha``, kept inside v* > 0)
    and adds the small-sample bias. Returns that (F, 2), the root α* itself (a warm start
    for a nearby ``alpha``) and whether every frame's solve converged.
    """
    moments = _noise_moments(mom, e, alpha, cumulants)
    ast = (alpha if start is None else start).copy()
    ok = np.zeros(len(e), bool)
    for _ in range(max_iter):
        score, jac = _expected_score(ast, e, moments)
        step = -np.einsum("fij,fj->fi", _inv2(jac), score)
        step[~np.isfinite(step)] = 0.0
        t = np.ones(len(e))
        for _half in range(30):
            trial = ast + t[:, None] * step
            bad = ~np.all(trial[:, :1] * e - trial[:, 1:] > 0, axis=1) | (trial[:, 0] <= 0)
            if not bad.any():
                break
            t[bad] *= 0.5
        ast = trial
        ok = np.all(np.abs(t[:, None] * step) <= 1e-10 * (np.abs(ast) + np.abs(ast[:, :1])), axis=1)
        if ok.all():
            break
    return ast + _small_sample_bias(e, alpha, mom["read_var"], cumulants), ast, ok


def _covariance(expected, qh, alpha, alpha_fit, read_var, cumulants):
    """Sandwich covariance of the per-frame (Ĝ, Ĥ), not bias-corrected.

    ``alpha`` sets the true noise (v, κ4), ``alpha_fit`` is where the fit lands on
    average (:func:`_pseudo_true`), where the objective's curvature is taken.
    ``qh`` (F, n, p) is an orthonormal basis of the Jacobian's columns (f = qh qhᵀ).
    O(n² p) per frame.
    """
    e = np.asarray(expected, float)
    g = alpha[:, :1]
    v = 2.0 * (g * e - alpha[:, 1:])
    vs = 2.0 * (alpha_fit[:, :1] * e - alpha_fit[:, 1:])
    k4 = _fourth_cumulant(g, v, read_var, cumulants)
    qt = np.swapaxes(qh, 1, 2)
    hat = qh @ qt
    m2 = (np.eye(e.shape[1])[None] - hat) ** 2
    m = np.einsum("fij,fj->fi", m2, v)
    # M V M = V − f V − V f + f V f, with f = Q Qᵀ of rank p.
    vq = v[:, :, None] * qh
    fv = qh @ np.swapaxes(vq, 1, 2)
    mvm = -fv - np.swapaxes(fv, 1, 2) + qh @ (qt @ vq) @ qt
    idx = np.arange(e.shape[1])
    mvm[:, idx, idx] += v
    u = np.stack([2.0 * e, np.full_like(e, -2.0)], axis=-1)
    cu = u / vs[..., None] ** 2
    # Cov(r_i², r_j²) = 2 (MVM)_ij² + Σ_k M_ik² κ4_k M_jk²
    b = 2 * np.swapaxes(cu, 1, 2) @ (mvm**2 @ cu)
    w = np.swapaxes(m2, 1, 2) @ cu  # (F, n, 2): Σ_i M_ik² c_i
    b += weighted_gram(k4, w)
    a = weighted_gram((2 * m / vs - 1) / vs**2, u)
    a_inv = _inv2(a)
    return a_inv @ b @ a_inv


def register_cumulants(register, gain, e_per_adu):
    """The register's third and fourth pixel cumulants per unit of register variance.

    For compound-Poisson input through a register whose one-electron output X has raw
    moments μ_k, a pixel's register variance is ``v_reg = λ μ_2/φ²`` (ADU²) and its higher
    cumulants ``κ_k = λ μ_k/φ^k``. In COTS's gain G (F² = 2: ``G = g F²/(2φ)``) they are
    ``κ3 = c3·G·v_reg`` and ``κ4 = c4·G²·v_reg`` with ``c3 = 2 g μ3/μ2²`` and
    ``c4 = 4 g² μ4/μ2³``: 3 and 12 for the gamma register (an exponential X), 2.98 and
    11.84 at 5× for a 536-stage cascade.

    Parameters
    ----------
    register : a register of :mod:`emccdcal.model.noise` (``EMModel(...).register``)
    gain : float
        COTS's G under F² = 2, ADU/e⁻ (where the gain g is read: the cumulants vary slowly).
    e_per_adu : float
        φ, e⁻/ADU.

    Returns
    -------
    (float, float)
        c3 and c4 (dimensionless).

    Examples
    --------
    >>> from emccdcal.model.noise import EMModel
    >>> register_cumulants(EMModel("gamma").register, 1.3, 3.859)
    (3.0, 12.0)
    >>> c3, c4 = register_cumulants(EMModel("cascade", 536).register, 1.163, 3.859)
    >>> round(c3, 3), round(c4, 2)
    (2.982, 11.84)
    """
    g = float(register.gain_from_gain_f2(2.0 * gain * e_per_adu)[0])
    mu = register.single_electron_moments(max(g, 1.0))
    return (float(2.0 * g * mu[2] / mu[1] ** 2), float(4.0 * g**2 * mu[3] / mu[1] ** 3))


def variance_bias_covariance(
    expected, jacobian, alpha, *, read_noise=0.0, cumulants=GAMMA_CUMULANTS
):
    """Bias and sandwich covariance of the per-frame variance fit (G, H).

    The fitted E_i come from the same counts as the residuals, so the residuals are
    smaller than the noise (``E r_i² = v_i − 2 f_ii v_i + (fVf)_ii``, f the hat matrix)
    and the plain variance fit is biased low: by O(p/n) (p = 5 spot parameters, n pixels)
    on average, much more where a few bright pixels carry high leverage. The bias here is
    where the fit lands on average, α* − α: the root of the expected score with the
    residual and fitted-value moments to second order in f ε (a first-order theory in
    1/n, solved rather than linearised, since the shift is ~10 %), plus the O(1/n)
    small-sample bias of the variance fit itself (zero for Gaussian noise, not for the
    register's skewed, heavy-tailed noise). The third and fourth cumulants are the
    register's alone, ``κ3 = c3 G (v − σ²)`` and ``κ4 = c4 G² (v − σ²)``
    (:func:`register_cumulants`; c3 = 3, c4 = 12 for the gamma register): the Gaussian
    read noise σ adds to the variance only. The covariance is the sandwich at α*.
    Derivation: ``docs/cots.md``.

    Parameters
    ----------
    expected : array_like, shape (F, n) or (F, h, w)
        Fitted expected counts E_i (ADU).
    jacobian : array_like, shape (F, n, 5) or (F, h, w, 5)
        ∂E_i/∂(spot parameters) at the fits (:attr:`SpotFit.jacobian`).
    alpha : array_like, shape (F, 2) or (2,)
        True (G, H) = (G, G·S0) (ADU/e⁻, ADU²/e⁻): where the bias is evaluated.
    read_noise : float or array_like of shape (F, n) or (F, h, w)
        Read-noise SD σ of the pixels (ADU); 0 as in COTS as published.
    cumulants : (float, float)
        (c3, c4) of :func:`register_cumulants`; the gamma register's by default.

    Returns
    -------
    bias : ndarray, shape (F, 2)
        E[α̂] − α: subtract it from α̂ (evaluated at the truth, or at the corrected value).
    cov : ndarray, shape (F, 2, 2)
        Covariance of the uncorrected α̂.
    """
    e = np.asarray(expected, float).reshape(len(expected), -1)
    alpha = np.broadcast_to(np.asarray(alpha, float), (len(e), 2)).copy()
    read_var = np.square(np.asarray(read_noise, float))
    read_var = np.broadcast_to(read_var.reshape(len(e), -1) if read_var.ndim else read_var, e.shape)
    qh = _thin_q(jacobian)
    mom = _hat_moments(e, qh @ np.swapaxes(qh, 1, 2), read_var)
    fit_point = _pseudo_true(mom, e, alpha, cumulants)[0]
    return fit_point - alpha, _covariance(e, qh, alpha, fit_point, read_var, cumulants)
