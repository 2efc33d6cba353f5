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

The window engine (:mod:`._engine`) does this for any register; each register model is
one module supplying its part of K (:mod:`._gamma`: the gamma register and no
multiplication; :mod:`._exact`: the exact cascade), reached through
``EMModel(name).register`` (docs/architecture.md lists what a model supplies).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import defaults, plugins
from .._util import check_number
from ..errors import OptionError
from . import _engine, adc
from ._engine import Spectrum, fast_len, window  # noqa: F401  (for fit/ and data/)
from ._engine import extent as window_extent  # noqa: F401
from .cascade import DEFAULT_STAGES

__all__ = [
    "EMModel",
    "RecordedEMModel",
    "as_em_model",
    "choose_em_model",
    "DEFAULT_EM_MODEL",
    "logpmf",
    "pmf",
    "logpmf_grad",
    "mean",
    "variance",
    "third_cumulant",
    "excess_noise_factor",
]
# Pointwise evaluation, every count under its own parameters (bead fitting), is
# :mod:`.pointwise`'s. Also here, for the fits of fit/ and data/ (not the public API): the
# window engine's
# ``window``, ``window_extent``, ``fast_len`` and ``Spectrum``, each model's
# ``EMModel.register`` with its rows, and ``register_groups``.


def register_tables():
    """Within this block (this thread; also a decorator), the register models keep the
    tables they build for the likelihood and reuse them (the exact register's transform:
    :func:`emccdcal.model.cascade.transform_tables`): the door through which a fit opens
    them, which no module outside ``model/`` opens itself."""
    from .cascade import transform_tables

    return transform_tables()


# --------------------------------------------------------------------------------------
# Parameter checking
# --------------------------------------------------------------------------------------
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
    """The model of the EM register: a name (one of :data:`EM_MODELS`) and the register's
    stages, holding the register object they make (:attr:`register`).

    ``"gamma"`` is the paper's: the output of n electrons is Gamma(n, g), excess-noise
    factor 2 at every gain. ``"cascade"``, the default (:data:`DEFAULT_EM_MODEL`, as
    everywhere: a run, a plan, a function of this module), is the exact register of
    ``stages`` stages, in
    each of which every electron makes one more with probability p = g^{1/N} − 1
    (:mod:`emccdcal.model.cascade`); its excess-noise factor is below 2 (1.795 at
    g = 5, N = 536). Both reduce to no multiplication (Poisson–normal) at g = 1.

    The register object is made once, from the name through the registry
    (:mod:`emccdcal.plugins`), or given as it is (:meth:`of`, as xarray takes a backend
    class); nothing outside ``model/`` asks which model it has.

    Examples
    --------
    >>> str(EMModel("cascade", 604)), str(EMModel()), str(EMModel("gamma"))
    ('cascade (604 stages)', 'cascade (536 stages)', 'gamma')
    >>> float(EMModel("cascade").register.excess_noise_factor(5.0))
    1.79...
    """

    name: str = defaults.DEFAULT_EM_MODEL
    stages: int = DEFAULT_STAGES
    #: The register model object (:class:`emccdcal.model.Register` or any
    #: :class:`emccdcal.model.RegisterModel`); made from the name where not given.
    register: Any = field(default=None, compare=False, repr=False, kw_only=True)

    def __post_init__(self):
        from .cascade import _check_stages

        given = self.register is not None
        if not given and self.name not in _registers():
            raise OptionError(plugins.unknown(plugins.REGISTERS, self.name, "em_model"))
        cls = type(self.register) if given else _registers()[self.name]
        # A model without stages has one value of them, whatever was passed.
        uses = cls.uses_stages
        object.__setattr__(self, "stages", _check_stages(self.stages) if uses else DEFAULT_STAGES)
        if self.stages > defaults.MAX_STAGES:  # the likelihood's cost grows with them
            raise OptionError(
                f"stages must be at most {defaults.MAX_STAGES} (real registers "
                f"have 400 to 1100), got {self.stages}"
            )
        if not given:
            object.__setattr__(self, "register", cls(self.stages))
        if not cls.__module__.startswith("emccdcal."):
            _check_normalised(self)  # another package's: checked before any use

    @classmethod
    def of(cls, register) -> EMModel:
        """The model of a register object (an instance of a register model class).

        Examples
        --------
        >>> from emccdcal.model._exact import Cascade
        >>> EMModel.of(Cascade(604)) == EMModel("cascade", 604)
        True
        """
        return cls(register.name, getattr(register, "stages", DEFAULT_STAGES), register=register)

    def __str__(self) -> str:
        return f"{self.name} ({self.stages} stages)" if self.register.uses_stages else self.name

    @property
    def label(self) -> str:
        """A short text: ``"gamma"``, ``"cascade, 536 stages"``."""
        return self.name + (f", {self.stages} stages" if self.register.uses_stages else "")

    @property
    def attrs(self) -> dict:
        """The model as a result's attributes: ``em_model``, and ``register_stages`` for
        a model with stages."""
        return {
            "em_model": self.name,
            **({"register_stages": int(self.stages)} if self.register.uses_stages else {}),
        }

    @classmethod
    def from_attrs(cls, attrs) -> EMModel | RecordedEMModel | None:
        """The model a result's attributes record (:attr:`attrs`), or None where they
        record none (a result without a likelihood, such as ``mv-adu``).

        A model not installed here (another package's, absent) comes back as a
        :class:`RecordedEMModel`: the result's numbers need no model, so it still loads,
        exports and applies; only what computes with the register refuses, naming it.
        """
        if "em_model" not in attrs:
            return None
        name, stages = str(attrs["em_model"]), int(attrs.get("register_stages", DEFAULT_STAGES))
        if name not in _registers():
            return RecordedEMModel(name, stages)
        return cls(name, stages)


