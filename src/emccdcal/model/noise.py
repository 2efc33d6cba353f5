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
from dataclasses import dataclass

import numpy as np

from .. import defaults, plugins
from .._util import check_number
from ..errors import OptionError
from . import _engine
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
    "logpmf_rows",
    "LogpmfTable",
]
# Also here, for the fits of fit/ and data/ (not the public API): the window engine's
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
    """The model of the EM register, by name: one of :data:`EM_MODELS`.

    ``"gamma"`` is the paper's: the output of n electrons is Gamma(n, g), excess-noise
    factor 2 at every gain. ``"cascade"``, the default (:data:`DEFAULT_EM_MODEL`, as
    everywhere: a run, a plan, a function of this module), is the exact register of
    ``stages`` stages, in
    each of which every electron makes one more with probability p = g^{1/N} − 1
    (:mod:`emccdcal.model.cascade`); its excess-noise factor is below 2 (1.795 at
    g = 5, N = 536). Both reduce to no multiplication (Poisson–normal) at g = 1.

    What a model does lives in its :attr:`register` (one module per model under
    ``emccdcal/model/``); nothing outside ``model/`` asks which model it has.

    Examples
    --------
    >>> str(EMModel("cascade", 604)), str(EMModel()), str(EMModel("gamma"))
    ('cascade (604 stages)', 'cascade (536 stages)', 'gamma')
    >>> float(EMModel("cascade").register.excess_noise_factor(5.0))
    1.79...
    """

    name: str = defaults.DEFAULT_EM_MODEL
    stages: int = DEFAULT_STAGES

    def __post_init__(self):
        if self.name not in _registers():
            raise OptionError(plugins.unknown(plugins.REGISTERS, self.name, "em_model"))
        from .cascade import _check_stages

        if not _registers()[self.name].__module__.startswith("emccdcal.") and (
            self.name not in _CHECKING
        ):
            _check_normalised(self.name)  # another package's: checked before any use
        # A model without stages has one value of them, whatever was passed.
        uses = _registers()[self.name].uses_stages
        object.__setattr__(self, "stages", _check_stages(self.stages) if uses else DEFAULT_STAGES)
        if self.stages > defaults.MAX_STAGES:  # the likelihood's cost grows with them
            raise OptionError(
                f"stages must be at most {defaults.MAX_STAGES} (real registers "
                f"have 400 to 1100), got {self.stages}"
            )

    @property
    def register(self):
        """The register model's pieces: its rows for the window engine, fit coordinates,
        excess-noise factor, description (:mod:`._gamma`, :mod:`._exact`)."""
        return _registers()[self.name](self.stages)

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


#: Register models whose normalisation is being checked (:func:`_check_normalised`).
_CHECKING: set = set()


