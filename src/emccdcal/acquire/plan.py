"""``emccdcal plan``: what to record to reach a target precision, from the Fisher
information of the exact likelihood.

Every frame of an acquisition carries a known amount of information about the
parameters the calibration estimates: the expected outer product of its scores
(:meth:`emccdcal.fit.series.SeriesLikelihood.expected_information`), the same scores the fit uses. N
frames carry N times as much, so the standard error a calibration will report is known
before a frame is recorded, for any number of frames at each set-point or level:

    cov = H⁻¹ + Σ_stacks S V Sᵀ,   H = Σ_a N_a I_a,   S = H⁻¹ Σ_a N_a C_a,

``I_a`` the information of one frame of acquisition ``a``, ``C_a`` its cross information
with the offset and read-noise maps, and ``V = diag(σ²/N_dark, σ²/(2(N_dark − 1)))`` the
variances of maps made from ``N_dark`` dark frames (what the fit adds for them). No
number of light frames averages the offset map's error away, so the planner chooses the
dark frames too.

The plan is the least total of frames (light and dark) that brings every targeted
relative standard error to the target: frames are added where they buy the most
precision per frame (a greedy allocation over the acquisitions and the darks, then
trimmed), for the light levels of a grid from the brightest down, and the cheapest level wins. The light is kept
clear of the ADC's range: the brightest acquisition's mean plus :data:`ADC_MARGIN_SD`
standard deviations stays below :data:`ADC_FILL` of the range (and below the register's
pixel's and the register's full wells where they are given).

Examples
--------
>>> from emccdcal.acquire.plan import plan
>>> p = plan(method="gs", e_per_adu=3.859, read_noise=15.5, offset=587.7, adc_bits=16,
...          setpoints=[1, 5, 25, 100, 300], target_se=0.5)
>>> p.reached and p.total_frames < 5 * 5000
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import _roots, _xp, defaults
from .._util import check_int, check_number
from ..errors import OptionError
from ..fit.series import SeriesLikelihood, acquisition_models, choose_register
from ..model import adc, noise

__all__ = [
    "Plan",
    "Acquisition",
    "plan",
    "predict",
    "camera_of",
    "PLAN_METHODS",
    "ADC_FILL",
    "ADC_MARGIN_SD",
]

#: The methods a plan is made for.
PLAN_METHODS = defaults.PLAN_METHODS
#: The brightest acquisition's mean plus this many SDs ...
ADC_MARGIN_SD = 6.0
#: ... stays below this fraction of the ADC's range (and of the full wells given).
ADC_FILL = 0.9
#: Light levels tried for a gain series, as fractions of the brightest the ADC allows.
_GS_FRACTIONS = np.geomspace(0.05, 1.0, 10)
#: Levels of an intensity series, as fractions of the brightest (the paper's doubling).
_IS_FRACTIONS = 2.0 ** -np.arange(6)[::-1]
#: Frames a stack starts with, and the least a plan asks for.
_FIRST_FRAMES = 50


@dataclass(frozen=True)
class Acquisition:
    """One stack of a plan.

    Attributes
    ----------
    setpoint : float
        EM gain set-point (1: no multiplication).
    photoelectrons : float
        Light, e⁻ per pixel per frame (at the sensor, before multiplication).
    frames : int
        Frames to record.
    em_gain : float
        The true gain the plan assumed (the set-point unless told), dimensionless.
    predicted_se : dict
        Predicted relative standard error per pixel, percent, of each estimate of this
        stack: ``em_gain`` (gain series, is-gain) and ``photoelectrons``.
    """

    setpoint: float
    photoelectrons: float
    frames: int
    em_gain: float
    predicted_se: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Plan:
    """A planned calibration: the stacks to record and the precision they will give.

    Attributes
    ----------
    method : str
        ``gs``, ``is-adu`` or ``is-gain``.
    acquisitions : tuple of Acquisition
        Light stacks (a gain series: one per set-point; an intensity series: one per
        level).
    dark_frames : int
        Dark frames per dark stack: one per set-point (gain series) or one for the
        series (intensity series).
    target_se : float
        The target, percent (relative SE per pixel of each em_gain; of e_per_adu for
        is-adu).
    predicted_se : float
        The worst predicted relative SE of a targeted estimate, percent.
    reached : bool
        Whether ``predicted_se`` meets the target within ``max_frames``.
    camera : dict
        What the plan assumed: e_per_adu (e⁻/ADU), read_noise (ADU), offset (ADU),
        adc_bits, em_model, stages, pixel_well and register_well (e⁻ or None).
    frame_rate_hz : float or None
        Frames per second, for the time.
    max_frames : int or None
        Most frames of one stack.
    """

    method: str
    acquisitions: tuple
    dark_frames: int
    target_se: float
    predicted_se: float
    reached: bool
    camera: dict
    frame_rate_hz: float | None = None
    max_frames: int | None = None

    @property
    def em_model(self) -> noise.EMModel:
        """The register model the plan assumed (its camera's ``em_model`` and ``stages``)."""
        return _camera_model(self.camera)

    @property
    def read_noise_variance_se(self) -> float:
        """Predicted relative SE of each pixel's read-noise variance σ² from the dark
        frames, percent (:func:`read_noise_variance_se`)."""
        return read_noise_variance_se(self.camera["read_noise"], self.dark_frames)

    @property
    def dark_stacks(self) -> int:
        return len(self.acquisitions) if self.method == "gs" else 1

    @property
    def total_frames(self) -> int:
        """Light and dark frames together."""
        return sum(a.frames for a in self.acquisitions) + self.dark_stacks * self.dark_frames

    @property
    def seconds(self) -> float | None:
        """Recording time at the frame rate, s (None without one)."""
        return None if not self.frame_rate_hz else self.total_frames / self.frame_rate_hz

    @property
    def photoelectrons(self) -> float:
        """The light of a gain series (shared by its set-points), e⁻ per pixel per frame."""
        return self.acquisitions[0].photoelectrons


def _camera_model(camera: dict) -> noise.EMModel:
    """The register model of a plan's camera (its ``em_model`` name and ``stages``): the
    one place a plan's text becomes a model."""
    return choose_register(camera["em_model"], camera["stages"])[0]


def _nice(n: float) -> int:
    """``n`` rounded up to two significant figures (3721 → 3800), at least the least
    a plan asks for."""
    n = max(float(n), _FIRST_FRAMES)
    step = 10 ** max(0, int(math.floor(math.log10(n))) - 1)
    return int(math.ceil(n / step - 1e-9) * step)


class _Design:
    """The per-frame information of a set of acquisitions, for P candidate light
    levels at once (the engine's pixels), and the covariance of any allocation."""

    def __init__(self, method, setpoints, gains, photoelectrons, camera, model):
        # photoelectrons: (P, A) light of each acquisition per candidate
        self.method, self.camera = method, camera
        self.setpoints, self.gains, self.light = list(setpoints), list(gains), photoelectrons
        P, A = photoelectrons.shape
        phi, sigma, s0 = camera["e_per_adu"], camera["read_noise"], camera["offset"]
        models = acquisition_models(setpoints, [np.full(P, s0)] * A, [np.full(P, sigma)] * A, model)
        self.likelihood = SeriesLikelihood(method, models, e_per_adu=phi)
        x = self.likelihood.point(
            {
                "photoelectrons": photoelectrons,
                "em_gain": np.asarray(gains, float),
                "e_per_adu": phi,
            }
        )
        self.info, self.cross = self.likelihood.expected_information(x)
        self.sigma2 = sigma**2
        # parameters each acquisition informs (an empty level's E is not estimated)
        self.informs = self.likelihood.informs  # (A, F)

    def covariance(self, frames, dark, level=None):
        """Covariance of the free parameters (C, P, F, F) for allocations ``frames``
        (C, A) and dark frames ``dark`` (C,); NaN rows for parameters no frame informs.
        With ``level``, of that candidate light only (P = 1)."""
        info, crosses = self.info, self.cross
        if level is not None:
            info, crosses = info[level : level + 1], crosses[level : level + 1]
        H = np.einsum("ca,paij->cpij", frames, info)
        F = H.shape[-1]
        active = (frames[:, :, None] > 0) & self.informs[None]  # (C, A, F)
        live = active.any(axis=1)  # (C, F)
        eye = np.eye(F)
        # an uninformed parameter gets unit information and is reported as NaN
        H = H + (~live)[:, None, :, None] * eye
        cov0 = np.linalg.inv(H)
        v = np.stack([self.sigma2 / dark, self.sigma2 / (2.0 * np.maximum(dark - 1, 1))], -1)
        weighted = np.einsum("ca,pafm->cpafm", frames, crosses)
        if self.method == "gs":  # one dark stack per set-point
            sens = np.einsum("cpfg,cpagm->cpafm", cov0, weighted)
            maps = np.einsum("cpafm,cm,cpagm->cpfg", sens, v, sens)
        else:  # one dark stack for the series: its errors move every level together
            sens = np.einsum("cpfg,cpgm->cpfm", cov0, weighted.sum(axis=2))
            maps = np.einsum("cpfm,cm,cpgm->cpfg", sens, v, sens)
        cov = cov0 + maps
        cov = np.where((live[:, None, :, None] & live[:, None, None, :]), cov, np.nan)
        return cov


def _targets(design):
    """Indices of the parameters a plan's target is on."""
    key = "e_per_adu" if design.method == "is-adu" else "em_gain"
    return [j for j, p in enumerate(design.likelihood.parameters) if p.quantity == key]


def _relative_se(cov, idx):
    """Relative SEs (percent) of log-parameters ``idx``: 100·SD of ln θ."""
    return 100.0 * np.sqrt(np.stack([cov[..., j, j] for j in idx], -1))


def _allocate(design, p, targets, target, max_frames, dark_cost, floor=None, allowed=None):
    """Greedy allocation for candidate light ``p``: frames (A,), dark (int), worst SE.
    ``floor`` (A + 1,): the least frames of each stack, then of the darks (by default of
    every stack of a gain series, of an intensity series' brightest level, and
    _FIRST_FRAMES darks); ``allowed`` (A,): the stacks that may have frames at all (by
    default every one)."""
    A = design.info.shape[1]
    if floor is None:
        floor = np.full(A + 1, float(_FIRST_FRAMES))
        if design.method != "gs":  # an intensity series starts at its brightest level
            floor[: A - 1] = 0.0
    state = np.asarray(floor, dtype=float)  # light frames of each stack, then darks
    floor = state.copy()
    cost = np.r_[np.ones(A), dark_cost]
    cap = np.full(A + 1, np.inf if max_frames is None else float(max_frames))
    if allowed is not None:
        cap[:A] = np.where(allowed, cap[:A], 0.0)

    def worst(states):
        cov = design.covariance(states[:, :A], states[:, A], level=p)[:, 0]
        se = _relative_se(cov, targets)
        return np.nanmax(np.where(np.isnan(se), np.inf, se), axis=1), se

    def excess(se):
        return np.sum(np.maximum((se / target) ** 2 - 1.0, 0.0), axis=-1)

    now, se = worst(state[None])
    for _ in range(2000):
        if now[0] <= target:
            break
        steps = np.maximum(_FIRST_FRAMES, np.ceil(0.2 * state))
        trial = state[None] + np.diag(np.minimum(steps, cap - state))
        moved = trial.sum(axis=1) > state.sum()
        if not moved.any():
            break
        w, s = worst(trial)
        e0 = excess(np.nan_to_num(se, nan=1e9))[0]
        gain_per_frame = (e0 - excess(np.nan_to_num(s, nan=1e9))) / (
            np.maximum((trial - state[None]) @ cost, 1e-9)
        )
        gain_per_frame[~moved] = -np.inf
        pick = int(np.argmax(gain_per_frame))
        state, now, se = trial[pick], w[pick : pick + 1], s[pick : pick + 1]
    # Trim: take back frames the greedy steps overshot, largest saving first.
    for _ in range(200):
        if now[0] > target:
            break
        cut = np.floor(0.05 * state)
        trial = state[None] - np.diag(cut)
        ok_cut = (cut > 0) & (np.diag(trial) >= floor)
        w, s = worst(trial)
        ok = ok_cut & (w <= target)
        if not ok.any():
            break
        pick = int(np.argmax(np.where(ok, cut * cost, -1)))
        state, now, se = trial[pick], w[pick : pick + 1], s[pick : pick + 1]
    return state[:A], state[A], float(now[0])


def _offset_within_adc(camera) -> None:
    """An offset at or past the ADC's last count leaves no room for any light."""
    top = 2 ** camera["adc_bits"] - 1
    if camera["offset"] >= top:
        raise OptionError(
            f"offset {camera['offset']:g} ADU is at or past the ADC's last count "
            f"{top} ({camera['adc_bits']} bits): is it in ADU, and the bits "
            "the camera's?"
        )


def _within_adc(setpoints, gains, light, camera) -> None:
    """Refuse light whose mean count is past the ADC's last count: such frames saturate,
    and no prediction of their precision means anything."""
    top = 2 ** camera["adc_bits"] - 1
    for s, g, E in zip(setpoints, gains, light):
        mean = camera["offset"] + E * g / camera["e_per_adu"]
        if mean > top:
            raise OptionError(
                f"{E:g} e- per pixel per frame at set-point {s:g} (gain {g:g}) is a mean "
                f"count of {mean:.4g} ADU, past the ADC's {top} ({camera['adc_bits']} bits): "
                "those frames saturate; less light"
            )


def _brightest(setpoint_gain, camera, model) -> float:
    """The most light (e⁻ per pixel per frame) whose mean plus ADC_MARGIN_SD SDs, at
    gain ``setpoint_gain``, stays below ADC_FILL of the ADC range and of the full wells:
    the pixel's holds the light E, the register's the multiplied charge E·g."""
    phi, sigma, s0 = camera["e_per_adu"], camera["read_noise"], camera["offset"]
    top = ADC_FILL * (2 ** camera["adc_bits"] - 1)
    f2 = float(noise.excess_noise_factor(setpoint_gain, em_model=model))
    pixel_well, register_well = camera.get("pixel_well"), camera.get("register_well")

    def fits(E):
        sd_adu = math.sqrt(f2 * E * setpoint_gain**2 / phi**2 + sigma**2)
        ok = s0 + E * setpoint_gain / phi + ADC_MARGIN_SD * sd_adu <= top
        if pixel_well:
            ok = ok and E + ADC_MARGIN_SD * math.sqrt(E) <= ADC_FILL * pixel_well
        if register_well:
            sd_e = math.sqrt(f2 * E) * setpoint_gain
            ok = ok and E * setpoint_gain + ADC_MARGIN_SD * sd_e <= ADC_FILL * register_well
        return ok

    if not fits(1.0):
        raise OptionError(
            f"even 1 e- per pixel per frame at gain {setpoint_gain:g} leaves the ADC's "
            f"range ({camera['adc_bits']} bits, offset {s0:g} ADU, {phi:g} e-/ADU) or a "
            "full well given: leave out the highest set-point"
        )
    lo, hi = 1.0, 2.0
    while fits(hi):
        lo, hi = hi, hi * 2.0
    return _roots.bisect(lambda x: not fits(x), lo, hi, 60, geometric=True)[0]


#: Read noise (e⁻) below which a 1× count's photon numbers show (the comb's revival
#: exp(−2π²(σφ)²) above 0.7 %: docs/cmos.md).
COMB_SHOWS_BELOW_E = 0.5
#: Where they show, the levels are a ladder: from LADDER_FIRST_E e⁻ up, each
#: LADDER_RATIO times the last, ...
LADDER_FIRST_E = 0.5
LADDER_RATIO = 3.0
#: ... each rung holding the frames that put φ within 1/(LADDER_Z · E) of itself
#: (relative) before the next rung of E e⁻, whose ripples are 1/E apart: the fit climbs
#: from the dimmest level's basins (emccdcal.fit.comb) and stays on the true ripple.
LADDER_Z = 3.0
#: The least frames of a rung, rungs of a ladder and dark frames: fewer, and the fit's
#: errors exceed the likelihood's curvature (a simulated qCMOS, 0.27 e⁻, docs/cmos.md:
#: at 50 frames a rung they were 4–8 times the prediction, at 100 the intervals covered
#: 0.915; with 50 darks, or a ladder ending at 4.5 e⁻, some pixels ended on an alias of
#: φ, z up to 22; at 200 frames, 400 darks and four rungs 0.948, RMS z 1.01, |z| ≤ 3.7).
LADDER_FRAMES = 200
LADDER_RUNGS = 4
LADDER_DARKS = 400


def _ladder(top) -> np.ndarray:
    """The rungs (e⁻ per pixel per frame) of a resolved comb's intensity series, up to
    the brightest light ``top`` the ADC holds."""
    n = max(int(math.floor(math.log(top / LADDER_FIRST_E) / math.log(LADDER_RATIO))), 0) + 1
    return LADDER_FIRST_E * LADDER_RATIO ** np.arange(n)


def _ladder_floors(design, targets):
    """The least frames (A + 1,) of each height of a resolved comb's ladder, lowest
    first from :data:`LADDER_RUNGS` rungs: every rung up to the top at least
    :data:`LADDER_FRAMES`, those below it the frames that put φ within its next rung's
    ripples (:data:`LADDER_Z`), the rungs above none; :data:`LADDER_DARKS` darks."""
    rungs = design.light[0]
    A = rungs.size
    # φ's relative SE from one frame of each rung alone (its darks many)
    se = _relative_se(design.covariance(100.0 * np.eye(A), np.full(A, 1e6), level=0)[:, 0],
                      targets)  # fmt: skip
    one_frame = np.nanmax(se, axis=1) / 100.0 * 10.0
    needs = np.maximum(np.ceil((LADDER_Z * rungs[1:] * one_frame[:-1]) ** 2), LADDER_FRAMES)
    for height in range(min(LADDER_RUNGS, A), A + 1):
        yield np.r_[needs[: height - 1], LADDER_FRAMES, np.zeros(A - height), LADDER_DARKS]


def _cheapest(allocations, target, dark_cost):
    """The cheapest of ``(p, frames, dark, worst SE)`` allocations, tried in order until
    the cost has risen twice in a row: ``(p, frames, dark)``."""
    best, rises = None, 0
    for p, frames, dark, worst in allocations:
        total = frames.sum() + dark_cost * dark
        key = (worst > target, total if worst <= target else worst)
        if best is None or key < best[0]:
            best, rises = (key, p, frames, dark), 0
        else:
            rises += 1
            if rises == 2:
                break
    return best[1:]


def check_camera_kind(kind, method) -> None:
    """A plan's ``camera_kind``: one of :data:`emccdcal.defaults.CAMERA_KINDS`, and for a
    camera without an EM register an intensity series at 1× (``is-adu``)."""
    if kind is None:
        return
    if kind not in defaults.CAMERA_KINDS:
        raise OptionError(
            f"camera_kind must be one of {', '.join(defaults.CAMERA_KINDS)}; got {kind!r}"
        )
    if kind in defaults.WITHOUT_EM_REGISTER and method != "is-adu":
        raise OptionError(
            f"a camera_kind = {kind!r} has no EM register: its plan is an intensity series "
            "at 1x (method is-adu)"
        )


def plan(
    *,
    method="gs",
    e_per_adu,
    read_noise,
    offset,
    adc_bits=16,
    setpoints=(1, 5, 25, 100, 300),
    em_gain=None,
    setpoint=None,
    target_se=0.5,
    em_model=defaults.DEFAULT_EM_MODEL,
    stages=None,
    pixel_well=None,
    register_well=None,
    max_frames=None,
    frame_rate_hz=None,
    device=None,
    read_noise_target_se=None,
    camera_kind=None,
) -> Plan:
    """The acquisition that reaches ``target_se`` with the fewest frames.

    Parameters
    ----------
    method : {"gs", "is-adu", "is-gain"}
        A gain series (one light, a stack per set-point, φ known), or an intensity series
        (several lights at one set-point: 1× for ``is-adu``, ``setpoint`` for
        ``is-gain``).
    e_per_adu : float
        Roughly the camera's ADU conversion factor, e⁻/ADU (the data sheet's, or a
        previous result's).
    read_noise, offset : float
        Read noise and offset, ADU.
    adc_bits : int
        ADC bit depth, bits.
    setpoints : sequence of float
        The set-points of a gain series (1× included: it anchors the light).
    em_gain : sequence of float or float, optional
        The true gains assumed at the set-points (default: the set-points), or at
        ``setpoint`` for is-gain.
    setpoint : float, optional
        The set-point of an is-gain series (default: the highest of ``setpoints``).
    target_se : float
        Relative standard error per pixel, percent: of every em_gain (gs, is-gain) or of
        e_per_adu (is-adu).
    em_model, stages : optional
        The register model (default the exact cascade of 536 stages).
    pixel_well, register_well : float, optional
        Full wells, e⁻ (a data sheet's): the light E is kept below the pixel's, the
        multiplied charge E·g below the register's.
    max_frames : int, optional
        Most frames of one stack (light or dark).
    frame_rate_hz : float, optional
        For the recording time.
    device : {"cpu", "cuda", "jax", "array-api-strict"}, optional
        Where the expected information's windows are computed, as
        :func:`emccdcal.calibrate`'s.
    read_noise_target_se : float, optional
        Relative SE per pixel of the read-noise variance σ² from the darks, percent: the
        dark frames are at least :func:`darks_for_read_noise` (a localization tool's
        variance map; Huang et al. 2013 record ~20 000 darks or more: 1 % at σ ≥ 2 ADU).
    camera_kind : {"emccd", "scmos", "qcmos", "ccd"}, optional
        The kind of camera, recorded in the plan (``acquire --simulated`` records from a
        simulated camera of that kind); one without an EM register is planned as an
        intensity series at 1× (``is-adu``).

    Returns
    -------
    Plan

    Raises
    ------
    OptionError
        A parameter out of range, or a camera whose ADC cannot hold one photoelectron at
        the highest set-point.

    Examples
    --------
    >>> import emccdcal
    >>> p = emccdcal.plan(e_per_adu=3.9, read_noise=15.5, offset=590, target_se=2)
    >>> p.reached, p.predicted_se <= 2
    (True, True)
    >>> p.acquisitions[0].setpoint  # 1x first: it anchors the light
    1.0
    """
    if method not in PLAN_METHODS:
        raise OptionError(f"a plan is for one of {', '.join(PLAN_METHODS)}; got {method!r}")
    check_camera_kind(camera_kind, method)
    camera = {
        "e_per_adu": check_number("e_per_adu", e_per_adu, positive=True),
        "read_noise": check_number("read_noise", read_noise, positive=True),
        "offset": check_number("offset", offset, minimum=0.0),
        "adc_bits": check_int("adc_bits", adc_bits, minimum=2, maximum=32),
        "pixel_well": None
        if pixel_well is None
        else check_number("pixel_well", pixel_well, positive=True),
        "register_well": None
        if register_well is None
        else check_number("register_well", register_well, positive=True),
    }
    _offset_within_adc(camera)
    camera["camera_kind"] = camera_kind
    # photon numbers resolved: φ's information is the comb's, which only a ladder of
    # levels delivers (the fit's error elsewhere is the envelope's, docs/cmos.md)
    comb = method == "is-adu" and camera["e_per_adu"] * camera["read_noise"] < COMB_SHOWS_BELOW_E
    target = check_number("target_se", target_se, positive=True)
    if max_frames is not None:
        max_frames = check_int("max_frames", max_frames, minimum=_FIRST_FRAMES)
    if frame_rate_hz is not None:
        frame_rate_hz = check_number("frame_rate", frame_rate_hz, positive=True)
    model = choose_register(em_model, stages)[0]
    _xp.resolve(device)  # an unknown or missing device: one line before any work
    camera |= {
        "em_model": model.name,
        "stages": model.stages if model.register.uses_stages else None,
    }
    sps = sorted({check_number("setpoints", s, minimum=1.0) for s in np.atleast_1d(setpoints)})

    if method == "gs":
        if 1.0 not in sps or len(sps) < 2:
            raise OptionError(
                "a gain series needs 1x (it anchors the light) and at least "
                f"one set-point above it; got {', '.join(f'{s:g}' for s in sps)}"
            )
        gains = _assumed(em_gain, sps)
        top = _brightest(max(gains), camera, model)
        light = top * _GS_FRACTIONS[:, None] * np.ones(len(sps))
        lab_setpoints = sps
    else:
        s = (
            1.0
            if method == "is-adu"
            else check_number(
                "setpoint", setpoint if setpoint is not None else max(sps), minimum=1.0
            )
        )
        if method == "is-gain" and s == 1:
            raise OptionError(
                "is-gain is an intensity series at a set-point above 1x: give --setpoint G"
            )
        (g,) = _assumed(em_gain, [s])
        top = _brightest(g, camera, model)
        light = (_ladder(top) if comb else top * _IS_FRACTIONS)[None, :]
        gains, lab_setpoints = [g] * light.shape[1], [s] * light.shape[1]
    with _xp.computing_on(device):
        design = _Design(method, lab_setpoints, gains, light, camera, model)
    targets = _targets(design)
    dark_cost = len(sps) if method == "gs" else 1
    if comb:  # the ladder's heights, lowest first
        tries = (
            (0, *_allocate(design, 0, targets, target, max_frames, 1, floor, floor[:-1] > 0))
            for floor in _ladder_floors(design, targets)
        )
    else:  # from the brightest light down: the cost falls with the light per frame
        # wherever the ADC is not in the way
        tries = (
            (p, *_allocate(design, p, targets, target, max_frames, dark_cost))
            for p in range(light.shape[0] - 1, -1, -1)
        )
    p, frames, dark = _cheapest(tries, target, dark_cost)
    frames = np.array([_nice(n) if n > 0 else 0 for n in frames])
    if read_noise_target_se is not None:
        needed = darks_for_read_noise(
            camera["read_noise"],
            check_number("read_noise_target_se", read_noise_target_se, positive=True),
        )
        dark = max(dark, needed)
    dark = _nice(dark)
    if max_frames is not None:
        frames, dark = np.minimum(frames, max_frames), min(dark, max_frames)
    return _plan_of(design, p, frames, dark, target, frame_rate_hz, max_frames)


def camera_of(result) -> dict:
    """What a plan needs to know of a camera, from an earlier calibration of it: the
    medians over pixels of φ (e⁻/ADU) and, at 1× where it has darks (else at its lowest
    set-point with darks), of the offset and read noise (ADU).

    Parameters
    ----------
    result : str, Path or Calibration
        A result (or a group, as :func:`~emccdcal.result.load_calibration` reads).

    Returns
    -------
    dict
        ``e_per_adu``, ``offset``, ``read_noise``.
    """
    from ..result import load_calibration, pixel_statistics

    cal = load_calibration(result)
    offset, sigma = cal.dark(1.0 if 1.0 in cal.offset or not cal.offset else min(cal.offset))
    return {
        name: pixel_statistics(values)["median"]
        for name, values in (
            ("e_per_adu", cal.e_per_adu),
            ("offset", offset),
            ("read_noise", sigma),
        )
    }


def _assumed(em_gain, setpoints):
    if em_gain is None:
        return [float(s) for s in setpoints]
    values = list(np.atleast_1d(em_gain))
    if len(values) != len(setpoints):
        raise OptionError(f"--em-gain has {len(values)} value(s) for {len(setpoints)} set-point(s)")
    return [
        1.0 if s == 1 else check_number("em_gain", g, minimum=1.0)
        for s, g in zip(setpoints, values)
    ]


def predict(
    method,
    setpoints,
    gains,
    photoelectrons,
    frames,
    dark_frames,
    camera,
    target_se=float("nan"),
    *,
    frame_rate_hz=None,
    max_frames=None,
) -> Plan:
    """The precision a given acquisition will reach: the :class:`Plan` of exactly these
    stacks (what :func:`plan` returns for its choice, and what a hand-edited plan is
    checked with).

    Parameters
    ----------
    method : str
    setpoints, gains, photoelectrons, frames : sequence
        Per light stack: set-point, assumed true gain, light (e⁻/px/frame), frames.
    dark_frames : int
        Per dark stack.
    camera : dict
        e_per_adu, read_noise, offset, adc_bits, em_model, stages (as :attr:`Plan.camera`).
    """
    model = _camera_model(camera)
    light = np.asarray(photoelectrons, float)[None, :]
    design = _Design(method, setpoints, gains, light, camera, model)
    return _plan_of(
        design, 0, np.asarray(frames, float), dark_frames, target_se, frame_rate_hz, max_frames
    )


def dark_limited(p: Plan) -> float | None:
    """Whether the dark frames, not the light frames, keep ``p`` from its target: the
    worst SE (percent) it would reach with exact offset and read-noise maps where that
    reaches the target and ten times the light frames would not; else None."""
    a = p.acquisitions

    def worst(light_factor, darks):
        return predict(
            p.method,
            [x.setpoint for x in a],
            [x.em_gain for x in a],
            [x.photoelectrons for x in a],
            [light_factor * x.frames for x in a],
            darks,
            p.camera,
        ).predicted_se

    exact = worst(1, 10**9)
    if exact <= p.target_se and worst(10, p.dark_frames) > p.target_se:
        return exact
    return None


def read_noise_variance_se(read_noise, dark_frames) -> float:
    """The relative SE (percent) of a pixel's read-noise variance σ² (ADU²) from
    ``dark_frames`` dark frames at 1×: sqrt(2/(n − 1)) of a normal's sample variance;
    below :data:`emccdcal.model.adc.ROUNDING_BELOW` the rounded normal's maximum
    likelihood (its Fisher information, the worst over where the offset falls between
    two integers), 2·SE(σ)/σ.

    >>> round(read_noise_variance_se(15.5, 20001), 3)     # Huang et al.'s 20 000 darks
    1.0
    """
    n = max(int(dark_frames), 2)
    if not adc.rounds(True, read_noise):
        return 100.0 * math.sqrt(2.0 / (n - 1))
    return 100.0 * _rounded_variance_se_per_frame(read_noise) / math.sqrt(n)


def _rounded_variance_se_per_frame(read_noise) -> float:
    """√n times the relative SE of a rounded normal's σ² fitted to n counts."""
    sigma = np.full(3, float(read_noise))
    var = np.linalg.inv(adc.information(np.array([0.0, 0.25, 0.5]), sigma))[:, 1, 1].max()
    return 2.0 * math.sqrt(var) / float(read_noise)


def darks_for_read_noise(read_noise, target_se) -> int:
    """The fewest dark frames whose read-noise variance reaches ``target_se`` percent
    (:func:`read_noise_variance_se`)."""
    t = float(target_se) / 100.0
    if not adc.rounds(True, read_noise):
        return int(math.ceil(2.0 / t**2 + 1.0))
    return int(math.ceil((_rounded_variance_se_per_frame(read_noise) / t) ** 2))


def _plan_of(design, level, frames, dark_frames, target_se, frame_rate_hz, max_frames):
    """The :class:`Plan` of ``frames`` (A,) at the design's candidate light ``level``;
    stacks of no frames are left out."""
    cov = design.covariance(
        np.asarray(frames, float)[None], np.array([float(dark_frames)]), level=level
    )[0, 0]
    lik = design.likelihood
    acqs = []
    for a, (s, g, E, n) in enumerate(
        zip(design.setpoints, design.gains, design.light[level], frames)
    ):
        if n <= 0:
            continue
        mine = {}
        for quantity in ("em_gain", "photoelectrons", "e_per_adu"):
            j = lik.index(quantity, a)
            # a gain is a multiplied stack's; a shared E is reported with the 1× stack
            if (
                j is None
                or (quantity == "em_gain" and s == 1)
                or (
                    quantity == "photoelectrons"
                    and lik.parameters[j].acquisition is None
                    and s != 1
                )
            ):
                continue
            mine[quantity] = float(100.0 * math.sqrt(cov[j, j]))
        acqs.append(Acquisition(float(s), float(E), int(n), float(g), mine))
    worst = float(np.max(_relative_se(cov, _targets(design))))
    return Plan(
        design.method,
        tuple(acqs),
        int(dark_frames),
        float(target_se),
        worst,
        bool(worst <= target_se * (1 + 1e-9)),
        dict(design.camera),
        frame_rate_hz,
        max_frames,
    )