@dataclass(frozen=True)
class RecordedEMModel:
    """A register model a result names that is not installed here: its name and stages,
    as the result recorded them, printed and recorded again; its ``register`` refuses.

    Examples
    --------
    >>> m = RecordedEMModel("someone-elses", 600)
    >>> str(m), m.attrs
    ('someone-elses (600 stages)', {'em_model': 'someone-elses', 'register_stages': 600})
    """

    name: str
    stages: int = DEFAULT_STAGES

    @property
    def register(self):
        raise OptionError(
            f"em_model {self.name!r}, which this result was fitted with, is not installed "
            "here: its numbers are used as they are (export, apply), and what computes "
            "with the register needs the package that provides it"
        )

    def __str__(self) -> str:
        return f"{self.name} ({self.stages} stages)"

    @property
    def label(self) -> str:
        return f"{self.name}, {self.stages} stages"

    @property
    def attrs(self) -> dict:
        return {"em_model": self.name, "register_stages": int(self.stages)}


@functools.cache
def _check_normalised(model: EMModel) -> None:
    """Refuse, once per process and model, a register model (another package's) whose
    counts' distribution is not one: its probabilities at a test point (5 e⁻, gain 20,
    1 e⁻/ADU, σ = 3 ADU) must sum to 1 over every count that can occur. A model whose sum
    is e⁵ leaves the gains where they are and moves the log-likelihood by 72 %."""
    name = model.name
    counts = np.arange(0, 4000)
    try:
        total = float(np.sum(pmf(counts, 5.0, 20.0, 1.0, 100.0, 3.0, em_model=model)))
    except Exception as exc:  # noqa: BLE001 - another package's code, in one line
        from .._util import one_line

        raise OptionError(
            f"em_model {name!r} fails on a test distribution ({type(exc).__name__}: "
            f"{one_line(exc)})"
        ) from None
    if not abs(total - 1.0) < 1e-3:
        raise OptionError(
            f"em_model {name!r}: its distribution of counts sums to {total:.6g}, not 1 "
            "(at 5 e-, gain 20): not a probability distribution"
        )


def _registers() -> dict:
    """The register models by name: the entry points of ``emccdcal.registers``
    (:mod:`emccdcal.plugins`), the package's own (:mod:`._gamma`, :mod:`._exact`) and any
    other package's."""
    return plugins.load(plugins.REGISTERS)


def __getattr__(name):
    if name == "EM_MODELS":  # the register models EMModel knows, plug-ins included
        return tuple(_registers())
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: The model that stages alone select.
_WITH_STAGES = "cascade"


#: The register model of a run that neither its caller nor its manifest names (declared
#: in :mod:`emccdcal.defaults`).
DEFAULT_EM_MODEL = defaults.DEFAULT_EM_MODEL


