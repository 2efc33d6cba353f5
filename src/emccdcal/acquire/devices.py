"""A simulated EMCCD, sCMOS and qCMOS for Micro-Manager: a camera and a shutter made with
pymmcore-plus's Python device API (``pymmcore_plus.experimental.unicore``), whose frames
come from the project's simulators (:func:`emccdcal.simulate.camera.simulate_frames`,
:func:`emccdcal.simulate.cmos.simulate_cmos_frames`).

The camera has a settable EM gain (the standard ``EMGain`` property), a lamp
(``Light``: photoelectrons per pixel per frame while the shutter is open), a region of
interest, and a known truth: its φ, read noise, register and true gain at every
set-point (the paper's gains at 5/25/100/300×, else the set-point), an offset that falls
with the set-point plus a fixed per-pixel pattern. ``emccdcal acquire --simulated``
records from it exactly as from a real camera, and writes that truth beside the files.

Needs the ``acquire`` extra (pymmcore-plus).
"""

from __future__ import annotations

import threading

import numpy as np
from pymmcore_plus.experimental.unicore import CameraDevice, ShutterDevice, pymm_property

from ..simulate.camera import Camera, default_em_gain, offset_at_setpoint, simulate_frames
from ..simulate.cmos import simulate_cmos_frames

__all__ = ["SimulatedShutter", "SimulatedEMCCD", "SimulatedCMOS", "SENSOR_SHAPE"]

#: The simulated sensor, rows × cols, px.
SENSOR_SHAPE = (64, 64)
#: Values drawn per batch of frames (bounds the memory of a sequence).
_BATCH_VALUES = 1 << 20
#: The largest set-point the simulated camera takes.
_MAX_SETPOINT = 1000.0


class SimulatedShutter(ShutterDevice):
    """A shutter in front of the simulated camera's lamp."""

    def __init__(self) -> None:
        super().__init__()
        self._open = False

    def get_open(self) -> bool:
        return self._open

    def set_open(self, open: bool) -> None:  # noqa: A002 - the device API's name
        self._open = bool(open)


