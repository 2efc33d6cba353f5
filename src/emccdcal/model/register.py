"""The base class of a register model: state the register once, inherit the rest.

A register is defined by what one electron entering it becomes: the distribution of its
output X (electrons). Everything emccdcal needs follows from that distribution's moment
generating function ``M(u) = E[e^{uX}]``, and a subclass of :class:`Register` supplies
only its **transform** ``v(u, g) = M(u) − 1`` at mean gain g (and a name and a
description), as a subclass of ``scipy.stats.rv_continuous`` supplies only its density:

>>> import numpy as np
>>> class Noiseless(Register):
...     '''Every electron becomes exactly g electrons (no excess noise).'''
...     name = "noiseless"
...     description = "multiplication without excess noise"
...     def transform(self, u, g):
...         return np.expm1(u * g)
>>> round(float(Noiseless().excess_noise_factor(np.array(30.0))), 12)
1.0

What it inherits, and how (each may be overridden with a closed form):

* the moments of one electron's output (:meth:`Register.single_electron_moments`), the
  excess-noise factor F² = E[X²]/g² and the gain from g·F²
  (:meth:`Register.gain_from_gain_f2`): by Cauchy's integral of the transform on a small
  circle around 0, which is exact to round-off for a transform analytic there;
* sampling the output of n electrons (:meth:`Register.sample`): from the exact
  distribution of a sum of n outputs, one inverse FFT of ``M(iω)^n`` on the integers (a
  register's output is a whole number of electrons);
* the rows the likelihood's window engine evaluates (:class:`TransformRows`; what rows
  are: :mod:`emccdcal.model._engine`), with the fit coordinates (ln E, ln(1/φ), ln g), the
  derivatives the fit needs (by u, on a circle in the complex plane; by ln g, five-point
  differences: relative accuracy about 1e-10 and 1e-8 for the second, or exact where
  :meth:`Register.transform_terms` is overridden), and the far tail by the saddlepoint
  approximation.

The exact register (:mod:`._exact`) is a subclass that overrides the transform's
derivatives, moments and samplers with its own exact recursions.
"""

from __future__ import annotations

import numpy as np

from .. import _roots, _xp, defaults
from ._engine import READOUT, fast_len, real_cgf
from ._engine import cgf as count_cgf

__all__ = ["Register", "TransformRows"]

#: Points on the circle of Cauchy's integral for the moments at u = 0 and its radius, in
#: units of 1/g: the transform of every register is analytic well beyond (its nearest
#: singularity is near 1/g), so the aliasing error is below (0.1·g·|u*|)^-32.
_MOMENT_POINTS, _MOMENT_RADIUS = 32, 0.1
#: Points on the circle for the derivatives by u, and its radius (units of 1/g): the
#: error is (radius/distance to the nearest singularity)^8, below 1e-8 while a tilt is
#: at least 0.01/g away from it (farther tilts go to the saddlepoint approximation).
_STENCIL_POINTS, _STENCIL_RADIUS = 8, 1e-3
#: Step in ln g of the five-point differences by the gain (truncation error ~h⁴, round-off
#: ~1e-14/h² for the second derivative of a transform accurate to 1e-14).
_LN_GAIN_STEP, _LN_GAIN_SHIFTS = 1e-3, (-2, -1, 1, 2)


def _by_ln_gain(at, centre=None):
    """The first derivative by ln g from the transform at the :data:`_LN_GAIN_SHIFTS`
    (five-point differences), or the second where the centre's value is given."""
    h, (m2, m1, p1, p2) = _LN_GAIN_STEP, at
    if centre is None:
        return (m2 - 8.0 * m1 + 8.0 * p1 - p2) / (12.0 * h)
    return (-m2 + 16.0 * m1 - 30.0 * centre + 16.0 * p1 - p2) / (12.0 * h * h)