def choose_em_model(
    em_model=None, stages=None, *, manifest_model=None, manifest_stages=None, camera_model=None
) -> tuple[EMModel, str]:
    """The register model of a run, and where its stages come from.

    The model: the caller's ``em_model`` (a name or an :class:`EMModel`), else the
    cascade where the caller gives ``stages``, else the manifest's ``em_model``, else
    :data:`DEFAULT_EM_MODEL`. The cascade's stages: the caller's, else the manifest's
    ``register_stages``, else those :data:`emccdcal.model.cascade.KNOWN_REGISTERS` states
    for the files' ``camera_model``, else :data:`DEFAULT_STAGES`.

    Returns
    -------
    model : EMModel
    stages_source : str
        ``"given"``, ``"manifest"``, ``"camera model 'M': SOURCE"`` or ``"default"``;
        ``""`` for a model without stages.

    Examples
    --------
    >>> model, source = choose_em_model(camera_model="DU888_BV")
    >>> str(model), source
    ('cascade (604 stages)', "camera model 'DU888_BV': Andor DU-888 (iXon 888), a CCD201-20 sensor")
    >>> str(choose_em_model("gamma")[0]), str(choose_em_model()[0])
    ('gamma', 'cascade (536 stages)')
    """
    from .cascade import known_stages

    if em_model is not None and not isinstance(em_model, str):
        em_model = as_em_model(em_model)  # an EMModel or a register object
    if isinstance(em_model, EMModel):
        if stages is not None and (
            not em_model.register.uses_stages or int(stages) != em_model.stages
        ):
            raise OptionError(f"stages={stages!r} disagrees with the {em_model} model")
        return em_model, "given" if em_model.register.uses_stages else ""
    name = as_em_model(
        em_model
        or (_WITH_STAGES if stages is not None else None)
        or manifest_model
        or DEFAULT_EM_MODEL
    ).name
    if not EMModel(name).register.uses_stages:
        if stages is not None:
            raise OptionError(
                f"stages are the {_WITH_STAGES} model's: give em_model="
                f"'{_WITH_STAGES}' with them (the {name} model has none)"
            )
        return EMModel(name), ""
    if stages is not None:
        return EMModel(name, stages), "given"
    if manifest_stages is not None:
        return EMModel(name, manifest_stages), "manifest"
    known = known_stages(camera_model)
    if known is not None:
        return EMModel(name, known[0]), f"camera model {camera_model!r}: {known[1]}"
    return EMModel(name), "default"


def as_em_model(em_model=defaults.DEFAULT_EM_MODEL) -> EMModel:
    """The :class:`EMModel` that every function here takes as ``em_model``: the model
    itself, a register object (:meth:`EMModel.of`), or a name (its default stages; a
    register of other length is ``EMModel("cascade", N)``). A run's model, with the stages its caller, manifest or
    camera give, is :func:`choose_em_model`'s."""
    if isinstance(em_model, EMModel):
        return em_model
    if hasattr(em_model, "rows") and hasattr(em_model, "name"):  # a register object
        return EMModel.of(em_model)
    if not isinstance(em_model, str):
        raise OptionError(
            f"em_model must be one of {', '.join(_registers())} or an EMModel, got {em_model!r}"
        )
    return EMModel(em_model)


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


def variance(
    photoelectrons, em_gain, e_per_adu, offset, read_noise, *, em_model=defaults.DEFAULT_EM_MODEL
):
    """Variance of the count, ADU²: ``σ² + F²E(g/φ)²`` with the register model's F²
    (:func:`excess_noise_factor`: 2 for the gamma model), ``σ² + E/φ²`` at g = 1, and
    the ADC's 1/12 where the model rounds (:mod:`emccdcal.model.adc`: there σ is the
    analog read noise).

    Parameters are those of :func:`mean`, and the register model as in :func:`logpmf`.

    Examples
    --------
    >>> round(float(variance(370.0, 5.0, 3.859, 587.0, 15.5, em_model="cascade")), 4)
    1355.3292
    """
    E, g, phi, _, sigma = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    F2 = excess_noise_factor(g, em_model=em_model)
    rounding = adc.rounds(g == 1, sigma) / 12.0
    return sigma**2 + rounding + np.where(g == 1, E / phi**2, F2 * E * (g / phi) ** 2)


def third_cumulant(photoelectrons, em_gain, e_per_adu, offset, read_noise):
    """Third cumulant of the count, ADU³: ``6E(g/φ)³`` (the gamma model) or ``E/φ³`` (PN)."""
    E, g, phi, _, _ = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    return np.where(g == 1, E / phi**3, 6 * E * (g / phi) ** 3)


