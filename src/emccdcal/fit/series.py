"""The one door to the likelihood engine: a method's likelihood over a block of pixels.

Every caller that fits a series or asks what a series would tell (``calibrate``, the
posterior sampler, ``acquire``'s running fit, ``plan``) describes it the same way and goes
through :class:`SeriesLikelihood`:

- each acquisition's **model half**, :class:`AcquisitionModel`: its set-point, the
  register model (one :class:`emccdcal.model.noise.EMModel` value), the offset and
  read-noise maps of the block's pixels and how well they are known;
- its **data half**, the pixels' histograms (:class:`emccdcal.data.stats.PixelHistograms`),
  or none at all where only the model's expected information is wanted (a plan);
- the method, and φ where the method holds it fixed.

What a run fits is decided here too, once for every caller: :func:`specify` turns a
manifest and a method into the acquisitions fitted, the register model and the checked
options; :func:`acquisition_models` makes the model halves; :func:`choose_register`
the register model of a run. Outside ``fit/`` and ``model/`` no module does any of it itself.

The parameters are named records (:class:`emccdcal.fit.engine.Parameter`), looked up by
quantity and acquisition (:meth:`SeriesLikelihood.index`), never by parsing a name.
How the engine's blocks and layouts are built is private to :mod:`emccdcal.fit`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .._util import nanmedian
from ..data.dark import map_variances
from ..data.stacks import read_band
from ..defaults import MAX_ACQUISITIONS
from ..errors import DataQualityWarning, InputError, OptionError
from ..model import noise
from . import comb, engine, gof, layouts, mv, profile, scores
from .engine import QUANTITIES, Parameter

__all__ = [
    "AcquisitionModel",
    "FitSpec",
    "Parameter",
    "SeriesLikelihood",
    "acquisition_models",
    "fit_series",
    "choose_register",
    "specify",
]


@dataclass(frozen=True)
class FitSpec:
    """What a run of a method on a manifest fits (:func:`specify`).

    Attributes
    ----------
    method : str
    acquisitions : tuple of emccdcal.data.manifest.Acquisition
        Those the method fits, in its order.
    em_model : noise.EMModel
        The register model.
    stages_source : str
        Where its stages came from (:func:`emccdcal.model.noise.choose_em_model`).
    options : dict or None
        The method's options, checked.
    e_per_adu, e_per_adu_se : ndarray (rows, cols) or None
        The φ the method holds fixed (e⁻/ADU) and its standard error where it came with
        one (a chained result's); None where φ is not given.
    e_per_adu_source : emccdcal.data.manifest.Source or None
        Where the given φ came from.
    """

    method: str
    acquisitions: tuple
    em_model: noise.EMModel
    stages_source: str
    options: dict | None
    e_per_adu: np.ndarray | None = None
    e_per_adu_se: np.ndarray | None = None
    e_per_adu_source: object = None


def specify(
    manifest,
    method,
    *,
    e_per_adu=None,
    e_per_adu_se=None,
    e_per_adu_source=None,
    accept_phi=False,
    em_model=None,
    stages=None,
    options=None,
) -> FitSpec:
    """The fit's specification of a run: the method's options checked, its register model
    (the caller's, else the manifest's or the camera's, else the default), the manifest's
    acquisitions it fits, and the φ it is given (a (rows, cols) map in e⁻/ADU, its SE map
    and where it came from; :func:`emccdcal.given_phi.e_per_adu_inputs` reads a chained
    result's), checked against the data before any fitting: a φ the 1× acquisition's
    photon transfer contradicts is refused, unless ``accept_phi``.

    Raises
    ------
    OptionError, MethodError, InputError
        An option, a model, a manifest or a φ the method cannot take, in one line.
    """
    options = layouts.check_options(method, options)
    model, source = choose_register(em_model, stages, manifest)
    acqs = manifest.acquisitions
    phi_given = e_per_adu is not None
    idx = layouts.select_acquisitions(
        method, [a.em_gain_setpoint for a in acqs], [a.level for a in acqs], phi_given
    )
    used = tuple(acqs[i] for i in idx)
    if phi_given and method not in ("is-adu", "mv-adu") and not accept_phi:
        _check_given_phi(e_per_adu, e_per_adu_se, e_per_adu_source, used, method)
    return FitSpec(method, used, model, source, options, e_per_adu, e_per_adu_se, e_per_adu_source)


def choose_register(em_model=None, stages=None, manifest=None) -> tuple[noise.EMModel, str]:
    """The register model of a run and where its stages come from: the caller's
    ``em_model`` (a name or an :class:`~emccdcal.model.noise.EMModel`) and ``stages``,
    else the manifest's, else its camera's, else the default
    (:func:`emccdcal.model.noise.choose_em_model`)."""
    if manifest is None:
        return noise.choose_em_model(em_model, stages)
    return noise.choose_em_model(
        em_model,
        stages,
        manifest_model=manifest.em_model,
        manifest_stages=manifest.register_stages,
        camera_model=manifest.camera.get("model"),
    )


def acquisition_models(
    setpoints, offsets, read_noise, em_model, dark_frames=None, map_groups=None
) -> list:
    """The model halves of a series' acquisitions over P pixels: per acquisition its
    set-point, offset and read-noise maps (each (P,), ADU), the register model, the dark
    frames behind its maps and their group (None: exact maps, each its own)."""
    n = len(setpoints)
    dark_frames = [None] * n if dark_frames is None else list(dark_frames)
    map_groups = [None] * n if map_groups is None else list(map_groups)
    return [
        AcquisitionModel(float(s), o, r, em_model, d, g)
        for s, o, r, d, g in zip(setpoints, offsets, read_noise, dark_frames, map_groups)
    ]


@dataclass(frozen=True)
class AcquisitionModel:
    """The model half of one acquisition for a block of P pixels.

    Attributes
    ----------
    setpoint : float
        The EM-gain set-point; 1 means no multiplication (the Poisson–normal model).
    offset, read_noise : ndarray, shape (P,)
        S0 and σ of the pixels (ADU).
    em_model : noise.EMModel
        The register model of a multiplied acquisition.
    dark_frames : int, optional
        Frames of the dark stack the maps come from: their own variances are σ²/n for
        the offset (the SE of a mean) and σ²/(2(n−1)) for the read noise (of an SD),
        ADU²; None for maps taken as exact.
    map_group : hashable, optional
        Acquisitions of one group share one pair of maps (one dark stack), so their map
        errors are one draw.
    """

    setpoint: float
    offset: np.ndarray
    read_noise: np.ndarray
    em_model: noise.EMModel
    dark_frames: int | None = None
    map_group: object = None

    def _block(self, histograms=None) -> engine.AcquisitionBlock:
        """The engine's block of this acquisition, with its data where given."""
        pn = bool(self.setpoint == 1)
        offset_var, read_noise_var = map_variances(
            self.offset, self.read_noise, self.dark_frames, pn
        )
        maps = dict(
            offset=self.offset,
            read_noise=self.read_noise,
            poisson_normal=pn,
            map_group=self.map_group,
            em_model=self.em_model,
            offset_var=offset_var,
            read_noise_var=read_noise_var,
        )
        if histograms is None:
            return engine.AcquisitionBlock(
                values=None, counts=None, mean=None, var=None, n=None, **maps
            )
        h = histograms
        # Only the bins some pixel uses: the block's data, and so its fit, do not depend
        # on which other pixels were histogrammed with it.
        used = (h.counts != 0).any(axis=0)
        width = h.counts.shape[1] - int(np.argmax(used[::-1])) if h.counts.size else 0
        return engine.AcquisitionBlock(
            values=h.values[:, :width],
            counts=h.counts[:, :width],
            mean=h.mean,
            var=h.var,
            n=h.n,
            **maps,
        )


class SeriesLikelihood:
    """A method's likelihood of a series over a block of P pixels.

    Parameters
    ----------
    method : str
        A likelihood method (:data:`emccdcal.fit.layouts.LIKELIHOOD_METHODS`).
    models : sequence of AcquisitionModel
        The acquisitions the method uses, in order.
    histograms : sequence of emccdcal.data.stats.PixelHistograms, optional
        Each acquisition's data, P pixels each. Without them only what needs no data is
        available (:meth:`expected_information`, :meth:`point`); the hierarchical gain
        series, whose prior is centred on its data, needs them.
    e_per_adu : array_like, shape (P,) or scalar, optional
        φ (e⁻/ADU) where the method holds it fixed.
    options : dict, optional
        The method's options (:func:`emccdcal.fit.layouts.check_options`).

    Examples
    --------
    What one frame of a 1× and a 10× acquisition tells about the gain (no data needed):

    >>> from emccdcal.model.noise import EMModel
    >>> m = [AcquisitionModel(s, np.array([100.0]), np.array([5.0]), EMModel("gamma"))
    ...      for s in (1, 10)]
    >>> lik = SeriesLikelihood("gs", m, e_per_adu=2.0)
    >>> [p.name for p in lik.parameters]
    ['ln_photoelectrons', 'ln_em_gain[1]']
    >>> lik.index("em_gain", 1), lik.index("em_gain", 0)
    (1, None)
    """

    def __init__(self, method, models, histograms=None, *, e_per_adu=None, options=None):
        self.method = method
        self.models = list(models)
        if len(self.models) > MAX_ACQUISITIONS:  # its information grows as their cube
            raise OptionError(
                f"a series of {len(self.models)} acquisitions: at most {MAX_ACQUISITIONS} "
                "(the fit's information matrices grow as the cube of their number)"
            )
        P = np.shape(self.models[0].offset)[0]
        data = [None] * len(self.models) if histograms is None else list(histograms)
        self.blocks = [m._block(h) for m, h in zip(self.models, data)]
        setpoints = np.array([float(m.setpoint) for m in self.models])
        phi = (
            None if e_per_adu is None else np.broadcast_to(np.asarray(e_per_adu, dtype=float), (P,))
        )
        self.e_per_adu = phi
        if histograms is None:
            self.layout, self.start = layouts.layout_of(method, setpoints, phi, P), None
        else:
            series = layouts.Series(self.blocks, setpoints, phi)
            self.layout, self.start = layouts.build_layout(method, series, options)

    @classmethod
    def _of(cls, method, models, blocks, layout, start, e_per_adu):
        lik = cls.__new__(cls)
        lik.method, lik.models, lik.blocks = method, models, blocks
        lik.layout, lik.start, lik.e_per_adu = layout, start, e_per_adu
        return lik

    # ---- the parameters --------------------------------------------------------------
    @property
    def parameters(self) -> list[Parameter]:
        """The free parameters, in the order of ``x``'s columns."""
        return list(self.layout.parameters)

    def index(self, quantity: str, acquisition: int | None = None) -> int | None:
        """Column of the free parameter that sets ``quantity`` of ``acquisition`` (own or
        shared); without an acquisition, the shared one; None where the method fixes it."""
        return self.layout.index(quantity, acquisition)

    @property
    def informs(self) -> np.ndarray:
        """Which free parameters each acquisition's data inform (A, F)."""
        return np.abs(self.layout.matrix).sum(axis=1) > 0

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of ``x`` (F,), logs of the quantities."""
        return self.layout.lower, self.layout.upper

    def point(self, values) -> np.ndarray:
        """``x`` (P, F) of given quantities: ``values`` maps a quantity to its value for
        every pixel and acquisition (broadcast to (P, A)); a shared parameter takes the
        value of the first acquisition it moves."""
        P, A = self.layout.constant.shape[:2]
        x = np.zeros((P, self.layout.n_free))
        for j, p in enumerate(self.parameters):
            a = p.acquisition
            if a is None:
                a = int(np.flatnonzero(self.layout.matrix[:, QUANTITIES.index(p.quantity), j])[0])
            x[:, j] = np.log(np.broadcast_to(np.asarray(values[p.quantity], float), (P, A))[:, a])
        return x

    def take(self, idx) -> SeriesLikelihood:
        """The same likelihood for pixels ``idx`` (repeats allowed)."""
        sub = lambda a: None if a is None else a[idx]  # noqa: E731
        return self._of(
            self.method,
            self.models,
            [b.take(idx) for b in self.blocks],
            self.layout.subset(idx),
            sub(self.start),
            sub(self.e_per_adu),
        )

    # ---- evaluation ----------------------------------------------------------------------
    @noise.register_tables()  # a sampler's thousands of calls share the register's tables
    def objective(self, x) -> np.ndarray:
        """Log-likelihood plus the layout's own log prior (P,), nats: what :meth:`fit`
        maximises."""
        return engine.objective(self.layout, self.blocks, x)

    @noise.register_tables()
    def fit(self, **options) -> engine.FitResult:
        """The maximum-likelihood (or, with a prior, MAP) fit of every pixel from the
        method's starting values (:func:`emccdcal.fit.engine.fit`'s options)."""
        return engine.fit(self.layout, self.blocks, self.start, **options)

    def expected_information(self, x):
        """Per-frame Fisher information of ``x`` (P, A, F, F) and its cross information
        with the (offset, read noise) maps (P, A, F, 2): from the models alone."""
        return scores.expected_information(self.layout, self.blocks, x)

    # ---- what a calibration reports ------------------------------------------------------
    @noise.register_tables()
    def estimates(self, fit, *, e_per_adu_se=None, intervals=None, gof_test=True) -> dict:
        """E, g and φ of every acquisition with their standard errors, and with them
        each acquisition's goodness of fit, the log-likelihoods and convergence.

        Parameters
        ----------
        fit : emccdcal.fit.engine.FitResult
            This likelihood's :meth:`fit`.
        e_per_adu_se : ndarray, shape (P,), optional
            The SE of a given φ (e⁻/ADU): its error moves every E and g of a pixel
            together, and is added to their covariance.
        intervals : str, optional
            ``"profile"``: profile-likelihood bounds ``<name>_lower``/``_upper``; the
            hierarchical gain series always gets those of its unpooled model.
        gof_test : bool
            Each acquisition's goodness-of-fit p-value (``gof_pvalue``).

        Returns
        -------
        dict of ndarray
            ``photoelectrons``, ``em_gain``, ``e_per_adu`` and ``<name>_se`` (P, A);
            ``gof_pvalue``, ``acquisition_loglik`` (P, A); ``loglik``, ``converged``,
            ``n_floored``, ``iterations`` (P,); the hierarchical model's
            ``hyper_photoelectrons`` and ``hyper_sd_photoelectrons`` (P,).
        """
        layout, blocks = self.layout, self.blocks
        cov = fit.cov
        if self.method == "is-adu":  # a comb's ripples: its profile's width (fit.comb)
            cov = comb.ripple_covariance(layout, cov)
        if e_per_adu_se is not None:  # φ's own error moves every E and g together
            sens = profile.e_per_adu_sensitivity(layout, blocks, fit.x)
            rel_se = np.asarray(e_per_adu_se, float) / self.e_per_adu
            cov = profile.with_phi_error(cov, sens, rel_se)
        e = layouts.acquisition_estimates(layout, fit.x, cov)
        if self.e_per_adu is not None:  # φ given: its error is known only when chained
            se = np.nan if e_per_adu_se is None else np.asarray(e_per_adu_se, float)[:, None]
            e["e_per_adu_se"] = np.broadcast_to(se, e["e_per_adu"].shape).copy()
        if intervals == "profile":
            bounds = layouts.acquisition_bounds(layout, blocks, fit)
            if self.method == "is-adu":  # a comb of rival ripples: its χ²₁ holds one
                bounds = comb.ripple_bounds(layout, fit.cov, e, bounds)
            e.update(bounds)
        elif self.method == "gs-hierarchical":
            e.update(layouts.unpooled_bounds(layout, blocks, fit))
        if gof_test:
            e["gof_pvalue"] = self._gof(fit, e)
        e.update(
            loglik=fit.loglik,
            acquisition_loglik=fit.loglik_per_acquisition,
            converged=fit.converged,
            n_floored=fit.n_floored,
            iterations=fit.iterations,
        )
        if self.method == "gs-hierarchical":
            e["hyper_photoelectrons"], e["hyper_sd_photoelectrons"] = layout.hyperparameters(fit.x)
        return e

    def _gof(self, fit, e):
        """Each acquisition's goodness-of-fit p-value (P, A); a free parameter shared by
        k acquisitions counts 1/k towards each one's fitted-parameter number."""
        touches = np.any(self.layout.matrix != 0, axis=1)  # (A, F)
        n_fitted = (touches / np.maximum(touches.sum(axis=0), 1)).sum(axis=1)
        # no test where the fit found no finite likelihood (its parameters fit nothing)
        tested = np.where(np.isfinite(fit.loglik), 1.0, np.nan)
        return np.stack(
            [
                gof.gof_pvalues(
                    b,
                    e["photoelectrons"][:, a] * tested,
                    e["em_gain"][:, a],
                    e["e_per_adu"][:, a],
                    b.offset,
                    b.read_noise,
                    n_fitted_params=float(n_fitted[a]),
                    em_model=b.em_model,
                )[0]
                for a, b in enumerate(self.blocks)
            ],
            axis=1,
        )


def fit_series(
    method,
    models,
    histograms,
    *,
    e_per_adu=None,
    e_per_adu_se=None,
    options=None,
    intervals=None,
    gof_test=True,
) -> dict:
    """Fit a series and report it: :meth:`SeriesLikelihood.fit`, then
    :meth:`SeriesLikelihood.estimates` (see those for the arguments and the result)."""
    lik = SeriesLikelihood(method, models, histograms, e_per_adu=e_per_adu, options=options)
    with noise.register_tables():  # the fit's tables serve its estimates too
        return lik.estimates(
            lik.fit(), e_per_adu_se=e_per_adu_se, intervals=intervals, gof_test=gof_test
        )


def _check_given_phi(phi_map, phi_se, source, used, method) -> None:
    """Refuse a given φ that the data contradict, before any fitting.

    The 1× acquisition's photon transfer (:func:`emccdcal.fit.mv.photon_transfer_e_per_adu`,
    on at most :data:`~emccdcal.defaults.PHI_CHECK_PIXELS` pixels of the sensor's middle
    rows) gives φ̂ with its SE; the given φ (its median there) is refused where
    ``|ln(φ / φ̂)|`` exceeds :data:`~emccdcal.defaults.PHI_Z` relative SEs (the SE at
    least :data:`~emccdcal.defaults.PHI_SYSTEMATIC`, φ's own SE included), naming the
    inverse where φ·φ̂ is nearer 1. Without a 1× acquisition it is said, once, that φ
    went unchecked.

    Raises
    ------
    InputError
        One line: both values, the acquisition, and what to do.
    """
    from ..defaults import PHI_CHECK_FRAMES, PHI_CHECK_PIXELS, PHI_SYSTEMATIC, PHI_Z

    unit = next((a for a in used if a.em_gain_setpoint == 1), None)
    if unit is None:
        warnings.warn(
            f"{method}: e_per_adu ({source or 'given'}) could not be checked against "
            "the data (no 1x acquisition): make sure it is in e-/ADU and of this "
            "read-out mode",
            stacklevel=4,
            category=DataQualityWarning,
        )
        return
    rows, cols = unit.offset.shape
    k = max(1, min(rows, PHI_CHECK_PIXELS // cols))
    r0 = (rows - k) // 2
    stop = min(unit.n_frames_total, unit.skip_frames + PHI_CHECK_FRAMES)
    frames = read_band(unit.frames_path, r0, r0 + k, unit.skip_frames, stop)
    band = slice(r0, r0 + k)
    found, rel = mv.photon_transfer_e_per_adu(
        frames, unit.offset[band], unit.read_noise[band], dark_frames=unit.dark_frames
    )
    given = float(nanmedian(phi_map[band]))
    if not math.isfinite(found) or rel > 0.5:
        warnings.warn(
            f"{unit.frames_path}: too little light above the read noise to check "
            f"e_per_adu {given:.4g} ({source or 'given'}) against it",
            stacklevel=4,
            category=DataQualityWarning,
        )
        return
    if phi_se is not None:
        rel = math.hypot(rel, float(nanmedian((phi_se / phi_map)[band])))
    rel = max(rel, PHI_SYSTEMATIC)
    z = math.log(given / found) / rel
    if abs(z) <= PHI_Z:
        return
    inverse = abs(math.log(given * found)) < abs(math.log(given / found))
    hint = (
        f"it looks like ADU/e- (1/{given:.4g} = {1 / given:.4g} e-/ADU): give e-/ADU"
        if inverse
        else "is it in e-/ADU, and of this camera's read-out mode?"
    )
    raise InputError(
        f"{unit.frames_path}: e_per_adu {given:.4g} e-/ADU ({source or 'given'}) is "
        f"{given / found:.3g} times what this 1x acquisition's photon transfer says "
        f"({found:.4g} ± {100 * rel:.2g} %, {abs(z):.0f} SE off); {hint} (--accept-phi "
        "to use it all the same)"
    )