@functools.cache
def _check_normalised(name: str) -> None:
    """Refuse, once per process, a register model (another package's) whose counts'
    distribution is not one: its probabilities at a test point (5 e⁻, gain 20, 1 e⁻/ADU,
    σ = 3 ADU) must sum to 1 over every count that can occur. A model whose sum is e⁵
    leaves the gains where they are and moves the log-likelihood by 72 %."""
    counts = np.arange(0, 4000)
    _CHECKING.add(name)  # the test distribution's own EMModel is not checked again
    try:
        total = float(np.sum(pmf(counts, 5.0, 20.0, 1.0, 100.0, 3.0, em_model=name)))
    except Exception as exc:  # noqa: BLE001 - another package's code, in one line
        from .._util import one_line

        raise OptionError(
            f"em_model {name!r} fails on a test distribution ({type(exc).__name__}: "
            f"{one_line(exc)})"
        ) from None
    finally:
        _CHECKING.discard(name)
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
    itself, or a name (its default stages; a register of other length is
    ``EMModel("cascade", N)``). A run's model, with the stages its caller, manifest or
    camera give, is :func:`choose_em_model`'s."""
    if isinstance(em_model, EMModel):
        return em_model
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
    (:func:`excess_noise_factor`: 2 for the gamma model), ``σ² + E/φ²`` at g = 1.

    Parameters are those of :func:`mean`, and the register model as in :func:`logpmf`.

    Examples
    --------
    >>> round(float(variance(370.0, 5.0, 3.859, 587.0, 15.5, em_model="cascade")), 4)
    1355.3292
    """
    E, g, phi, _, sigma = _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    F2 = excess_noise_factor(g, em_model=em_model)
    return sigma**2 + np.where(g == 1, E / phi**2, F2 * E * (g / phi) ** 2)


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


# --------------------------------------------------------------------------------------
# Pointwise evaluation: every count under its own parameters (bead fitting)
# --------------------------------------------------------------------------------------
#: Points of FFT windows evaluated together by :func:`logpmf_rows`; bounds its memory
#: (a few tens of bytes per point).
_ROWS_POINTS = 2**22


def logpmf_rows(
    counts,
    row,
    photoelectrons,
    em_gain,
    e_per_adu,
    offset,
    read_noise,
    *,
    grad=False,
    em_model=defaults.DEFAULT_EM_MODEL,
):
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
    em_model : str or EMModel, optional
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
    params = [
        np.atleast_1d(a).ravel()
        for a in _check_params(photoelectrons, em_gain, e_per_adu, offset, read_noise)
    ]
    U = max(a.size for a in params)
    if any(a.size not in (1, U) for a in params):
        raise OptionError(
            "photoelectrons, em_gain, e_per_adu, offset and read_noise must "
            "have one value per row (or a single value)"
        )
    E, g, phi, S0, sigma = (np.broadcast_to(a, (U,)) for a in params)
    if idx.shape != k.shape:
        raise OptionError(f"row has {idx.size} entries but counts has {k.size}")
    if idx.size and (idx.dtype.kind not in "iu" or idx.min() < 0 or idx.max() >= U):
        raise OptionError(f"row must hold integer indices from 0 to {U - 1}")
    model = as_em_model(em_model)
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
        q = order[bounds[a] : bounds[b]]
        local = np.repeat(np.arange(b - a), np.diff(bounds[a : b + 1]))
        lp, d = _evaluate_public(
            E[r], g[r], phi[r], S0[r], sigma[r], cic[r], local, k[q], model, grad=grad
        )
        logp[q] = lp
        if grad:
            dE[q] = d["photoelectrons"]
    return (logp, dE) if grad else logp


def _window_lengths(E, g, phi, S0, sigma, model):
    """Length (counts) of the window that covers each row's distribution."""
    length = np.zeros(g.shape, dtype=np.int64)
    for register, part in register_groups(g, model):
        if part.any():
            rows = register.rows(E[part], g[part], phi[part], np.zeros(int(part.sum())))
            length[part] = _engine.window_start(rows, S0[part], sigma[part])[1]
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
    em_model : str or EMModel, optional
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

    def __init__(
        self,
        counts,
        pixel,
        e_lo,
        e_hi,
        em_gain,
        e_per_adu,
        offset,
        read_noise,
        *,
        em_model=defaults.DEFAULT_EM_MODEL,
    ):
        self.em_model = as_em_model(em_model)
        self.counts = _check_counts(counts).ravel()
        self.pixel = np.asarray(pixel).ravel()
        if self.pixel.shape != self.counts.shape:
            raise OptionError(
                f"pixel has {self.pixel.size} entries but counts has {self.counts.size}"
            )
        params = [
            np.atleast_1d(a).astype(float).ravel()
            for a in _check_params(1.0, em_gain, e_per_adu, offset, read_noise)[1:]
        ]
        K = max(a.size for a in params)
        self.em_gain, self.e_per_adu, self.offset, self.read_noise = (
            np.broadcast_to(a, (K,)).copy() for a in params
        )
        if self.pixel.size and (
            self.pixel.dtype.kind not in "iu" or self.pixel.min() < 0 or self.pixel.max() >= K
        ):
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
        if not (
            np.all(np.isfinite(lo))
            and np.all(np.isfinite(hi))
            and np.all(lo >= 0)
            and np.all(hi > lo)
        ):
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
                [self.coef, np.zeros((D - self.coef.shape[0], self.coef.shape[1]))]
            )
        chosen = np.zeros(self.degree.size, dtype=bool)
        chosen[pixels] = True
        q = np.flatnonzero(chosen[self.pixel])
        if q.size == 0:
            return
        # Distinct (pixel, count) pairs; each is tabulated at its pixel's nodes.
        pair, inv = np.unique(
            np.stack([self.pixel[q], self.counts[q]]), axis=1, return_inverse=True
        )
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
                np.repeat(cnt[sel], d),
                query_row,
                nodes_E,
                self.em_gain[rows],
                self.e_per_adu[rows],
                self.offset[rows],
                self.read_noise[rows],
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
        dx = np.where(lg, 1.0 / Ec, 0.5 / u)  # dx/dE
        d2x = np.where(lg, -1.0 / Ec**2, -0.25 / u**3)  # d²x/dE²
        d1 = ft / half * dx
        d2 = ftt / half**2 * dx**2 + ft / half * d2x
        return f, d1, d2, outside