def excess_noise_factor(em_gain, *, em_model=defaults.DEFAULT_EM_MODEL):
    """Excess-noise factor F² of the model's multiplication, ``Var(X)/(g²E)``.

    2 for the gamma model (any g > 1), 1 for no multiplication (g = 1); for the cascade
    model that of an N-stage register (:func:`emccdcal.model.cascade.excess_noise_factor`),
    below 2.
    """
    g = check_number("em_gain", em_gain, minimum=1.0, scalar=False)
    return as_em_model(em_model).register.excess_noise_factor(g)


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


def _model_of(em_model, register_cic=0.0):
    """The checked :class:`EMModel`; register CIC only goes with a model that has it."""
    model = as_em_model(em_model)
    if "register_cic" not in model.register.parameters and np.any(np.asarray(register_cic) != 0):
        raise OptionError(
            f"register_cic is a parameter of the cascade model, not of the "
            f"{model.name} model: give em_model='cascade' with it"
        )
    return model


def register_groups(g, model):
    """The rows of each register of ``model`` (no multiplication at g = 1, which a
    register may hand to another): pairs (register, boolean mask)."""
    register = as_em_model(model).register
    regs = [register.register_for(True), register.register_for(False)]
    if regs[0] == regs[1]:
        return [(regs[0], np.ones(g.shape, dtype=bool))]
    pn = g == 1.0
    return [(regs[0], pn), (regs[1], ~pn)]


def _evaluate_public(E, g, phi, S0, sigma, cic, row, k, model, grad=False):
    """log p(k) and gradients by the public parameters for rows of public parameters.

    Rows with g = 1 use the Poisson–normal model under every register model (no
    multiplication: the register's clock-induced charge is not counted there); the
    others the model's register. Gradients: ``photoelectrons``, ``em_gain`` (NaN at
    g = 1), ``e_per_adu``, ``offset``, ``read_noise`` and the register's own
    parameters (the cascade's ``register_cic``).
    """
    logp = np.full(k.shape, np.nan)
    names = ("photoelectrons", "em_gain", "e_per_adu", "offset", "read_noise")
    names += model.register.parameters
    grads = {name: np.full(k.shape, np.nan) for name in names} if grad else {}
    for register, part in register_groups(g, model):
        rows = np.flatnonzero(part)
        q = np.flatnonzero(part[row])
        if q.size == 0:
            continue
        local = np.full(g.shape, -1)
        local[rows] = np.arange(rows.size)
        lr = local[row[q]]
        reg_rows = register.rows(E[rows], g[rows], phi[rows], cic[rows])
        lp, d = _engine.evaluate(reg_rows, S0[rows], sigma[rows], lr, k[q], grad=grad)
        logp[q] = lp
        if not grad:
            continue
        public = register.public_gradients(d, g[rows][lr], phi[rows][lr])
        for name in names:
            if name in ("photoelectrons", "offset", "read_noise"):
                grads[name][q] = d[name]
            else:  # a parameter this register does not have (CIC without multiplication)
                grads[name][q] = public.get(name, 0.0)
    return logp, grads


def logpmf(
    counts,
    photoelectrons,
    em_gain,
    e_per_adu,
    offset,
    read_noise,
    *,
    em_model=defaults.DEFAULT_EM_MODEL,
    register_cic=0.0,
):
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
        The register: the exact Bernoulli cascade (the default, :data:`DEFAULT_EM_MODEL`,
        of 536 stages; ``EMModel("cascade", N)`` for N) or the paper's gamma
        approximation.
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
    >>> gamma = pmf(counts, 370.0, 5.0, 3.859, 587.0, 15.5, em_model="gamma")
    >>> exact = pmf(counts, 370.0, 5.0, 3.859, 587.0, 15.5)  # the default: 536 stages
    >>> round(float(sd(exact) / sd(gamma)), 4)
    0.9561
    """
    model = _model_of(em_model, register_cic)
    shape, k, row, rows = _prepare(
        counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, register_cic
    )
    logp, _ = _evaluate_public(*rows, row, k, model)
    return logp.reshape(shape)


def pmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, **model):
    """Probability of integer counts: ``exp(logpmf(...))``; parameters as :func:`logpmf`."""
    return np.exp(logpmf(counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, **model))


def logpmf_grad(
    counts,
    photoelectrons,
    em_gain,
    e_per_adu,
    offset,
    read_noise,
    *,
    em_model=defaults.DEFAULT_EM_MODEL,
    register_cic=0.0,
):
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
    model = _model_of(em_model, register_cic)
    shape, k, row, rows = _prepare(
        counts, photoelectrons, em_gain, e_per_adu, offset, read_noise, register_cic
    )
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

    E, g, phi, S0, sigma = (
        float(v) for v in _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    )
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