class SimulatedEMCCD(CameraDevice):
    """An EMCCD whose frames are drawn by the project's simulator.

    Parameters
    ----------
    camera : Camera
        φ (e⁻/ADU), read noise (ADU), offset at 1× and its drop per decade (ADU), offset
        pattern SD (ADU), register model and stages, ADC bits; its ``rows``/``cols`` are
        the sensor's.
    shutter : SimulatedShutter
        The shutter whose state decides whether the lamp reaches the sensor.
    seed : int
        Seed of the camera's truth (its offset pattern) and of its frames.
    run : int
        Which recording this is (0 first, 1 after a first resume, …): the frames of each
        run are independent draws of the same camera.
    """

    def __init__(self, camera: Camera, shutter: SimulatedShutter, *, seed: int, run: int = 0):
        super().__init__()
        self.camera, self.shutter, self.seed = camera, shutter, int(seed)
        truth_seed, frame_seed = np.random.SeedSequence(self.seed).spawn(2)
        self._draw_truth(np.random.default_rng(truth_seed))
        self._frame_seeds = np.random.SeedSequence(
            frame_seed.entropy, spawn_key=(*frame_seed.spawn_key, run)
        )
        self._exposure_ms, self._setpoint, self._light = 10.0, 1.0, 0.0
        self._roi: tuple[int, int, int, int] | None = None
        self.sequence_thread: threading.Thread | None = None

    # ---- the truth -------------------------------------------------------------------
    def _draw_truth(self, rng) -> None:
        """The camera's fixed truth, drawn once from its seed: the offset pattern (ADU)."""
        self.offset_pattern = rng.normal(0.0, self.camera.offset_spread, self.camera.shape)

    @staticmethod
    def true_em_gain(setpoint: float) -> float:
        """The camera's true mean EM gain at a set-point (dimensionless)."""
        return default_em_gain(setpoint)

    def offset_of(self, setpoint: float) -> float:
        """The offset at a set-point, ADU, before the per-pixel pattern."""
        return offset_at_setpoint(setpoint, self.camera.offset, self.camera.offset_drop)

    # ---- the device API ----------------------------------------------------------------
    def get_exposure(self) -> float:
        return self._exposure_ms

    def set_exposure(self, exposure: float) -> None:
        self._exposure_ms = float(exposure)

    def get_em_gain(self) -> float:
        return self._setpoint

    def set_em_gain(self, value: float) -> None:
        value = float(value)
        if not 1.0 <= value <= _MAX_SETPOINT:
            raise ValueError(f"EM gain set-point {value:g} outside 1-{_MAX_SETPOINT:g}")
        self._setpoint = value

    def get_ccd_temperature(self) -> float:
        return -70.0

    def wait_until_stopped(self, timeout: float = 120.0) -> None:
        """Wait for the acquisition thread of the last sequence to end (after it was told
        to stop): a thread still drawing frames when the process exits aborts it."""
        thread = self.sequence_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)

    def get_camera_name(self) -> str:
        return "emccdcal simulated EMCCD"

    def get_camera_id(self) -> str:
        return f"SIM-{self.seed}"

    def get_readout_mode(self) -> str:
        return "10 MHz"

    @pymm_property(limits=(0.0, 1e6), name="Light")
    def light(self) -> float:
        """The lamp: photoelectrons per pixel per frame while the shutter is open."""
        return self._light

    @light.setter
    def light(self, value: float) -> None:
        self._light = float(value)

    def shape(self) -> tuple[int, int]:
        if self._roi is not None:
            return (self._roi[3], self._roi[2])
        return self.camera.shape

    def dtype(self):
        return np.uint16

    def get_roi(self) -> tuple[int, int, int, int]:
        if self._roi is not None:
            return self._roi
        rows, cols = self.camera.shape
        return (0, 0, cols, rows)

    def set_roi(self, x: int, y: int, width: int, height: int) -> None:
        rows, cols = self.camera.shape
        if x < 0 or y < 0 or width <= 0 or height <= 0 or x + width > cols or y + height > rows:
            raise ValueError(
                f"region ({x}, {y}, {width}, {height}) is not on the {cols} × {rows} px sensor"
            )
        self._roi = (int(x), int(y), int(width), int(height))

    def clear_roi(self) -> None:
        self._roi = None

    def start_sequence(self, n, get_buffer):
        # The generator runs in pymmcore-plus's acquisition thread, which stopping a
        # sequence waits for only two seconds: record it, so that it can be waited for.
        self.sequence_thread = threading.current_thread()
        x, y, w, h = self.get_roi()
        draw = self._frames((y, x, h, w), self._light if self.shutter.get_open() else 0.0)
        batch = max(1, _BATCH_VALUES // (w * h))
        done = 0
        while n is None or done < n:
            for frame in draw(batch if n is None else min(batch, n - done)):
                buffer = get_buffer((h, w), np.uint16)
                buffer[:] = frame
                done += 1
                yield {"ROI-X-start": x, "ROI-Y-start": y}

    def _frames(self, region, light):
        """``draw(k)``: the next k frames (k, h, w) of ``region`` (y, x, h, w) at ``light``
        (photoelectrons per pixel per frame) and the present set-point."""
        y, x, h, w = region
        offset = np.clip(
            self.offset_of(self._setpoint) + self.offset_pattern[y : y + h, x : x + w], 0.0, None
        )
        gain = self.true_em_gain(self._setpoint)

        def draw(k):
            return simulate_frames(
                light,
                em_gain=gain,
                offset=offset,
                frames=k,
                adc_bits=self.camera.adc_bits,
                seed=self._frame_seeds.spawn(1)[0],
                cascade_method=self.camera.cascade_method,
                **self.camera.register(),
            )

        return draw


class SimulatedCMOS(SimulatedEMCCD):
    """An sCMOS or qCMOS (no EM register) whose frames are drawn by
    :func:`emccdcal.simulate.cmos.simulate_cmos_frames`: per-pixel φ, offset and read
    noise (its truth, :attr:`maps`), the ADC's rounding. Its EM gain stays at 1.

    Its ``CameraName`` is the model family it is made like (``ORCA-Quest`` for a
    qCMOS, ``ORCA-Flash4.0`` for an sCMOS, as :data:`emccdcal.simulate.cmos.PRESETS`),
    marked simulated, so that its files record the kind as such a camera's do. Its
    parameters are :class:`SimulatedEMCCD`'s, with an
    :class:`emccdcal.simulate.cmos.CMOSCamera` as ``camera``.
    """

    _NAMES = {"qcmos": "ORCA-Quest", "scmos": "ORCA-Flash4.0"}

    def _draw_truth(self, rng) -> None:
        """Per-pixel φ, offset, read noise and telegraph states (:attr:`maps`)."""
        self.maps = self.camera.maps(rng)

    @staticmethod
    def true_em_gain(setpoint: float) -> float:
        return 1.0

    def offset_of(self, setpoint: float) -> float:
        return float(self.camera.offset)

    def set_em_gain(self, value: float) -> None:
        if float(value) != 1.0:
            raise ValueError(f"EM gain {float(value):g}: this camera has no EM register")

    def get_camera_name(self) -> str:
        return f"{self._NAMES[self.camera.kind]} (emccdcal simulated {self.camera.kind})"

    def _frames(self, region, light):
        y, x, h, w = region
        maps = {name: m[y : y + h, x : x + w] for name, m in self.maps.items()}
        rng = np.random.default_rng(self._frame_seeds.spawn(1)[0])
        return lambda k: simulate_cmos_frames(
            light,
            maps,
            k,
            rng,
            adc_bits=self.camera.adc_bits,
            rts_switch=self.camera.rts_switch,
            rts_states=self.camera.rts_states,
        )
