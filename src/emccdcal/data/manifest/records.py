"""What a manifest resolves to: :class:`Source`, :class:`Acquisition`, :class:`Manifest` (frozen records with units), and the camera settings that identify a read-out state."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import InputWarning
from ..stacks import (
    load_stack,
)


#: The camera settings that identify a camera's read-out state (a calibration holds for
#: that state only), recorded in results as ``attrs["camera"]``.
CAMERA_IDENTITY = ("serial", "model", "amplifier", "readout_rate_mhz", "analog_gain", "adc_bits")


# --------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Source:
    """Where a map or a number came from: a typed record, never text to decode.

    Attributes
    ----------
    kind : {"value", "map", "dark", "result", "given"}
        A number in the manifest, a map file, a dark stack the maps were reduced from, a
        calibration result (φ and its standard error) or a value given by the caller.
    path : Path, optional
        The file of a map, a dark stack or a result.
    value : float, optional
        The number of a ``"value"``.

    Its text (``str``) is what results and messages show: ``"value 3.859"``, the map's
    path, ``"dark <path>"``, ``"result <path>"`` or ``"given"``.
    """

    kind: str
    path: Path | None = None
    value: float | None = None

    def __str__(self) -> str:
        if self.kind == "value":
            return f"value {self.value!r}"
        if self.kind == "map":
            return str(self.path)
        return self.kind if self.path is None else f"{self.kind} {self.path}"


@dataclass(eq=False)
class Acquisition:
    """One stack of raw counts at one EM gain set-point, with its offset and read noise.

    Attributes
    ----------
    name : str
        Label: the manifest's ``name``, else the frames file's stem.
    frames_path : Path
        The stack of raw counts, shape (frames, rows, cols).
    em_gain_setpoint : float
        The camera's EM gain setting (dimensionless, ≥ 1; 1 means no multiplication).
    level : str or None
        Label of the illumination level, if given.
    skip_frames : int
        Frames dropped at the start of the stack.
    offset : ndarray of float64, shape (rows, cols)
        Per-pixel offset S0, ADU.
    read_noise : ndarray of float64, shape (rows, cols)
        Per-pixel read noise σ, ADU (> 0).
    offset_source, read_noise_source : Source
        Where the maps came from: a map file, a dark stack or a number in the manifest.
    n_frames_total : int
        Frames in the file, before ``skip_frames``.
    dark_frames : int or None
        Dark frames behind the offset and read-noise maps: the dark stack's length, or the
        manifest's ``dark_frames``. ``None`` means the maps are taken as exact.
    dark_event_rate : ndarray or None
        Multiplied electrons per pixel per frame (e⁻) in the dark stack of a multiplied
        acquisition, fitted with its maps (:func:`emccdcal.data.dark.fit_dark`); None for
        maps given as files, 1× darks and darks without events.
    dark_telegraph_states : ndarray of int8 or None
        The offset states of each pixel's 1× dark stack: 1 for one normal, 2 to 4 at a
        random-telegraph pixel (4: four or more; :func:`emccdcal.data.telegraph.telegraph_pixels`);
        None without a 1× dark stack tested (a camera with an EM register).
    dark_stuck : ndarray of bool or None
        Pixels whose dark stack's counts never change (dead, or stuck at one value: read
        noise 0, which the fit leaves out); None for maps given as files or values.
    exposure_s, dark_exposure_s : float or None
        The exposure (s) of the frames and of the dark behind the maps (the manifest's
        ``exposure_s`` and ``dark_exposure_s``, which defaults to ``exposure_s``); None
        where not given.
    """

    name: str
    frames_path: Path
    em_gain_setpoint: float
    level: str | None
    skip_frames: int
    offset: np.ndarray = field(repr=False)
    read_noise: np.ndarray = field(repr=False)
    offset_source: Source
    read_noise_source: Source
    n_frames_total: int
    dark_frames: int | None = None
    dark_event_rate: np.ndarray | None = field(default=None, repr=False)
    dark_telegraph_states: np.ndarray | None = field(default=None, repr=False)
    dark_stuck: np.ndarray | None = field(default=None, repr=False)
    exposure_s: float | None = None
    dark_exposure_s: float | None = None

    @property
    def dark_telegraph(self) -> np.ndarray | None:
        """Pixels whose 1× dark stack holds two or more offset states (random-telegraph
        pixels), of bool; None where not tested."""
        states = self.dark_telegraph_states
        return None if states is None else states > 1

    @property
    def n_frames(self) -> int:
        """Frames used: those in the file minus ``skip_frames``."""
        return self.n_frames_total - self.skip_frames

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the frames."""
        rows, cols = self.offset.shape
        return int(rows), int(cols)

    def frames(self) -> np.ndarray:
        """The (n_frames, rows, cols) stack of raw counts (ADU), after ``skip_frames``.

        A read-only memory map where the file allows it (uncompressed TIFF, ``.npy``),
        so nothing is loaded until used; otherwise the file is read on each call. The
        dtype is the file's (possibly non-native byte order).
        """
        return load_stack(self.frames_path)[self.skip_frames :]


