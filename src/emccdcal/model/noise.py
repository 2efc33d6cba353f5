"""The EMCCD camera noise model, exact, in count (ADU) units.

Generative model (Ryan et al. 2021, Theory; docs/methods.md):

1. photoelectrons ``n ~ Poisson(E)`` per pixel per frame (``photoelectrons`` = E, e⁻);
2. EM register: ``X | n ~ Gamma(shape=n, scale=g)`` electrons, ``X = 0`` when ``n = 0``
   (``em_gain`` = g, dimensionless) — the paper's model, the default — or, with
   ``em_model="cascade"``, the exact Bernoulli cascade of N stages (:class:`EMModel`,
   docs/cascade.md);
3. read-out: ``S = S0 + X / φ + ε`` with ``ε ~ N(0, σ²)`` (``e_per_adu`` = φ in e⁻/ADU,
   ``offset`` = S0 and ``read_noise`` = σ in ADU).

``em_gain == 1`` means *no* multiplication: the Poisson–normal (PN) model
``S = S0 + n/φ + ε``. It is a separate model, not the g → 1 limit of the
Poisson–gamma–normal (PGN) one (docs/methods.md, test case 4).

Definition of the probability of a count
----------------------------------------
The count ``S`` is an integer. As in the paper and the authors' code, the probability of
the integer ``k`` is the model's density evaluated at ``k``; we normalise it over the
integers, ``p(k) = f(k) / Σ_j f(j)``, so that it is a proper pmf for any read noise (a
"discrete Gaussian" read-out). ``read_noise`` is therefore the standard deviation of dark
counts *including* ADC quantisation, which is what dark frames measure. The normaliser
differs from 1 by less than 1e-30 for ``read_noise`` ≥ 1.9 ADU and matters only below.

How it is computed
------------------
Everything follows from the cumulant generating function of the count,

    K(s) = s·S0 + σ²s²/2 + E·(M(s) − 1),   M(s) = 1/(1 − sθ) (PGN, θ = g/φ),
                                            M(s) = exp(s/φ)   (PN),

where M is the moment generating function of one photoelectron's output in ADU. The pmf on
a window of integers is one inverse real FFT of the characteristic function
``exp(K(iω))`` sampled at the window's DFT frequencies (docs/methods.md), summed over
aliases ``ω + 2πj`` so that a read noise below 2 ADU, whose density is not band-limited,
is still exact. FFT round-off limits the *relative* accuracy of a single window to values
above about 1e-7 of its peak; further out we evaluate the exponentially tilted
distribution ``f(k)·e^{tk−K(t)}`` (characteristic function ``exp(K(t+iω) − K(t))``), whose
peak sits where we need it, and undo the tilt in log space. Derivatives with respect to
any parameter λ are one more inverse FFT each, of ``∂λK · exp(K)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._util import check_number
from ..errors import OptionError
from .cascade import DEFAULT_STAGES

__all__ = [
    "EMModel",
    "as_em_model",
    "choose_em_model",
    "logpmf",
    "pmf",
    "logpmf_grad",
    "mean",
    "variance",
    "third_cumulant",
    "excess_noise_factor",
    "logpmf_rows",
    "LogpmfTable",
]


# --------------------------------------------------------------------------------------
# Parameter checking
# --------------------------------------------------------------------------------------
#: Threads of each FFT (scipy.fft's ``workers``; -1: every CPU). A process that already
#: runs one task per CPU (a Dask worker of a calibration) sets it to 1.
FFT_WORKERS = -1


def _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise):
    return (
        check_number("photoelectrons", photoelectrons, minimum=0.0, scalar=False),
        check_number("em_gain", em_gain, minimum=1.0, scalar=False),
        check_number("e_per_adu", e_per_adu, positive=True, scalar=False),
        check_number("offset", offset, minimum=0.0, scalar=False),
        check_number("read_noise", read_noise, positive=True, scalar=False),
    )


def _check_counts(counts):
    arr = np.asarray(counts)
    if arr.dtype.kind in "iu":
        values = arr.astype(np.int64)
    else:
        values = np.asarray(arr, dtype=float)
        if not np.all(np.isfinite(values)) or np.any(values != np.round(values)):
            raise OptionError("counts must be integers (raw ADU values)")
        values = values.astype(np.int64)
    if np.any(values < 0):
        raise OptionError("counts must be non-negative (raw ADU, never offset-subtracted)")
    return values


@dataclass(frozen=True)
class EMModel:
    """The model of the EM register.

    ``"gamma"`` is the paper's: the output of n electrons is Gamma(n, g), excess-noise
    factor 2 at every gain. ``"cascade"`` is the exact register of ``stages`` stages, in
    each of which every electron makes one more with probability p = g^{1/N} − 1
    (:mod:`emccdcal.model.cascade`); its excess-noise factor is below 2 (1.795 at
    g = 5, N = 536). Both reduce to no multiplication (Poisson–normal) at g = 1.

    Examples
    --------
    >>> str(EMModel("cascade", 604)), str(EMModel())
    ('cascade (604 stages)', 'gamma')
    """

    name: str = "gamma"
    stages: int = DEFAULT_STAGES

    def __post_init__(self):
        if self.name not in EM_MODELS:
            raise OptionError(f"unknown em_model {self.name!r}; choose one of "
                              f"{', '.join(EM_MODELS)}")
        from .cascade import _check_stages

        # The gamma model has no stages: one gamma model, whatever was passed.
        stages = _check_stages(self.stages) if self.cascade else DEFAULT_STAGES
        object.__setattr__(self, "stages", stages)

    @property
    def cascade(self) -> bool:
        """Whether this is the exact register."""
        return self.name == "cascade"

    def __str__(self) -> str:
        return f"cascade ({self.stages} stages)" if self.cascade else "gamma"

    @property
    def attrs(self) -> dict:
        """The model as a result's attributes: ``em_model``, and ``register_stages`` for
        the cascade."""
        return {"em_model": self.name,
                **({"register_stages": int(self.stages)} if self.cascade else {})}

    @classmethod
    def from_attrs(cls, attrs) -> EMModel | None:
        """The model a result's attributes record (:attr:`attrs`), or None where they
        record none (a result without a likelihood, such as ``mv-adu``)."""
        if "em_model" not in attrs:
            return None
        return cls(str(attrs["em_model"]), int(attrs.get("register_stages", DEFAULT_STAGES)))


#: The register models :class:`EMModel` knows.
EM_MODELS = ("gamma", "cascade")


def choose_em_model(given, em_model=None, stages=None) -> EMModel:
    """The register model of a run: the caller's ``em_model``/``stages`` where given,
    else ``given`` (a manifest's, or None), else the gamma model. ``stages`` alone
    selects the cascade."""
    if em_model is None and stages is None:
        return given or EMModel()
    if em_model is None:
        em_model = "cascade" if given is None or stages is not None else given.name
    return as_em_model(em_model, stages)


def as_em_model(em_model="gamma", stages=None) -> EMModel:
    """An :class:`EMModel` from a name (or an :class:`EMModel`) and optional stages;
    stages go with the cascade only."""
    if isinstance(em_model, EMModel):
        if stages is not None and (not em_model.cascade or int(stages) != em_model.stages):
            raise OptionError(f"stages={stages!r} disagrees with the {em_model} model")
        return em_model
    if not isinstance(em_model, str):
        raise OptionError(f"em_model must be one of {', '.join(EM_MODELS)}, got {em_model!r}")
    if stages is not None and em_model == "gamma":
        raise OptionError("stages are the cascade model's: give em_model='cascade' with "
                          "them (the gamma model has none)")
    return EMModel(em_model, DEFAULT_STAGES if stages is None else stages)


# --------------------------------------------------------------------------------------
# Moments (of the continuous model; equal to the pmf's up to the discrete normaliser)
# --------------------------------------------------------------------------------------
def mean(photoelectrons, em_gain, e_per_adu, offset, read_noise=1.0):
    """Mean count, ADU: ``S0 + g·E/φ`` (PN: ``S0 + E/φ``).

    Parameters
    ----------
    photoelectrons : array_like
        E, mean photoelectrons per pixel per frame (e⁻).
    em_gain : array_like
        g, mean EM gain (dimensionless, ≥ 1; exactly 1 selects the PN model).
    e_per_adu : array_like
        φ, ADU conversion factor (e⁻/ADU).
    offset : array_like
        S0, offset (ADU).
    read_noise : array_like, optional
        σ, read noise (ADU); unused, accepted so that all moment functions share one
        signature.

    Examples
    --------
    >>> float(mean(370.0, 5.0, 3.859, 587.0, 15.0))
    1066.398807981...
    """
    E, g, phi, S0, _ = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    return S0 + g * E / phi


def variance(photoelectrons, em_gain, e_per_adu, offset, read_noise, *, em_model="gamma",
             stages=None):
    """Variance of the count, ADU²: ``σ² + F²E(g/φ)²`` with the register model's F²
    (:func:`excess_noise_factor`: 2 for the gamma model), ``σ² + E/φ²`` at g = 1.

    Parameters are those of :func:`mean`, and the register model as in :func:`logpmf`.

    Examples
    --------
    >>> round(float(variance(370.0, 5.0, 3.859, 587.0, 15.5, em_model="cascade")), 4)
    1355.3292
    """
    E, g, phi, _, sigma = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    F2 = excess_noise_factor(g, em_model=em_model, stages=stages)
    return sigma**2 + np.where(g == 1, E / phi**2, F2 * E * (g / phi) ** 2)


def third_cumulant(photoelectrons, em_gain, e_per_adu, offset, read_noise):
    """Third cumulant of the count, ADU³: ``6E(g/φ)³`` (the gamma model) or ``E/φ³`` (PN)."""
    E, g, phi, _, _ = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    return np.where(g == 1, E / phi**3, 6 * E * (g / phi) ** 3)


def excess_noise_factor(em_gain, *, em_model="gamma", stages=None):
    """Excess-noise factor F² of the model's multiplication, ``Var(X)/(g²E)``.

    2 for the gamma model (any g > 1), 1 for no multiplication (g = 1); for the cascade
    model that of an N-stage register (:func:`emccdcal.model.cascade.excess_noise_factor`),
    below 2.
    """
    g = check_number("em_gain", em_gain, minimum=1.0, scalar=False)
    model = as_em_model(em_model, stages)
    if model.cascade:
        from .cascade import excess_noise_factor as exact

        return np.asarray(exact(g, model.stages))
    return np.where(g == 1, 1.0, 2.0)


# --------------------------------------------------------------------------------------
# The cumulant generating function and its parameter derivatives
# --------------------------------------------------------------------------------------
# Rows are parameter sets ("pixels"); every function takes 1-D arrays of length P and
# a complex array ``s`` of shape (P, M). ``scale`` is θ = g/φ (ADU per electron, PGN)
# or 1/φ (ADU per photoelectron, PN); ``shift`` is the offset relative to the window's
# first count, ADU.

#: Names of the native parameters the window evaluator differentiates by.
NATIVE = ("photoelectrons", "scale", "offset", "read_noise")


def _electron_mgf(s, scale, pn):
    """M(s) − 1 of one photoelectron's output (ADU), without cancellation at small s."""
    sa = s * scale[:, None]
    return np.where(pn[:, None], np.expm1(sa), sa / (1.0 - sa))


def _cgf(s, E, scale, shift, sigma, pn):
    return (
        s * shift[:, None]
        + 0.5 * (sigma[:, None] * s) ** 2
        + E[:, None] * _electron_mgf(s, scale, pn)
    )


def _cgf_derivatives(s, E, scale, shift, sigma, pn, second=False):
    """First (and optionally second) derivatives of K(s) by the native parameters.

    Returns ``first`` (dict name -> (P, M)) and ``second`` (dict (name, name) -> (P, M),
    upper triangle only, zero entries omitted).
    """
    sa = s * scale[:, None]
    pn_ = pn[:, None]
    # d M(s) / d scale, and its second derivative
    m = np.where(pn_, np.exp(sa), 1.0 / (1.0 - sa))
    dm = np.where(pn_, s * m, s * m * m)
    first = {
        "photoelectrons": np.where(pn_, np.expm1(sa), sa / (1.0 - sa)),
        "scale": E[:, None] * dm,
        "offset": s,
        "read_noise": sigma[:, None] * s * s,
    }
    if not second:
        return first, {}
    d2m = np.where(pn_, s * s * m, 2.0 * s * s * m * m * m)
    sec = {
        ("photoelectrons", "scale"): dm,
        ("scale", "scale"): E[:, None] * d2m,
        ("read_noise", "read_noise"): s * s,
    }
    return first, sec


def _cumulants(E, scale, shift, sigma, pn):
    """Mean and variance (ADU, ADU²) of the count relative to the window start."""
    mu = shift + E * scale
    var = sigma**2 + np.where(pn, E * scale**2, 2.0 * E * scale**2)
    return mu, var


def _tilted_family(t, E, scale, shift, sigma, pn):
    """Parameters of the exponentially tilted distribution ``f(y) e^{ty - K(t)}``.

    Tilting keeps the family: the photoelectron mean becomes E·M(t), the PGN scale
    θ/(1 − tθ) (PN: unchanged), and the Gaussian centre moves by σ²t.
    """
    ta = t * scale
    E_t = np.where(pn, E * np.exp(ta), E / (1.0 - ta))
    scale_t = np.where(pn, scale, scale / (1.0 - ta))
    return E_t, scale_t, shift + sigma**2 * t, sigma


def _real_cgf(t, E, scale, shift, sigma, pn):
    """K(t) for real t (PGN requires t·θ < 1), per row."""
    ta = t * scale
    return t * shift + 0.5 * (sigma * t) ** 2 + E * np.where(pn, np.expm1(ta), ta / (1.0 - ta))


def _extent(E, scale, shift, sigma, pn, width=12.0, cascade=None):
    """Window [lo, hi] (ADU, relative) outside which the distribution's mass is negligible.

    ``width`` standard deviations either side of the mean; below 80 photoelectrons also
    ``width`` read-noise widths around the zero-electron peak (which carries e^-E) and,
    for the PGN, forty single-electron scales more on the right for the exponential tail.
    """
    if cascade is not None:
        return _cascade_extent(np.zeros(E.shape), E, scale, shift, sigma, cascade, width)
    mu, var = _cumulants(E, scale, shift, sigma, pn)
    sd = np.sqrt(var)
    few = E < 80.0
    lo = np.where(few, np.minimum(mu - width * sd, shift - width * sigma), mu - width * sd)
    tail = np.where(pn, width * scale, np.where(few, 40.0 * scale, width * scale))
    hi = mu + width * sd + tail + 1.0
    return lo, hi


def _alias_count(sigma_min):
    """Aliases ±J of the characteristic function needed for read noise ``sigma_min`` (ADU).

    The density at the integers has the DTFT Σ_j Φ(ω + 2πj) (Poisson summation); alias j
    is bounded by exp(−σ²(2π|j| − π)²/2) and dropped once that is below e^-46.
    """
    return int(np.floor((np.sqrt(92.0) / sigma_min + np.pi) / (2.0 * np.pi)))


def _band_limit(E, scale, sigma, pn, n, level=80.0):
    """Highest rfft bin m beyond which |Φ(2πm/n)| < e^-level (for J = 0), in closed form.

    −ln|Φ(ω)| is at least B(ω) = σ²ω²/2 + E·ω²θ²/(1 + ω²θ²) for the PGN, and at least
    σ²ω²/2 + 2Eψ²ω²/π² for the PN while ωψ ≤ π (1 − cos x ≥ 2x²/π² there; beyond, the
    Gaussian factor alone). B is increasing, so the ω_c solving B(ω_c) = 80 bounds the
    band; for the PGN it is the root of a quadratic in ω².
    """
    s2 = 0.5 * sigma**2
    t2 = scale**2
    # PGN: s2·u + E·t2·u/(1 + t2·u) = level, u = ω²  →  a u² + b u − level = 0
    a = s2 * t2
    b = s2 + E * t2 - level * t2
    with np.errstate(divide="ignore", invalid="ignore"):
        u_pgn = np.where(a > 0, (-b + np.sqrt(b * b + 4.0 * a * level)) / (2.0 * a), level / s2)
        u_pn = level / (s2 + 2.0 * E * t2 / np.pi**2)
    w_pn = np.sqrt(u_pn)
    w_pn = np.where(w_pn * scale <= np.pi, w_pn, np.sqrt(level / s2))  # Gaussian bound only
    w = np.where(pn, w_pn, np.sqrt(u_pgn))
    m = np.ceil(w * n / (2.0 * np.pi)).astype(np.int64) + 2
    return np.where(w >= np.pi, n // 2 + 1, np.minimum(m, n // 2 + 1))


def _window(E, scale, shift, sigma, pn, n, *, tilt=None, derivs=False, second=False,
            names=NATIVE, cascade=None, band=None):
    """Tilted pmf of the counts 0 … n−1 relative to the window start, and derivatives.

    Parameters
    ----------
    E, scale, shift, sigma : ndarray, shape (P,)
        Photoelectrons (e⁻), ADU per electron (θ = g/φ, or 1/φ for PN), offset relative
        to the window start (ADU) and read noise (ADU).
    pn : ndarray of bool, shape (P,)
        Poisson–normal rows (em_gain == 1).
    n : int
        Window length; the distribution's mass outside the window must be negligible
        (it wraps around).
    tilt : ndarray, shape (P,), optional
        Exponential tilt t per row (1/ADU); ``None`` means 0.
    derivs, second : bool
        Also return first (and second) derivatives of the tilted density by the native
        parameters ``names``, on the same tilted scale.
    names : tuple of str
        Which of :data:`NATIVE` (with ``cascade``: :data:`NATIVE_CASCADE`) to
        differentiate by (each costs one inverse FFT).
    cascade : _Cascade, optional
        The exact register of every row (``scale`` is then 1/φ, ADU per electron, and
        ``pn`` is ignored); ``None``: the gamma model (or Poisson–normal rows).
    band : int, optional
        DFT bins to evaluate (cascade only; default: from a bound, widened until the
        transform has died out at the edge).

    Returns
    -------
    p : ndarray, shape (P, n)
        ``f(y)·exp(t·y − K(t))``: the density at the integers y, tilted. Round-off is
        about 1e-16 of ``p.max(axis=1)``.
    d1 : dict
        name -> (P, n) first derivatives (same tilted scale; divide by ``p`` for the
        derivative of log f).
    d2 : dict
        (name, name) -> second derivatives of f, upper triangle, as :class:`Spectrum`:
        not transformed, because they are only ever summed against weights at the data
        (:meth:`Spectrum.dot`), which costs one forward FFT for all pairs instead of an
        inverse FFT for each.
    """
    P = E.shape[0]
    t = np.zeros(P) if tilt is None else tilt
    J = _alias_count(float(sigma.min()))
    if cascade is not None:
        K_t, _, _, E_t, theta_t = _cascade_real(t, E, scale, shift, sigma, cascade)
        m_hi = n // 2 + 1 if J else _cascade_band_limit(E_t, theta_t, scale, sigma, n, band)
    elif J == 0:
        E_t, scale_t, _, _ = _tilted_family(t, E, scale, shift, sigma, pn)
        m_hi = int(_band_limit(E_t, scale_t, sigma, pn, n).max())
        K_t = _real_cgf(t, E, scale, shift, sigma, pn)
    else:
        m_hi = n // 2 + 1
        K_t = _real_cgf(t, E, scale, shift, sigma, pn)
    omega = 2.0 * np.pi * np.arange(m_hi) / n
    phi = 0.0
    d1 = {name: 0.0 for name in names} if derivs else {}
    d2 = {}
    for j in range(-J, J + 1):
        s = t[:, None] + 1j * (omega[None, :] + 2.0 * np.pi * j)
        if cascade is None:
            cf = np.exp(_cgf(s, E, scale, shift, sigma, pn) - K_t[:, None])
            if derivs:
                first, sec = _cgf_derivatives(s, E, scale, shift, sigma, pn, second)
        else:
            order = 2 if second else 1 if derivs else 0
            K, first, sec = _cascade_cgf(s, E, scale, shift, sigma, cascade, order, names)
            cf = np.exp(K - K_t[:, None])
        phi = phi + cf
        if derivs:
            for name in names:
                d1[name] = d1[name] + first[name] * cf
            if second:
                for a_i, a in enumerate(names):
                    for b in names[a_i:]:
                        term = first[a] * first[b] + sec.get((a, b), 0.0)
                        d2[(a, b)] = d2.get((a, b), 0.0) + term * cf
    if cascade is not None and m_hi < n // 2 + 1:
        # The band was a bound's guess: where the transform has not died out at its
        # edge (a tilted window's wide electron distribution), widen it and start again.
        edge = np.abs(phi[:, -1])
        if np.any(edge > _CASCADE_EDGE):
            return _window(E, scale, shift, sigma, pn, n, tilt=tilt, derivs=derivs,
                           second=second, names=names, cascade=cascade,
                           band=min(n // 2 + 1, 2 * m_hi))
    p = _irfft(phi, n)
    d1 = {name: _irfft(v, n) for name, v in d1.items()}
    d2 = {key: Spectrum(v, n) for key, v in d2.items()}
    return p, d1, d2


# --------------------------------------------------------------------------------------
# The exact (Bernoulli-cascade) register
# --------------------------------------------------------------------------------------
#: Native parameters of the cascade model: ``scale`` is 1/φ (ADU per electron), the gain
#: and the register's clock-induced charge enter through the register's transform.
NATIVE_CASCADE = ("photoelectrons", "scale", "em_gain", "register_cic", "offset",
                  "read_noise")
#: A cascade window's band ends where the tilted transform is below this (its values
#: beyond are below the FFT's round-off of ~1e-16 of the peak).
_CASCADE_EDGE = np.exp(-40.0)


class _Cascade:
    """The exact register of a set of parameter rows: N stages, and each row's mean gain
    g and register clock-induced-charge rate (e⁻ per pixel per frame entering the
    register at a uniformly random stage)."""

    def __init__(self, stages, gain, cic):
        self.stages = int(stages)
        self.gain = np.asarray(gain, dtype=float)
        self.cic = np.broadcast_to(np.asarray(cic, dtype=float), self.gain.shape)

    def take(self, idx):
        return _Cascade(self.stages, self.gain[idx], self.cic[idx])

    @property
    def has_cic(self) -> bool:
        return bool(np.any(self.cic > 0))

    def transform(self, u, order, cic):
        from .cascade import register_transform

        return register_transform(u, self.gain, self.stages, order=order, cic=cic)


def _cascade_cgf(s, E, scale, shift, sigma, casc, order=0, names=()):
    """K(s) of the cascade model and its derivatives by the native parameters.

    ``K(s) = s·shift + σ²s²/2 + E·v(s/φ) + c·v̄(s/φ)`` with ``v = G_N(e^u) − 1`` of one
    electron and ``v̄`` its mean over the stages a register-CIC electron enters at.
    Returns ``(K, first, second)``; ``second`` holds both orders of every pair.
    """
    cic = casc.has_cic or "register_cic" in names
    T = casc.transform(s * scale[:, None], order, cic)
    Ec, c, g = E[:, None], casc.cic[:, None], casc.gain[:, None]

    def mix(key):  # E·v + c·v̄, and likewise for a derivative of v
        return Ec * T[key] + c * T["cic_" + key] if cic else Ec * T[key]

    K = s * shift[:, None] + 0.5 * (sigma[:, None] * s) ** 2 + mix("v")
    first, sec = {}, {}
    if order >= 1:
        first = {"photoelectrons": T["v"], "scale": s * mix("u"), "em_gain": mix("g") / g,
                 "offset": s, "read_noise": sigma[:, None] * s * s}
        if cic:
            first["register_cic"] = T["cic_v"]
    if order >= 2:
        sec = {("photoelectrons", "scale"): s * T["u"],
               ("photoelectrons", "em_gain"): T["g"] / g,
               ("scale", "scale"): s * s * mix("uu"),
               ("scale", "em_gain"): s * mix("ug") / g,
               ("em_gain", "em_gain"): (mix("gg") - mix("g")) / g**2,
               ("read_noise", "read_noise"): s * s}
        if cic:
            sec[("scale", "register_cic")] = s * T["cic_u"]
            sec[("em_gain", "register_cic")] = T["cic_g"] / g
        sec.update({(b, a): v for (a, b), v in list(sec.items())})
    return K, first, sec


def _cascade_real(t, E, scale, shift, sigma, casc):
    """K(t), K'(t), K''(t) of the cascade model at real tilts t (P,), and the tilted
    photoelectron mean and single-electron mean output (ADU), per row."""
    cic = casc.has_cic
    if not cic and not np.any(t):
        # Untilted: the moments in closed form (mean output g, second moment g²F²).
        from .cascade import excess_noise_factor

        g = casc.gain
        F2 = excess_noise_factor(g, casc.stages)
        return (np.zeros(E.shape), shift + E * g * scale, sigma**2 + E * (g * scale) ** 2 * F2,
                E, g * scale)
    T = casc.transform(t * scale, 2, cic)

    def mix(key):
        return E * T[key] + casc.cic * T["cic_" + key] if cic else E * T[key]

    K = t * shift + 0.5 * (sigma * t) ** 2 + mix("v")
    dK = shift + sigma**2 * t + scale * mix("u")
    d2K = sigma**2 + scale**2 * mix("uu")
    growth = 1.0 + T["v"]  # G(e^{t/φ}): the tilted photoelectron mean is E·G
    # The tilted single-electron output; far below the mean it is one electron.
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = np.where(growth > 0, scale * T["u"] / growth, scale)
    return K, dK, d2K, E * growth, theta


def _cascade_extent(t, E, scale, shift, sigma, casc, width=12.0):
    """Window [lo, hi] (ADU, relative) of the cascade model tilted by t, as :func:`_extent`
    (mean ± ``width`` SDs, the zero-electron peak and a tail of forty single-electron
    outputs when photoelectrons are few)."""
    _, mu, var, E_t, theta_t = _cascade_real(t, E, scale, shift, sigma, casc)
    sd = np.sqrt(var)
    few = E_t < 80.0
    lo = np.where(few, np.minimum(mu - width * sd, shift + sigma**2 * t - width * sigma),
                  mu - width * sd)
    hi = mu + width * sd + np.where(few, 40.0, width) * theta_t + 1.0
    return lo, hi


def _cascade_band_limit(E_t, theta_t, scale, sigma, n, band=None):
    """DFT bins to evaluate for cascade rows: the gamma model's bound at e^-40 with half
    the photoelectrons (the cascade's transform decays like the gamma model's with
    F²/2 ≥ ½ of them at low frequencies, and like it saturates at high ones), which
    :func:`_window` widens where the transform has not died out at the edge (e^-40 of
    its value at 0: the FFT's round-off is larger). Where the read noise does not
    suppress the electron lattice's revival of the transform at ω = 2πφ, the Gaussian's
    band."""
    if band is not None:
        return int(band)
    full = n // 2 + 1
    w_gauss = np.sqrt(160.0) / sigma
    if np.any(2.0 * np.pi / scale < w_gauss):
        m = int(np.ceil(float(w_gauss.max()) * n / (2.0 * np.pi))) + 2
        return min(m, full)
    pn = np.zeros(E_t.shape, dtype=bool)
    return int(_band_limit(0.5 * E_t, theta_t, sigma, pn, n, level=40.0).max())


class Spectrum:
    """The first ``m`` DFT bins (P, m) of a real window of length ``n``, as :func:`_window`
    builds them (the characteristic function at ω = 2πk/n; the window is its inverse).

    Summing a window against weights needs no inverse FFT: by Parseval,
    ``Σ_y w(y) f(y) = (1/n) Σ_k c_k Re(F_k Ŵ_k)`` with ``Ŵ = rfft(w)``, ``c_0 = 1``,
    ``c_k = 2`` for the bins that stand for a conjugate pair, and 1 at Nyquist.
    """

    def __init__(self, spectrum, n):
        self.spectrum, self.n = spectrum, n

    def window(self):
        """The window itself (P, n)."""
        return _irfft(self.spectrum, self.n)

    @staticmethod
    def weights_spectrum(weights, m):
        """``rfft`` of a (P, n) weight grid, its first ``m`` bins: shared by every dot."""
        from scipy import fft

        return fft.rfft(weights, axis=-1, workers=FFT_WORKERS)[:, :m]

    def dot(self, weights_hat):
        """``Σ_y w(y) f(y)`` per row, from ``weights_spectrum(w, m)`` (P, m)."""
        m, n = self.spectrum.shape[1], self.n
        c = np.full(m, 2.0)
        c[0] = 1.0
        if n % 2 == 0 and m == n // 2 + 1:
            c[-1] = 1.0
        return np.einsum("k,pk->p", c, (self.spectrum * weights_hat).real) / n


def _irfft(spectrum, n):
    """The window (P, n) of the first DFT bins (P, m) of the density (m ≤ n//2 + 1).

    The density's DFT is the characteristic function at −ω, the conjugate of the one
    evaluated at +ω; the bins beyond ``m`` are zero (irfft pads them).
    """
    from scipy import fft

    return fft.irfft(np.conj(spectrum), n=n, axis=-1, workers=FFT_WORKERS)


# --------------------------------------------------------------------------------------
# Exact log-pmf at arbitrary counts: windows, tilted where the counts lie in a tail
# --------------------------------------------------------------------------------------
#: A window value is trusted where it is at least this fraction of the window's peak:
#: FFT round-off is ~1e-16 of the peak, so the relative error there is below ~1e-9.
_TRUSTED = 1e-7
#: The cascade's transform comes from N stages of a recursion whose relative round-off
#: grows to ~N·1e-16 (1e-13 at 536 stages): its windows are trusted only closer to their
#: peak, and tilted windows centred on the rest.
_TRUSTED_CASCADE = 1e-4
#: Longest tilted window (counts) before the few-electron PGN tail goes to quadrature.
_MAX_WINDOW = 2**20


def _window_start(E, scale, S0, sigma, pn, cascade=None):
    """Integer start and length of the window covering the distribution (absolute ADU)."""
    lo, hi = _extent(E, scale, S0, sigma, pn, cascade=cascade)
    start = np.floor(lo).astype(np.int64)
    return start, (np.ceil(hi).astype(np.int64) - start + 1)


def _saddlepoint(k, E, scale, S0, sigma, pn):
    """Tilt t with K'(t) = k (the tilted mean at count k), by bisection."""

    def dcgf(t):
        ta = t * scale
        with np.errstate(over="ignore", invalid="ignore"):
            growth = np.where(pn, np.exp(ta), 1.0 / (1.0 - ta) ** 2)
            return S0 + sigma**2 * t + E * scale * growth

    t_lo = np.minimum(0.0, (k - S0 - E * scale) / sigma**2)
    t_hi = np.maximum(0.0, (k - S0) / sigma**2)
    t_hi = np.where(pn, t_hi, np.minimum(t_hi, (1.0 - 1e-12) / scale))
    for _ in range(100):
        mid = 0.5 * (t_lo + t_hi)
        above = dcgf(mid) > k
        t_hi = np.where(above, mid, t_hi)
        t_lo = np.where(above, t_lo, mid)
    return 0.5 * (t_lo + t_hi)


def _cascade_saddlepoint(k, E, scale, S0, sigma, casc):
    """Tilt t that puts the cascade model's tilted mean K'(t) within half a tilted SD of
    count k: Newton's method on K' from the gamma model's saddlepoint, kept inside a
    bracket, bisecting where it leaves the bracket or stops converging. (Any tilt gives
    exact values; the saddlepoint only centres the window on the target.)

    The bracket: the electron part of K' is positive and increasing in t, so
    ``S0 + σ²t ≤ K'(t)`` everywhere and ``K'(t) ≤ K'(0) + σ²t`` for t ≤ 0.
    """
    mean0 = _cascade_real(np.zeros(E.shape), E, scale, S0, sigma, casc)[1]
    lo = np.minimum(0.0, (k - mean0) / sigma**2)
    hi = (k - S0) / sigma**2
    # Start from the gamma model's saddlepoint (closed-form cumulants, cheap): its
    # register differs only in F², so Newton then needs a few steps, not a bisection.
    t = _saddlepoint(k, E, casc.gain * scale, S0, sigma, np.zeros(E.shape, dtype=bool))
    t = np.where((t > lo) & (t < hi), t, 0.5 * (lo + hi))
    previous = np.full(E.shape, np.inf)  # |K'(t) − k| of the step before
    for _ in range(100):
        with np.errstate(over="ignore", invalid="ignore"):
            _, dK, d2K, _, _ = _cascade_real(t, E, scale, S0, sigma, casc)
        bad = ~np.isfinite(dK) | ~np.isfinite(d2K)
        above = bad | (dK > k)
        hi = np.where(above, t, hi)
        lo = np.where(above, lo, t)
        miss = np.abs(dK - k)
        close = ~bad & (miss < 0.5 * np.sqrt(d2K))
        if np.all(close):
            break
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = t - (dK - k) / d2K
        # Newton where it stays in the bracket and is converging; else bisect.
        slow = ~(miss < 0.5 * previous)
        previous = np.where(bad, np.inf, miss)
        inside = ~bad & ~slow & (newton > lo) & (newton < hi)
        t = np.where(close, t, np.where(inside, newton, 0.5 * (lo + hi)))
    return t


def _cascade_spa(k, t, E, scale, S0, sigma, casc, grad):
    """Saddlepoint approximation of log f(k) at tilts t with K'(t) ≈ k, for the far tail
    beyond the longest window (relative error of order 1/(number of electrons) there,
    far below 1e-10 of the peak): ``K(t) − tk − ½ ln(2πK''(t))``; gradients by the
    envelope theorem, ``∂K/∂λ`` at the fixed t."""
    K, _, d2K, _, _ = _cascade_real(t, E, scale, S0, sigma, casc)
    logf = K - t * k - 0.5 * np.log(2.0 * np.pi * d2K)
    if not grad:
        return logf, {}
    names = _cascade_names(casc)
    _, first, _ = _cascade_cgf(t[:, None].astype(complex), E, scale, S0, sigma, casc, 1, names)
    grads = {name: first[name][:, 0].real for name in names}
    grads["offset"] = grads["offset"] - t
    return logf, grads


def _cascade_names(casc):
    """Native parameters of cascade rows (``register_cic`` only where it is used)."""
    return tuple(n for n in NATIVE_CASCADE if n != "register_cic" or casc.has_cic)


def _log_normaliser(E, scale, S0, sigma, pn, derivs=False, cascade=None):
    """log Σ_k f(k) per row (and its native derivatives): 0 unless read noise < ~3 ADU.

    By Poisson summation Σ_k f(k) = Σ_j Φ(2πj) = 1 + 2 Σ_{j≥1} Re Φ(2πj).
    """
    U = E.shape[0]
    J = _alias_count(float(sigma.min())) + 1
    names = NATIVE if cascade is None else _cascade_names(cascade)
    grads = {name: np.zeros(U) for name in names}
    if J <= 1 and float(sigma.min()) > 3.1:
        return np.zeros(U), grads
    s = 2j * np.pi * np.arange(1, J + 1)[None, :] * np.ones((U, 1))
    # Only the fractional part of the offset matters at the frequencies 2πj.
    frac = S0 - np.floor(S0)
    if cascade is None:
        cf = np.exp(_cgf(s, E, scale, frac, sigma, pn))
        first = _cgf_derivatives(s, E, scale, frac, sigma, pn)[0] if derivs else {}
    else:
        K, first, _ = _cascade_cgf(s, E, scale, frac, sigma, cascade, int(derivs), names)
        cf = np.exp(K)
    Z = 1.0 + 2.0 * cf.real.sum(axis=1)
    if derivs:
        grads = {name: 2.0 * (first[name] * cf).real.sum(axis=1) / Z for name in names}
    return np.log(Z), grads


def _evaluate(E, scale, S0, sigma, pn, row, k, grad=False, cascade=None):
    """log p(k) (and native gradients) for queries ``k`` of parameter rows ``row``.

    Parameters
    ----------
    E, scale, S0, sigma, pn : ndarray, shape (U,)
        Distinct parameter rows (see :func:`_window`; S0 absolute, ADU).
    cascade : _Cascade, optional
        The exact register of every row (``scale`` = 1/φ); ``None``: the gamma model.
    row : ndarray of int, shape (Q,)
        Row of each query.
    k : ndarray of int64, shape (Q,)
        Counts (ADU).
    """
    Q = k.shape[0]
    logp = np.full(Q, np.nan)
    names = NATIVE if cascade is None else _cascade_names(cascade)
    grads = {name: np.full(Q, np.nan) for name in names} if grad else {}
    todo = np.ones(Q, dtype=bool)
    tilt_u = np.zeros(E.shape[0])
    if cascade is None:
        mean_u = S0 + E * scale
        quad_rows = ~pn & (scale > sigma)
    else:
        mean_u = _cascade_real(tilt_u, E, scale, S0, sigma, cascade)[1]
        quad_rows = np.zeros(E.shape[0], dtype=bool)
    first_round = True
    rounds = 0
    while todo.any():
        rounds += 1
        if rounds > 20000:  # pragma: no cover - a safeguard, never a silent NaN
            raise RuntimeError("noise model: tail evaluation did not finish")
        if first_round:
            rows = np.unique(row)
            targets = None
        elif quad_rows.any():
            # The exponential tail of a PGN whose single-electron scale exceeds the read
            # noise: tilted windows would have to be enormous, quadrature is exact there.
            q = np.flatnonzero(todo & quad_rows[row])
            for chunk in np.array_split(q, max(1, q.size // 4096)):
                r = row[chunk]
                lf, dq = _quadrature_logpdf(k[chunk].astype(float), E[r], scale[r], S0[r],
                                            sigma[r], grad=grad)
                logp[chunk] = lf
                for name in grads:
                    grads[name][chunk] = dq[name]
            todo[q] = False
            quad_rows[:] = False
            continue
        else:
            # Next target of each row: its unfinished query nearest to the mean.
            q = np.flatnonzero(todo)
            order = np.lexsort((np.abs(k[q] - mean_u[row[q]]), row[q]))
            rows, first = np.unique(row[q[order]], return_index=True)
            targets = q[order[first]]
            if cascade is None:
                tilt_u[rows] = _saddlepoint(k[targets].astype(float), E[rows], scale[rows],
                                            S0[rows], sigma[rows], pn[rows])
            else:
                tilt_u[rows] = _cascade_saddlepoint(k[targets].astype(float), E[rows],
                                                    scale[rows], S0[rows], sigma[rows],
                                                    cascade.take(rows))
        t = tilt_u[rows]
        if cascade is None:
            fam = _tilted_family(t, E[rows], scale[rows], S0[rows], sigma[rows], pn[rows])
            start, length = _window_start(*fam, pn[rows])
        else:
            lo, hi = _cascade_extent(t, E[rows], scale[rows], S0[rows], sigma[rows],
                                     cascade.take(rows))
            start = np.floor(lo).astype(np.int64)
            length = np.ceil(hi).astype(np.int64) - start + 1
        if targets is not None:
            # Far in a few-electron PGN tail the tilted window grows without bound: hand
            # those rows to the quadrature, which is exact there.
            huge = ~pn[rows] & (length > _MAX_WINDOW)
            if huge.any() and cascade is not None:
                # The cascade's far tail beyond the longest window: the saddlepoint
                # approximation (values there are far below 1e-10 of the peak).
                q = targets[huge]
                r = rows[huge]
                lf, dq = _cascade_spa(k[q].astype(float), t[huge], E[r], scale[r], S0[r],
                                      sigma[r], cascade.take(r), grad)
                logp[q] = lf
                for name in grads:
                    grads[name][q] = dq[name]
                todo[q] = False
                keep = ~huge
                rows, t, start, length = rows[keep], t[keep], start[keep], length[keep]
                targets = targets[keep]
                if rows.size == 0:
                    continue
            elif huge.any():
                quad_rows[rows[huge]] = True
                keep = ~huge
                rows, t, start, length = rows[keep], t[keep], start[keep], length[keep]
                targets = targets[keep]
                if rows.size == 0:
                    continue
        # Rows of similar window length share one batched FFT.
        group = np.ceil(np.log2(np.maximum(length, 2))).astype(int)
        for gval in np.unique(group):
            sel = group == gval
            r = rows[sel]
            n = _fast_len(int(length[sel].max()))
            shift = S0[r] - start[sel]
            casc = None if cascade is None else cascade.take(r)
            p, d1, _ = _window(
                E[r], scale[r], shift, sigma[r], pn[r], n, tilt=t[sel], derivs=grad,
                names=names, cascade=casc,
            )
            if cascade is None:
                K_t = _real_cgf(t[sel], E[r], scale[r], shift, sigma[r], pn[r])
            else:
                K_t = _cascade_real(t[sel], E[r], scale[r], shift, sigma[r], casc)[0]
            # Queries of these rows that fall in the window.
            local = np.full(E.shape[0], -1)
            local[r] = np.arange(r.size)
            qi = np.flatnonzero(todo & (local[row] >= 0))
            li = local[row[qi]]
            y = k[qi] - start[sel][li]
            inside = (y >= 0) & (y < n)
            qi, li, y = qi[inside], li[inside], y[inside]
            pv = p[li, y]
            trusted = _TRUSTED if cascade is None else _TRUSTED_CASCADE
            ok = pv >= trusted * p.max(axis=1)[li]
            if targets is not None:
                ok |= np.isin(qi, targets)
            qi, li, y, pv = qi[ok], li[ok], y[ok], pv[ok]
            # A forced target can still sit in an unresolvable valley (a Poisson–normal
            # comb with read noise below the electron spacing, far out): its value is
            # below round-off, reported as probability 0 rather than a wrong number.
            pv = np.where(pv > 0, pv, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                logp[qi] = np.log(pv) + K_t[li] - t[sel][li] * y
                for name in grads:
                    grads[name][qi] = np.where(pv > 0, d1[name][li, y] / pv, 0.0)
            todo[qi] = False
        first_round = False
    logZ, dlogZ = _log_normaliser(E, scale, S0, sigma, pn, derivs=grad, cascade=cascade)
    logp -= logZ[row]
    for name in grads:
        grads[name] -= dlogZ[name][row]
    return logp, grads


def _quadrature_logpdf(k, E, theta, S0, sigma, grad=False):
    """log f(k) of the PGN by Gauss–Legendre quadrature of its Bessel form (docs/methods.md).

    ``f(k) = e^{-E} N(k; S0, σ) + ∫ q_c(u) N(k; S0 + u, σ) du`` with the Poisson–gamma
    density ``q_c`` evaluated through ``i1e`` (never overflows). The integrand is positive,
    so the result has full *relative* precision far into the tails, where an FFT window
    cannot reach: used for the exponential tail of few-electron PGN (θ > σ). Arrays of
    shape (Q,), one parameter set per query. With ``grad``, also ∂ log f/∂E and ∂/∂θ.
    """
    from scipy import special

    nodes, weights = np.polynomial.legendre.leggauss(16)
    x = (k - S0)[:, None]
    width = 2.0 * np.minimum(sigma, theta)
    lo = np.maximum(0.0, k - S0 - 12.0 * sigma)
    hi = np.maximum(lo, k - S0 + 12.0 * sigma)
    n_panel = np.clip(np.ceil((hi - lo) / width), 1, 256).astype(int)
    M = int(n_panel.max())
    panel = np.arange(M)[None, :]
    h = ((hi - lo) / n_panel)[:, None]
    a = lo[:, None] + panel * h
    u = (a[:, :, None] + 0.5 * h[:, :, None] * (nodes + 1.0)).reshape(k.size, -1)
    w = (0.5 * h[:, :, None] * weights * (panel < n_panel[:, None])[:, :, None]).reshape(k.size, -1)
    Ec, tc, sc = E[:, None], theta[:, None], sigma[:, None]
    u = np.maximum(u, 1e-300)
    z = 2.0 * np.sqrt(Ec * u / tc)
    log_q = 0.5 * np.log(Ec / (tc * u)) - (np.sqrt(u / tc) - np.sqrt(Ec)) ** 2 + np.log(special.i1e(z))
    log_n = -0.5 * ((x - u) / sc) ** 2 - np.log(np.sqrt(2.0 * np.pi) * sc)
    with np.errstate(divide="ignore"):
        log_terms = log_q + log_n + np.log(w)
    atom = -E - 0.5 * ((k - S0) / sigma) ** 2 - np.log(np.sqrt(2.0 * np.pi) * sigma)
    stacked = np.concatenate([log_terms, atom[:, None]], axis=1)
    top = stacked.max(axis=1, keepdims=True)
    weight = np.exp(stacked - top)
    total = weight.sum(axis=1)
    logf = top[:, 0] + np.log(total)
    if not grad:
        return logf, {}
    # ∂ ln q_c/∂E = −1 + √(u/(θE))·R(z), ∂ ln q_c/∂θ = (u/θ − (z/2)R(z))/θ, R = I0/I1.
    R = special.i0e(z) / special.i1e(z)
    dE = -1.0 + np.sqrt(u / (tc * Ec)) * R
    dT = (u / tc - 0.5 * z * R) / tc
    share = weight[:, :-1] / total[:, None]
    atom_share = weight[:, -1] / total
    # Offset and read noise act through the Gaussian factor, atom (u = 0) included.
    resid = np.concatenate([x - u, x], axis=1)
    all_share = weight / total[:, None]
    return logf, {
        "photoelectrons": np.sum(share * dE, axis=1) - atom_share,
        "scale": np.sum(share * dT, axis=1),
        "offset": np.sum(all_share * resid, axis=1) / sigma**2,
        "read_noise": (np.sum(all_share * resid**2, axis=1) / sigma**2 - 1.0) / sigma,
    }


def _fast_len(n):
    from scipy import fft

    return fft.next_fast_len(int(n), real=True)


def _prepare(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, register_cic):
    """Validate, broadcast and reduce to distinct parameter rows."""
    k = _check_counts(counts)
    params = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    cic = check_number("register_cic", register_cic, minimum=0.0, scalar=False)
    arrays = np.broadcast_arrays(k, *params, cic)
    shape = arrays[0].shape
    flat = [a.ravel() for a in arrays]
    table = np.stack(flat[1:], axis=1)
    uniq, row = np.unique(table, axis=0, return_inverse=True)
    return shape, flat[0], row.ravel(), uniq.T


def _model_of(em_model, stages, register_cic=0.0):
    """The checked :class:`EMModel`; register CIC only goes with the cascade."""
    model = as_em_model(em_model, stages)
    if not model.cascade and np.any(np.asarray(register_cic) != 0):
        raise OptionError("register_cic is a parameter of the cascade model: give "
                          "em_model='cascade' with it")
    return model


def _evaluate_public(E, g, phi, S0, sigma, cic, row, k, model, grad=False):
    """log p(k) and gradients by the public parameters for rows of public parameters.

    Rows with g = 1 use the Poisson–normal model under either register model (no
    multiplication: the register's clock-induced charge is not counted there); the
    others the model's register. Gradients: ``photoelectrons``, ``em_gain`` (NaN at
    g = 1), ``e_per_adu``, ``offset``, ``read_noise`` and, for the cascade,
    ``register_cic``.
    """
    pn = g == 1.0
    logp = np.full(k.shape, np.nan)
    names = ("photoelectrons", "em_gain", "e_per_adu", "offset", "read_noise")
    if model.cascade:
        names += ("register_cic",)
    grads = {name: np.full(k.shape, np.nan) for name in names} if grad else {}
    gamma_rows = np.ones(g.shape, bool) if not model.cascade else pn
    for part in (gamma_rows, ~gamma_rows):
        rows = np.flatnonzero(part)
        q = np.flatnonzero(part[row])
        if q.size == 0:
            continue
        local = np.full(g.shape, -1)
        local[rows] = np.arange(rows.size)
        lr = local[row[q]]
        Er, gr, phr, S0r, sr = E[rows], g[rows], phi[rows], S0[rows], sigma[rows]
        if part is gamma_rows:
            pnr = pn[rows]
            scale = np.where(pnr, 1.0 / phr, gr / phr)
            lp, d = _evaluate(Er, scale, S0r, sr, pnr, lr, k[q], grad=grad)
        else:
            casc = _Cascade(model.stages, gr, cic[rows])
            lp, d = _evaluate(Er, 1.0 / phr, S0r, sr, np.zeros(rows.size, bool), lr, k[q],
                              grad=grad, cascade=casc)
        logp[q] = lp
        if not grad:
            continue
        gq, phq = gr[lr], phr[lr]
        grads["photoelectrons"][q] = d["photoelectrons"]
        grads["offset"][q] = d["offset"]
        grads["read_noise"][q] = d["read_noise"]
        if part is gamma_rows:
            # scale = g/φ (PGN) or 1/φ (PN): chain rule to the public parameters.
            pnq = pn[rows][lr]
            grads["em_gain"][q] = np.where(pnq, np.nan, d["scale"] / phq)
            grads["e_per_adu"][q] = np.where(pnq, -d["scale"] / phq**2,
                                             -d["scale"] * gq / phq**2)
            if model.cascade:
                grads["register_cic"][q] = 0.0
        else:  # scale = 1/φ
            grads["em_gain"][q] = d["em_gain"]
            grads["e_per_adu"][q] = -d["scale"] / phq**2
            grads["register_cic"][q] = d.get("register_cic", 0.0)
    return logp, grads


def logpmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, *,
           em_model="gamma", stages=None, register_cic=0.0):
    """Natural log of the probability of integer counts under the EMCCD noise model.

    Broadcasts like NumPy. ``em_gain == 1`` selects the Poisson–normal model, any other
    value (> 1) multiplication by the register model ``em_model`` (see the module
    docstring).

    Parameters
    ----------
    counts : array_like of int
        Raw counts S (ADU), non-negative integers, never offset-subtracted.
    photoelectrons : array_like
        E, mean photoelectrons per pixel per frame (e⁻), ≥ 0.
    em_gain : array_like
        g, mean EM gain (dimensionless), ≥ 1.
    e_per_adu : array_like
        φ, ADU conversion factor (e⁻/ADU), > 0.
    offset : array_like
        S0, offset (ADU), ≥ 0.
    read_noise : array_like
        σ, read noise (ADU), > 0: the SD of dark counts.
    em_model : {"gamma", "cascade"} or EMModel, optional
        The register: the paper's gamma approximation (default) or the exact
        Bernoulli cascade of ``stages`` stages (:class:`EMModel`).
    stages : int, optional
        N, stages of the cascade (default 536).
    register_cic : array_like, optional
        c, clock-induced charge made inside the register (cascade only), e⁻ per pixel
        per frame, entering at a uniformly random stage and multiplied by the stages
        after it. Charge made before the register (pixel CIC, dark current) simply adds
        to E.

    Returns
    -------
    ndarray
        ln P(S = counts), nats.

    Raises
    ------
    OptionError
        For negative, non-finite or non-integer counts and for parameters out of range;
        the message names the parameter.

    Examples
    --------
    The paper's Fig. 1 parameters (docs/validation.md, case 5):

    >>> import numpy as np
    >>> p = np.exp(logpmf([90, 100, 130], 10.0, 1.0, 3.5, 100.0, 10.0))
    >>> [f"{v:.10e}" for v in p]
    ['1.7503385211e-02', '3.8157156576e-02', '1.0291887305e-03']

    At 5× the exact register is narrower than the gamma model (F² = 1.795, not 2):

    >>> counts = np.arange(500, 3000)
    >>> sd = lambda p: np.sqrt(np.sum(p * counts**2) - np.sum(p * counts)**2)
    >>> gamma = pmf(counts, 370.0, 5.0, 3.859, 587.0, 15.5)
    >>> exact = pmf(counts, 370.0, 5.0, 3.859, 587.0, 15.5, em_model="cascade", stages=536)
    >>> round(float(sd(exact) / sd(gamma)), 4)
    0.9561
    """
    model = _model_of(em_model, stages, register_cic)
    shape, k, row, rows = _prepare(counts, photoelectrons, em_gain, e_per_adu, offset,
                                   read_noise, register_cic)
    logp, _ = _evaluate_public(*rows, row, k, model)
    return logp.reshape(shape)


def pmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, **model):
    """Probability of integer counts: ``exp(logpmf(...))``; parameters as :func:`logpmf`."""
    return np.exp(logpmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise,
                         **model))


def logpmf_grad(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, *,
                em_model="gamma", stages=None, register_cic=0.0):
    """Log-pmf and its analytic gradient by every parameter.

    Parameters are those of :func:`logpmf`.

    Returns
    -------
    logp : ndarray
        As :func:`logpmf`.
    grad : dict of ndarray
        ∂ ln p / ∂ parameter for ``photoelectrons`` (1/e⁻), ``em_gain`` (1),
        ``e_per_adu`` (ADU/e⁻), ``offset`` (1/ADU) and ``read_noise`` (1/ADU); with the
        cascade model also ``register_cic`` (1/e⁻). The Poisson–normal model
        (em_gain == 1) has no gain parameter: its ``em_gain`` entry is NaN.
    """
    model = _model_of(em_model, stages, register_cic)
    shape, k, row, rows = _prepare(counts, photoelectrons, em_gain, e_per_adu, offset,
                                   read_noise, register_cic)
    logp, grad = _evaluate_public(*rows, row, k, model, grad=True)
    return logp.reshape(shape), {name: v.reshape(shape) for name, v in grad.items()}


# --------------------------------------------------------------------------------------
# The authors' grid model, for cross-checks only
# --------------------------------------------------------------------------------------
#: Grid length of the authors' model (``s_bit = 17``) and its probability floor.
PAPER_GRID = 2**17
PAPER_FLOOR = 1e-16


def paper_pmf_grid(photoelectrons, em_gain, e_per_adu, offset, read_noise):
    """The authors' noise model on their 2^17-point grid, for cross-checks only.

    Reproduces ``NoiseModel_TFv1.py`` of ryand-LANL/EMCCD-calibration as docs/methods.md
    describes it, including what we believe are its flaws: the zero-electron bin
    carries ``φ·e^{-E}(1 + E/g)`` (mass φ·e^{-E} instead of e^{-E}), the PGN density is
    sampled at unit spacing without quadrature, the 1× model is the continuous
    interpolation ``φ·E^{Sφ}e^{-E}/Γ(Sφ+1)`` of the Poisson pmf, the Gaussian read-out is
    a circular FFT convolution, and values below 1e-16 are replaced by 1e-16. The result
    is therefore not normalised (Σ p ≈ 2.86 at E = 0.5, g = 5, φ = 3.859). Use
    :func:`logpmf` for anything but comparisons with the authors' numbers.

    Parameters
    ----------
    photoelectrons, em_gain, e_per_adu, offset, read_noise : float
        Scalars, as :func:`logpmf`.

    Returns
    -------
    ndarray, shape (131072,)
        p(S) for S = 0 … 2^17 − 1.
    """
    from scipy import fft, special

    E, g, phi, S0, sigma = (float(v) for v in _check_params(
        photoelectrons, em_gain, e_per_adu, offset, read_noise))
    s = np.arange(PAPER_GRID, dtype=float)
    if g == 1:
        with np.errstate(divide="ignore"):
            log_q = s * phi * np.log(E) - E - special.gammaln(s * phi + 1.0)
        q = phi * np.exp(log_q)
    else:
        r = phi / g
        u = s[1:]
        z = 2.0 * np.sqrt(E * u * r)
        # sqrt(E r/u) e^{-ur-E} I1(z), with I1 scaled: i1e(z) = e^{-z} I1(z).
        q = np.empty_like(s)
        q[1:] = np.sqrt(E * r / u) * np.exp(-u * r - E + z) * special.i1e(z)
        q[0] = phi * np.exp(-E) * (1.0 + E / g)
    kernel = np.exp(-0.5 * ((s - S0) / sigma) ** 2) / (np.sqrt(2.0 * np.pi) * sigma)
    p = fft.ifft(fft.fft(q) * fft.fft(kernel)).real
    return np.maximum(p, PAPER_FLOOR)


def paper_logpmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise):
    """Log of :func:`paper_pmf_grid` at ``counts`` (0 ≤ counts < 2^17); cross-checks only.

    Note the convolution: the grid's Gaussian kernel is centred at the offset, so the
    output index is the count itself, as in the authors' code.
    """
    k = _check_counts(counts)
    if np.any(k >= PAPER_GRID):
        raise OptionError(f"counts must be below {PAPER_GRID} in the paper's grid model")
    return np.log(paper_pmf_grid(photoelectrons, em_gain, e_per_adu, offset, read_noise)[k])


# --------------------------------------------------------------------------------------
# Pointwise evaluation: every count under its own parameters (bead fitting)
# --------------------------------------------------------------------------------------
#: Points of FFT windows evaluated together by :func:`logpmf_rows`; bounds its memory
#: (a few tens of bytes per point).
_ROWS_POINTS = 2**22


def logpmf_rows(counts, row, photoelectrons, em_gain, e_per_adu, offset, read_noise, *,
                grad=False, em_model="gamma", stages=None):
    """Log-pmf of counts, each under a parameter set picked by index (no broadcasting).

    :func:`logpmf` broadcasts its arguments and looks for repeated parameter sets among
    all of them; when the parameter sets are already known to be distinct (one per pixel
    and trial intensity, as in bead fitting) this is the direct route: the queries name
    their row, and the rows are evaluated in batches of bounded memory. The values are
    those of :func:`logpmf` (the same exact evaluator).

    Parameters
    ----------
    counts : array_like of int, shape (Q,)
        Raw counts S (ADU), non-negative integers.
    row : array_like of int, shape (Q,)
        Index of each count's parameter set, ``0 <= row < U``.
    photoelectrons, em_gain, e_per_adu, offset, read_noise : array_like, shape (U,)
        One parameter set per row, as in :func:`logpmf`: E (e⁻), g (1; exactly 1 selects
        the Poisson–normal model), φ (e⁻/ADU), S0 (ADU), σ (ADU).
    grad : bool, optional
        Also return ∂ ln p / ∂E (1/e⁻).
    em_model, stages : optional
        The register model, as in :func:`logpmf`.

    Returns
    -------
    logp : ndarray, shape (Q,)
        ln P(S = counts), nats.
    dlogp_dE : ndarray, shape (Q,)
        Only with ``grad``.

    Examples
    --------
    >>> lp = logpmf_rows([90, 100, 130], [0, 0, 1], [10.0, 10.0], [1.0, 1.0], [3.5, 3.5],
    ...                  [100.0, 100.0], [10.0, 10.0])
    >>> [f"{v:.10e}" for v in np.exp(lp)]
    ['1.7503385211e-02', '3.8157156576e-02', '1.0291887305e-03']
    """
    k = _check_counts(counts).ravel()
    idx = np.asarray(row).ravel()
    params = [np.atleast_1d(a).ravel() for a in _check_params(
        photoelectrons, em_gain, e_per_adu, offset, read_noise)]
    U = max(a.size for a in params)
    if any(a.size not in (1, U) for a in params):
        raise OptionError("photoelectrons, em_gain, e_per_adu, offset and read_noise must "
                         "have one value per row (or a single value)")
    E, g, phi, S0, sigma = (np.broadcast_to(a, (U,)) for a in params)
    if idx.shape != k.shape:
        raise OptionError(f"row has {idx.size} entries but counts has {k.size}")
    if idx.size and (idx.dtype.kind not in "iu" or idx.min() < 0 or idx.max() >= U):
        raise OptionError(f"row must hold integer indices from 0 to {U - 1}")
    model = as_em_model(em_model, stages)
    logp = np.empty(k.size)
    dE = np.empty(k.size) if grad else None
    if k.size == 0:
        return (logp, dE) if grad else logp
    order = np.argsort(idx, kind="stable")
    used, first = np.unique(idx[order], return_index=True)
    bounds = np.append(first, order.size)
    length = _window_lengths(E[used], g[used], phi[used], S0[used], sigma[used], model)
    # Consecutive runs of used rows whose windows add up to at most _ROWS_POINTS.
    cum = np.cumsum(length)
    starts = [0]
    while starts[-1] < used.size:
        base = cum[starts[-1] - 1] if starts[-1] else 0
        stop = int(np.searchsorted(cum, base + _ROWS_POINTS, side="right"))
        starts.append(max(stop, starts[-1] + 1))
    cic = np.zeros(U)
    for a, b in zip(starts[:-1], starts[1:]):
        r = used[a:b]
        q = order[bounds[a]:bounds[b]]
        local = np.repeat(np.arange(b - a), np.diff(bounds[a:b + 1]))
        lp, d = _evaluate_public(E[r], g[r], phi[r], S0[r], sigma[r], cic[r], local, k[q],
                                 model, grad=grad)
        logp[q] = lp
        if grad:
            dE[q] = d["photoelectrons"]
    return (logp, dE) if grad else logp


def _window_lengths(E, g, phi, S0, sigma, model):
    """Length (counts) of the window that covers each row's distribution."""
    pn = g == 1.0
    if not model.cascade:
        return _window_start(E, np.where(pn, 1.0 / phi, g / phi), S0, sigma, pn)[1]
    length = _window_start(E, 1.0 / phi, S0, sigma, pn)[1]  # PN rows
    multiplied = ~pn
    if multiplied.any():
        m = multiplied
        casc = _Cascade(model.stages, g[m], 0.0)
        length[m] = _window_start(E[m], 1.0 / phi[m], S0[m], sigma[m], pn[m], cascade=casc)[1]
    return length


#: Smallest photoelectron value a :class:`LogpmfTable` covers (e⁻); below, E is clamped.
TABLE_MIN_PHOTOELECTRONS = 1e-3


def _table_layout(e_lo, e_hi):
    """Chebyshev nodes and variable per pixel for ranges [e_lo, e_hi] (e⁻).

    Returns the number of nodes and whether the variable is ln E (else √E). Measured
    (tests/test_noise_pointwise.py): in √E, 16 nodes keep |Δ ln p| below 1e-7 for ranges
    up to a factor 4 in E and 24 up to a factor 40; wider ranges reach down to where
    p(S | E) ∝ E^n for a few-electron count (ln p ~ n ln E, singular in √E at 0) and use
    ln E, with 32 nodes up to a factor 1e5 and 48 beyond.
    """
    ratio = e_hi / np.maximum(e_lo, TABLE_MIN_PHOTOELECTRONS)
    nodes = np.select([ratio <= 4.0, ratio <= 40.0, ratio <= 1e5], [16, 24, 32], 48)
    return nodes, ratio > 40.0


class LogpmfTable:
    """ln p(S_q | E) of fixed counts S_q as smooth functions of E, exact to ~1e-8 nats.

    In a fit of a model of the intensities (a bead's image), every pixel has its own
    count, noise parameters and trial intensity E, which changes at every iteration. The
    counts are data, fixed during the fit: for each one, ln p(S | E) is an analytic
    function of E over the pixel's plausible range ``[e_lo, e_hi]``. It is tabulated at
    Chebyshev nodes in √E by the exact evaluator (:func:`logpmf_rows`, each pixel's own
    g, φ, offset and read noise) and interpolated: ln p, ∂/∂E and ∂²/∂E² then cost a
    few dozen multiply-adds per count. Ranges wider than a factor 40 are tabulated in
    ln E instead of √E (a count far in the tail of a dim pixel has ln p ~ n ln E near
    E = 0). Interpolation error is below 1e-7 nats (typically
    1e-9, the exact evaluator's own accuracy) inside the ranges; outside, E is clamped
    to the range and the query flagged, so that the caller can widen the range
    (:meth:`set_range`) and evaluate again.

    Parameters
    ----------
    counts : array_like of int, shape (Q,)
        Raw counts (ADU).
    pixel : array_like of int, shape (Q,)
        Index of each count's pixel, ``0 <= pixel < K``.
    e_lo, e_hi : array_like, shape (K,)
        Range of E per pixel (e⁻), ``0 <= e_lo < e_hi``.
    em_gain, e_per_adu, offset, read_noise : array_like, shape (K,)
        Each pixel's noise parameters, as in :func:`logpmf` (``em_gain == 1``: PN).
    em_model, stages : optional
        The register model, as in :func:`logpmf`.

    Examples
    --------
    >>> t = LogpmfTable([700, 3000], [0, 1], [100.0, 100.0], [300.0, 300.0],
    ...                 [1.0, 25.0], [3.859, 3.859], [587.0, 587.0], [15.5, 15.5])
    >>> lp, d1, d2, outside = t.evaluate(np.array([150.0, 200.0]))
    >>> bool(np.allclose(lp, logpmf([700, 3000], [150.0, 200.0], [1.0, 25.0], 3.859,
    ...                              587.0, 15.5), atol=1e-7))
    True
    """

    def __init__(self, counts, pixel, e_lo, e_hi, em_gain, e_per_adu, offset, read_noise, *,
                 em_model="gamma", stages=None):
        self.em_model = as_em_model(em_model, stages)
        self.counts = _check_counts(counts).ravel()
        self.pixel = np.asarray(pixel).ravel()
        if self.pixel.shape != self.counts.shape:
            raise OptionError(f"pixel has {self.pixel.size} entries but counts has "
                             f"{self.counts.size}")
        params = [np.atleast_1d(a).astype(float).ravel() for a in _check_params(
            1.0, em_gain, e_per_adu, offset, read_noise)[1:]]
        K = max(a.size for a in params)
        self.em_gain, self.e_per_adu, self.offset, self.read_noise = (
            np.broadcast_to(a, (K,)).copy() for a in params)
        if self.pixel.size and (self.pixel.dtype.kind not in "iu" or self.pixel.min() < 0
                                or self.pixel.max() >= K):
            raise OptionError(f"pixel must hold integer indices from 0 to {K - 1}")
        self.u_lo = np.zeros(K)
        self.u_hi = np.zeros(K)
        self.degree = np.zeros(K, dtype=int)
        self.log = np.zeros(K, dtype=bool)
        self.coef = np.zeros((16, self.counts.size))
        self.set_range(np.arange(K), e_lo, e_hi)

    def _to_e(self, x, pix):
        return np.where(self.log[pix], np.exp(x), x**2)

    @property
    def e_range(self):
        """Per-pixel range (e_lo, e_hi) of E covered, e⁻."""
        pix = np.arange(self.u_lo.size)
        return self._to_e(self.u_lo, pix), self._to_e(self.u_hi, pix)

    def set_range(self, pixels, e_lo, e_hi):
        """(Re)tabulate the counts of ``pixels`` over new ranges ``[e_lo, e_hi]`` (e⁻)."""
        pixels = np.atleast_1d(np.asarray(pixels))
        lo = np.broadcast_to(np.asarray(e_lo, float), pixels.shape)
        hi = np.broadcast_to(np.asarray(e_hi, float), pixels.shape)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo >= 0)
                and np.all(hi > lo)):
            raise OptionError("table ranges must be finite with 0 <= e_lo < e_hi (e-)")
        lo = np.maximum(lo, TABLE_MIN_PHOTOELECTRONS)
        hi = np.maximum(hi, 2.0 * lo)
        self.degree[pixels], self.log[pixels] = _table_layout(lo, hi)
        lg = self.log[pixels]
        self.u_lo[pixels] = np.where(lg, np.log(lo), np.sqrt(lo))
        self.u_hi[pixels] = np.where(lg, np.log(hi), np.sqrt(hi))
        D = int(self.degree.max())
        if self.coef.shape[0] < D:
            self.coef = np.concatenate(
                [self.coef, np.zeros((D - self.coef.shape[0], self.coef.shape[1]))])
        chosen = np.zeros(self.degree.size, dtype=bool)
        chosen[pixels] = True
        q = np.flatnonzero(chosen[self.pixel])
        if q.size == 0:
            return
        # Distinct (pixel, count) pairs; each is tabulated at its pixel's nodes.
        pair, inv = np.unique(np.stack([self.pixel[q], self.counts[q]]), axis=1,
                              return_inverse=True)
        pix, cnt = pair
        coef = np.zeros((self.coef.shape[0], pix.size))
        for d in np.unique(self.degree[pix]):
            sel = np.flatnonzero(self.degree[pix] == d)
            px_d, first = np.unique(pix[sel], return_inverse=True)
            t = np.cos(np.pi * (np.arange(d) + 0.5) / d)
            mid = 0.5 * (self.u_lo[px_d] + self.u_hi[px_d])
            half = 0.5 * (self.u_hi[px_d] - self.u_lo[px_d])
            x = mid[:, None] + half[:, None] * t[None, :]
            nodes_E = np.where(self.log[px_d][:, None], np.exp(x), x**2).ravel()
            rows = np.repeat(px_d, d)
            query_row = (first[:, None] * d + np.arange(d)[None, :]).ravel()
            values = logpmf_rows(
                np.repeat(cnt[sel], d), query_row, nodes_E, self.em_gain[rows],
                self.e_per_adu[rows], self.offset[rows], self.read_noise[rows],
                em_model=self.em_model,
            ).reshape(sel.size, d)
            # Chebyshev coefficients from values at first-kind nodes (a DCT-II).
            m = np.arange(d)
            basis = np.cos(np.pi * np.outer(m, np.arange(d) + 0.5) / d) * (2.0 / d)
            basis[0] *= 0.5
            coef[:d, sel] = basis @ values.T
        self.coef[:, q] = coef[:, inv.ravel()]

    def evaluate(self, photoelectrons, index=None):
        """ln p and its first two derivatives by E at the given intensities.

        Parameters
        ----------
        photoelectrons : ndarray, shape (n,)
            E (e⁻) of each query.
        index : ndarray of int, shape (n,), optional
            Which counts (positions in ``counts``) the values of ``photoelectrons`` belong
            to; default all, in order.

        Returns
        -------
        logp : ndarray, shape (n,)
            ln p(S | E), nats (at the clamped E where outside).
        dlogp : ndarray, shape (n,)
            ∂ ln p / ∂E, 1/e⁻.
        d2logp : ndarray, shape (n,)
            ∂² ln p / ∂E², 1/e⁻².
        outside : ndarray of bool, shape (n,)
            E was outside its pixel's range and was clamped to it.
        """
        E = np.asarray(photoelectrons, dtype=float)
        coef = self.coef if index is None else self.coef[:, index]
        pix = self.pixel if index is None else self.pixel[index]
        lo, hi, lg = self.u_lo[pix], self.u_hi[pix], self.log[pix]
        e_lo, e_hi = self._to_e(lo, pix), self._to_e(hi, pix)
        outside = (E < e_lo * (1 - 1e-12)) | (E > e_hi * (1 + 1e-12)) | ~np.isfinite(E)
        Ec = np.clip(np.nan_to_num(E, nan=0.0), e_lo, e_hi)
        u = np.clip(np.where(lg, np.log(Ec), np.sqrt(Ec)), lo, hi)
        half = 0.5 * (hi - lo)
        t = (u - 0.5 * (hi + lo)) / half
        # T_m, T'_m, T''_m by their three-term recurrences, summed as they go.
        T0, T1 = np.ones_like(t), t
        D0, D1 = np.zeros_like(t), np.ones_like(t)
        S0_, S1 = np.zeros_like(t), np.zeros_like(t)
        f = coef[0] + coef[1] * t
        ft = coef[1].copy()
        ftt = np.zeros_like(t)
        for m in range(2, coef.shape[0]):
            T2 = 2.0 * t * T1 - T0
            D2 = 2.0 * T1 + 2.0 * t * D1 - D0
            S2 = 4.0 * D1 + 2.0 * t * S1 - S0_
            c = coef[m]
            f += c * T2
            ft += c * D2
            ftt += c * S2
            T0, T1, D0, D1, S0_, S1 = T1, T2, D1, D2, S1, S2
        # Chain rule: t = (x − mid)/half with x = √E or ln E.
        dx = np.where(lg, 1.0 / Ec, 0.5 / u)                  # dx/dE
        d2x = np.where(lg, -1.0 / Ec**2, -0.25 / u**3)        # d²x/dE²
        d1 = ft / half * dx
        d2 = ftt / half**2 * dx**2 + ft / half * d2x
        return f, d1, d2, outside