class Register:
    """A register model: subclass it, set :attr:`name` and :attr:`description`, and
    write :meth:`transform`.

    Parameters
    ----------
    stages : int, optional
        The register's length N, kept for a model that uses it (:attr:`uses_stages`);
        ignored otherwise.

    Attributes
    ----------
    name : str
        What ``--em-model`` and ``em_model=`` take (the entry point's name).
    description : str
        One line for reports.
    uses_stages : bool
        Whether the model depends on the number of stages (default False).
    parameters : tuple of str
        Extra public parameters of the likelihood (default none).
    misfit_hint : str or None
        What to tell a user whose fit with this model misfits (default none).
    trusted : float
        A likelihood window's values are used where at least this fraction of its peak
        (the transform's round-off sets it; 1e-4 suits a recursion over hundreds of
        stages, a closed form may raise it to 1e-7).
    """

    name: str = ""
    description: str = ""
    uses_stages = False
    parameters: tuple = ()
    misfit_hint = None
    trusted = 1e-4

    def __init__(self, stages=None):
        use = self.uses_stages and stages is not None
        self.stages = int(stages) if use else defaults.DEFAULT_STAGES

    def __eq__(self, other):
        return type(other) is type(self) and other.stages == self.stages

    def __hash__(self):
        return hash((type(self), self.stages))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.stages if self.uses_stages else ''})"

    # ---- what a subclass supplies ------------------------------------------------------
    def transform(self, u, g):
        """``M(u) − 1`` of one electron's output (electrons) at mean gain g.

        Parameters
        ----------
        u : ndarray, complex or real
            The argument (1/electron), any shape.
        g : ndarray
            Mean gain, broadcastable against ``u``.
        """
        raise NotImplementedError(f"{type(self).__name__} must define transform(u, g)")

    # ---- inherited ---------------------------------------------------------------------
    def transform_terms(self, u, g, order=1, cic=False, by_u=True):
        """The transform and its derivatives, as the window engine asks for them.

        Parameters
        ----------
        u : ndarray, shape (P, ...)
            The argument, complex or real.
        g : ndarray, shape (P,)
            Mean gain of each row.
        order : {0, 1, 2}
            Highest order of derivative.
        cic : bool
            Register clock-induced charge (a model that declares ``register_cic`` among
            its :attr:`parameters` overrides this method).
        by_u : bool
            Also the derivatives by u.

        Returns
        -------
        dict of ndarray
            ``"v"`` and, by order, ``"u"``, ``"g"`` (∂/∂u, ∂/∂ln g), ``"uu"``, ``"ug"``,
            ``"gg"``.
        """
        if cic:
            raise NotImplementedError(f"{self.name}: no register clock-induced charge")
        xp = _xp.namespace(u)
        g = xp.reshape(_xp.like(u, g), (-1,) + (1,) * (u.ndim - 1))
        terms = {"v": self.transform(u, g)}
        if order == 0:
            return terms
        shifted = [g * np.exp(j * _LN_GAIN_STEP) for j in _LN_GAIN_SHIFTS]
        at = [self.transform(u, gj) for gj in shifted]
        terms["g"] = _by_ln_gain(at)
        if by_u:
            terms.update(zip(("u", "uu"), self._by_u(u, g, order), strict=False))
        if order >= 2:
            terms["gg"] = _by_ln_gain(at, terms["v"])
            if by_u:
                terms["ug"] = _by_ln_gain([self._by_u(u, gj, 1)[0] for gj in shifted])
        return terms

    def _by_u(self, u, g, order):
        """∂v/∂u (and ∂²v/∂u²) by Cauchy's integral on a circle of radius
        :data:`_STENCIL_RADIUS`/g around each u."""
        xp = _xp.namespace(u)
        unit = np.exp(2j * np.pi * np.arange(_STENCIL_POINTS) / _STENCIL_POINTS)
        r = _STENCIL_RADIUS / g[..., None]
        on_circle = self.transform(u[..., None] + r * _xp.like(u, unit), g[..., None])
        out = [xp.mean(on_circle * _xp.like(u, unit.conj()), axis=-1) / r[..., 0]]
        if order >= 2:
            out.append(
                2.0 * xp.mean(on_circle * _xp.like(u, unit.conj() ** 2), axis=-1) / r[..., 0] ** 2
            )
        if not _xp.is_complex(xp, u):
            out = [xp.real(d) for d in out]
        return out

    def _raw_moments(self, g, count):
        """E[X^k], k = 1 … ``count``, of one electron's output at each gain (shape
        ``g.shape + (count,)``), by Cauchy's integral at u = 0."""
        g = np.asarray(g, dtype=float)
        unit = np.exp(2j * np.pi * np.arange(_MOMENT_POINTS) / _MOMENT_POINTS)
        r = _MOMENT_RADIUS / g[..., None]
        v = self.transform(r * unit, g[..., None])  # Σ_k m_k (r e^{iθ})^k / k!
        k = np.arange(1, count + 1)
        phase = unit.conj()[None, :] ** k[:, None]  # (count, points)
        coeffs = np.real(np.mean(v[..., None, :] * phase, axis=-1))
        return coeffs * np.cumprod(k) / r**k

    def single_electron_moments(self, g):
        """E[X^k], k = 1 … 4, of the output X (electrons) of one electron at gain g."""
        return self._raw_moments(float(g), 4)

    def excess_noise_factor(self, g):
        """F² = E[X²]/g² of one electron's output, at each gain g (dimensionless)."""
        m = self._raw_moments(g, 2)
        return m[..., 1] / m[..., 0] ** 2

    def gain_from_gain_f2(self, y):
        """g with ``g·F²(g) = y`` (bisection in ln g between 1 and y, since F² ≥ 1), and
        the slope ``d(g F²)/dg`` there."""
        y = np.asarray(y, dtype=float)
        top = np.log(np.maximum(y, 1.0))
        lo, hi = _roots.bisect(
            lambda x: np.exp(x) * self.excess_noise_factor(np.exp(x)) > y,
            np.zeros(y.shape),
            top,
            64,
        )
        g = np.exp(0.5 * (lo + hi))
        step = 1e-5 * g
        up, down = g + step, np.maximum(g - step, 1.0)
        slope = (up * self.excess_noise_factor(up) - down * self.excess_noise_factor(down)) / (
            up - down
        )
        return g, slope

    def sample(self, electrons, g, rng, **options):
        """Output electrons (float) of ``electrons`` entering the register at gain g: for
        each distinct input n, inversion of the exact distribution of the sum of n
        outputs (one inverse FFT of ``M(iω)^n`` on the integers)."""
        electrons = np.asarray(electrons)
        out = np.zeros(electrons.shape)
        m1, m2 = self._raw_moments(float(g), 2)
        for n in np.unique(electrons[electrons > 0]):
            at = electrons == n
            size = int(n * m1 + 40.0 * np.sqrt(n * m2) + 40.0 * float(g) + 64)
            length = fast_len(size)
            omega = 2.0 * np.pi * np.arange(length // 2 + 1) / length
            cf = np.exp(n * np.log1p(self.transform(-1j * omega, float(g))))
            pmf = np.clip(np.fft.irfft(cf, length), 0.0, None)
            cdf = np.cumsum(pmf) / pmf.sum()
            out[at] = np.searchsorted(cdf, rng.random(int(at.sum())), side="right")
        return out

    def register_for(self, poisson_normal):
        """The register of rows with (True) or without multiplication: at g = 1 none
        (the Poisson–normal model)."""
        from ._gamma import Gamma

        return Gamma() if poisson_normal else self

    def window_band(self, E_t, theta_t, sigma, scale, n):
        """DFT bins of a length-``n`` window to evaluate: the read noise's Gaussian factor
        alone bounds the transform (``|M(iω)| ≤ 1`` for every register)."""
        m = int(np.ceil(float((np.sqrt(160.0) / sigma).max()) * n / (2.0 * np.pi))) + 2
        return min(m, n // 2 + 1)

    def rows(self, E, g, phi, cic=0.0):
        """Rows of photoelectrons E, gain g and φ (e⁻/ADU) for the window engine."""
        return TransformRows(self, E, 1.0 / phi, g, cic)

    @staticmethod
    def coordinates(poisson_normal):
        """d(fit coordinates)/d(ln E, ln g, ln φ): (ln E, ln(1/φ), ln g)."""
        return _TRANSFORM_COORDS

    def rows_at(self, values, poisson_normal):
        """Rows from the exponentiated fit coordinates (E, 1/φ, g)."""
        E, scale, gain = values
        return TransformRows(self, E, scale, gain, 0.0)

    def public_gradients(self, d, g, phi):
        """∂ log p by the public parameters from the rows' native ones."""
        out = {"em_gain": d["em_gain"], "e_per_adu": -d["scale"] / phi**2}
        if "register_cic" in self.parameters:
            out["register_cic"] = d.get("register_cic", np.zeros(g.shape))
        return out


_TRANSFORM_COORDS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class TransformRows:
    """Rows of a register given by its transform (:meth:`Register.transform_terms`):
    photoelectrons E (e⁻), scale 1/φ (ADU per electron), each row's mean gain g and
    register clock-induced-charge rate (e⁻ per pixel per frame entering at a uniformly
    random stage, for a model that has it)."""

    def __init__(self, register, E, scale, gain, cic=0.0):
        self.register, self.E, self.scale = register, E, scale
        self.gain = np.asarray(gain, dtype=float)
        self.cic = np.broadcast_to(np.asarray(cic, dtype=float), self.gain.shape)
        self.pn = np.zeros(self.gain.shape, dtype=bool)
        self.trusted = register.trusted

    def take(self, idx):
        return TransformRows(
            self.register, self.E[idx], self.scale[idx], self.gain[idx], self.cic[idx]
        )

    @property
    def has_cic(self) -> bool:
        return bool(np.any(self.cic > 0))

    @property
    def names(self):
        """Native parameters (``register_cic`` only where it is used)."""
        return ("photoelectrons", "scale", "em_gain") + (("register_cic",) if self.has_cic else ())

    def cgf(self, s, order=0, names=()):
        """``K_X(s)`` (P, M) and its derivatives by ``names`` (without ``scale``, the
        transform skips its u-derivatives); ``second`` holds both orders of a pair."""
        cic = self.has_cic or "register_cic" in names
        by_u = "scale" in names
        E, scale, gain, cic_rate = _xp.like(s, self.E, self.scale, self.gain, self.cic)
        T = self.register.transform_terms(s * scale[:, None], gain, order, cic, by_u)
        Ec, c, g = E[:, None], cic_rate[:, None], gain[:, None]

        def mix(key):  # E·v + c·v̄, and likewise for a derivative of v
            return Ec * T[key] + c * T["cic_" + key] if cic else Ec * T[key]

        first, sec = {}, {}
        if order >= 1:
            first = {"photoelectrons": T["v"], "em_gain": mix("g") / g}
            if by_u:
                first["scale"] = s * mix("u")
            if cic:
                first["register_cic"] = T["cic_v"]
        if order >= 2:
            sec = {
                ("photoelectrons", "em_gain"): T["g"] / g,
                ("em_gain", "em_gain"): (mix("gg") - mix("g")) / g**2,
            }
            if by_u:
                sec.update(
                    {
                        ("photoelectrons", "scale"): s * T["u"],
                        ("scale", "scale"): s * s * mix("uu"),
                        ("scale", "em_gain"): s * mix("ug") / g,
                    }
                )
            if cic:
                sec[("em_gain", "register_cic")] = T["cic_g"] / g
                if by_u:
                    sec[("scale", "register_cic")] = s * T["cic_u"]
            sec.update({(b, a): v for (a, b), v in list(sec.items())})
        return mix("v"), first, sec

    def real(self, t):
        """``K_X``, ``K_X'``, ``K_X''`` at real tilts t, the tilted photoelectron mean and
        single-electron mean output (ADU)."""
        E, scale = self.E, self.scale
        if not self.has_cic and not np.any(t):
            # Untilted: the moments (mean output g, second moment g²F²).
            g = self.gain
            F2 = self.register.excess_noise_factor(g)
            return np.zeros(E.shape), E * g * scale, E * (g * scale) ** 2 * F2, E, g * scale
        cic = self.has_cic
        T = self.register.transform_terms(t * scale, self.gain, 2, cic)

        def mix(key):
            return E * T[key] + self.cic * T["cic_" + key] if cic else E * T[key]

        growth = 1.0 + T["v"]  # M(t/φ): the tilted photoelectron mean is E·M
        # The tilted single-electron output; far below the mean it is one electron.
        with np.errstate(divide="ignore", invalid="ignore"):
            theta = np.where(growth > 0, scale * T["u"] / growth, scale)
        return mix("v"), scale * mix("u"), scale**2 * mix("uu"), E * growth, theta

    def band(self, E_t, theta_t, sigma, n):
        """DFT bins to evaluate (:meth:`Register.window_band`)."""
        return self.register.window_band(E_t, theta_t, sigma, self.scale, n)

    def saddlepoint(self, k, S0, sigma):
        """Tilt t that puts the tilted mean K'(t) within half a tilted SD of count k:
        Newton's method on K' from the gamma model's saddlepoint, kept inside a bracket,
        bisecting where it leaves the bracket or stops converging. (Any tilt gives exact
        values; the saddlepoint only centres the window on the target.)

        The bracket: the electron part of K' is positive and increasing in t, so
        ``S0 + σ²t ≤ K'(t)`` everywhere and ``K'(t) ≤ K'(0) + σ²t`` for t ≤ 0.
        """
        from ._gamma import GammaRows

        E = self.E
        mean0 = real_cgf(self, np.zeros(E.shape), S0, sigma)[1]
        lo = np.minimum(0.0, (k - mean0) / sigma**2)
        hi = (k - S0) / sigma**2
        # Start from the gamma model's saddlepoint (closed-form cumulants, cheap): a
        # register differs from it mostly in F², so Newton then needs a few steps.
        gamma = GammaRows(E, self.gain * self.scale, np.zeros(E.shape, dtype=bool))
        t = gamma.saddlepoint(k, S0, sigma)
        t = np.where((t > lo) & (t < hi), t, 0.5 * (lo + hi))

        def residual(t):
            _, dK, d2K, _, _ = real_cgf(self, t, S0, sigma)
            return dK - k, d2K

        # solved once the miss is below half the tilted distribution's SD
        return _roots.newton_in_bracket(
            residual, lo, hi, t, max_iter=100, close=lambda miss, d2K: miss < 0.5 * np.sqrt(d2K)
        )

    def direct_tail(self, sigma):
        """None: every count first gets a (tilted) window."""
        return np.zeros(self.E.shape, dtype=bool)

    def tail(self, k, S0, sigma, grad=False):
        """Saddlepoint approximation of log f(k) beyond the longest window (relative error
        of order 1/(number of electrons) there, far below 1e-10 of the peak):
        ``K(t) − tk − ½ ln(2πK''(t))`` at ``K'(t) ≈ k``; gradients by the envelope
        theorem, ``∂K/∂λ`` at the fixed t."""
        t = self.saddlepoint(k, S0, sigma)
        K, _, d2K, _, _ = real_cgf(self, t, S0, sigma)
        logf = K - t * k - 0.5 * np.log(2.0 * np.pi * d2K)
        if not grad:
            return logf, {}
        names = self.names + READOUT
        _, first, _ = count_cgf(self, t[:, None].astype(complex), S0, sigma, 1, names)
        grads = {name: first[name][:, 0].real for name in names}
        grads["offset"] = grads["offset"] - t
        return logf, grads