@dataclass(eq=False)
class Manifest:
    """A validated manifest: the acquisitions of one calibration and their settings.

    Attributes
    ----------
    path : Path
        The manifest file.
    content_hash : str
        SHA-256 (hex) of the manifest file's bytes.
    e_per_adu : None, float or ndarray of float64 (rows, cols)
        ADU conversion factor φ, e⁻/ADU, if given: a number stays a number, a map file
        gives a map.
    e_per_adu_source : Source or None
        A map file, a number, or a result (φ and its standard error from an ``is-adu`` or
        ``mv-adu`` result, read by the calibration; then ``e_per_adu`` is None), or None
        when ``e_per_adu`` is absent.
    acquisitions : list of Acquisition
        In manifest order.
    shape : tuple of int
        (rows, cols) shared by all stacks and maps.
    adc_max : int
        ADC maximum, ADU: ``2**adc_bits - 1``. Counts at or above it are saturated.
    setpoints : tuple of float
        Sorted distinct EM gain set-points.
    levels : tuple of str
        Distinct illumination levels, in order of first appearance (acquisitions without
        a level are not represented).
    warnings : list of str
        Non-fatal findings (e.g. read noise growing with set-point), also issued with
        :func:`warnings.warn`.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), rows=4, cols=6, frames=200, setpoints=(1, 10), seed=1,
    ...     progress=False,
    ... )
    >>> manifest = emccdcal.read_manifest(sim.manifest)
    >>> manifest.shape, [a.name for a in manifest.acquisitions]
    ((4, 6), ['1x', '10x'])
    """

    path: Path
    content_hash: str
    e_per_adu: None | float | np.ndarray = field(repr=False)
    e_per_adu_source: Source | None
    acquisitions: list[Acquisition]
    shape: tuple[int, int]
    adc_max: int
    setpoints: tuple[float, ...]
    levels: tuple[str, ...]
    warnings: list[str] = field(default_factory=list)
    #: (row, col) of the stacks' first pixel on the sensor: the manifest's ``origin``,
    #: else what the files record (their ROI), else None (unknown).
    origin: tuple[int, int] | None = None
    #: (x, y) binning the files record, or None (not recorded).
    binning: tuple[int, int] | None = None
    #: The EM register's model (``em_model``) and the cascade's ``register_stages`` as
    #: the manifest gives them, or None: not given (the calibration's own default, the
    #: exact cascade with stages from the camera's model or a stated default).
    em_model: str | None = None
    register_stages: int | None = None
    #: The kind of camera (``emccd``, ``scmos``, ``qcmos``, ``ccd``): the manifest's
    #: ``camera_kind``, else None (not said; an EMCCD's calibration is assumed).
    camera_kind: str | None = None
    #: False where every stack is dark (``light = false``, the photon-free path: the dark
    #: signal's growth with exposure is the signal).
    light: bool = True
    #: What every frames file records alike of the camera (``serial``, ``model``,
    #: ``amplifier``, ``readout_rate_mhz``, ``analog_gain``, ``adc_bits``): the identity a calibration
    #: database keys on. A field the files leave out or disagree on is absent.
    camera: dict = field(default_factory=dict)

    def identity(self) -> dict:
        """What the frames record of the camera and read-out state (``camera`` with
        ``binning``), for :func:`emccdcal.identity.check`."""
        return {**self.camera, **({} if self.binning is None else {"binning": self.binning})}

    @property
    def rows_cols(self) -> str:
        """The sensor rows and columns the stacks cover, for messages."""
        if self.origin is None:
            return f"{self.shape[0]} × {self.shape[1]} px at an unknown place on the sensor"
        return _region_text(self.origin, self.shape)


def _origin(r, written, recorded: set, shape):
    """The stacks' sensor origin: the manifest's, else the one the files record."""
    if len(recorded) > 1:
        texts = "; ".join(_region_text(o, shape) for o in sorted(recorded))
        raise r.error(
            f"the stacks record different regions of the sensor ({texts}): a "
            "calibration needs the same pixels in every acquisition"
        )
    if written is not None:
        if recorded and tuple(written) not in recorded:
            warnings.warn(
                f"{r.path}: origin = {list(written)}, but the files record "
                f"{list(next(iter(recorded)))}; the manifest's is used",
                stacklevel=5,
                category=InputWarning,
            )
        return tuple(int(v) for v in written)
    return next(iter(recorded)) if recorded else None


def _binning(r, recorded: set):
    """The stacks' (x, y) binning where the files record one; different ones are an error."""
    if len(recorded) > 1:
        raise r.error(
            f"the stacks record different binnings ({', '.join(map(str, sorted(recorded)))}): "
            "a calibration needs the same pixels in every acquisition"
        )
    return next(iter(recorded)) if recorded else None


def _region_text(origin, shape) -> str:
    (r0, c0), (h, w) = origin, shape
    return f"sensor rows {r0}–{r0 + h - 1}, cols {c0}–{c0 + w - 1}"
