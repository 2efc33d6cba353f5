"""Micro-Manager for ``emccdcal acquire``: the camera through the core (its EM-gain
property, its settings as Micro-Manager names them), a core with the simulated EMCCD or
with a configuration file, a sequence of frames, and the core made ready and released.

Needs the ``acquire`` extra (pymmcore-plus), imported only by the functions that use it.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from .._files import read_bytes
from .._util import one_line
from ..errors import EmccdcalError, InputError, OptionError

__all__ = [
    "AcquireError",
    "Interrupted",
    "GAIN_PROPERTIES",
    "gain_property",
    "set_gain",
    "camera_properties",
    "simulated_core",
    "config_core",
    "sequence",
    "prepare",
    "release",
]

#: The EM-gain property of each Micro-Manager device adapter (by its library name);
#: others: the standard property ``EMGain`` where the camera has it.
GAIN_PROPERTIES = {
    "Andor": "Gain",
    "AndorSDK3": "Gain",
    "PVCAM": "MultiplierGain",
    "PICAM": "MultiplierGain",
    "PrincetonInstruments": "MultiplierGain",
}


class AcquireError(EmccdcalError, RuntimeError):
    """The recording stopped: the camera, the light, or the session (one line)."""


class Interrupted(AcquireError):
    """Ctrl-C: what was recorded is kept; ``--resume`` continues."""


# --------------------------------------------------------------------------------------
def _name(key) -> str:
    """A property name as text (pymmcore-plus hands standard ones as str enums)."""
    return str(getattr(key, "value", key))


def gain_property(core, camera: str, override: str | None = None) -> str:
    """The camera's EM-gain property: ``override``, else its adapter's
    (:data:`GAIN_PROPERTIES`), else ``EMGain``.

    Raises
    ------
    OptionError
        The camera has no such property (naming its adapter and ``--gain-property``).
    """
    names = {_name(p) for p in core.getDevicePropertyNames(camera)}
    library = _name(core.getDeviceLibrary(camera))
    prop = override or GAIN_PROPERTIES.get(library, "EMGain")
    if prop not in names:
        raise OptionError(
            f"camera '{camera}' (adapter {library}) has no property '{prop}' "
            "for its EM gain: name it with --gain-property (its properties: "
            f"{', '.join(sorted(names))})"
        )
    return prop


def set_gain(core, camera: str, prop: str, setpoint: float) -> None:
    """Set the camera's EM gain to ``setpoint`` through ``prop`` (an Andor's ``EMSwitch``
    off at 1×, on above)."""
    names = {_name(p) for p in core.getDevicePropertyNames(camera)}
    if "EMSwitch" in names:  # Andor: multiplication on, except at 1x
        core.setProperty(camera, "EMSwitch", "Off" if setpoint == 1 else "On")
        if setpoint == 1:
            return
    value = int(setpoint) if float(setpoint).is_integer() else float(setpoint)
    try:
        core.setProperty(camera, prop, value)
    except Exception as exc:  # noqa: BLE001 - the adapter's own error, in one line
        raise AcquireError(f"camera '{camera}' refused {prop} = {value}: {one_line(exc)}") from None


def camera_properties(core, camera: str) -> dict:
    """Every property of the camera as Micro-Manager names them in its files
    (``<label>-<property>``), with the core's ``Camera``, ``Exposure-ms``, ``ROI``,
    ``Binning`` and ``BitDepth``: what :func:`emccdcal.data.micromanager.settings_of`
    reads."""
    props = {"Camera": camera}
    for p in core.getDevicePropertyNames(camera):
        try:
            props[f"{camera}-{_name(p)}"] = str(core.getProperty(camera, p))
        except Exception:  # noqa: BLE001 - a property that cannot be read is not recorded
            continue
    x, y, w, h = core.getROI()
    props.update(
        {
            "Exposure-ms": float(core.getExposure()),
            "ROI": f"{x}-{y}-{w}-{h}",
            "BitDepth": int(core.getImageBitDepth()),
        }
    )
    binning = props.get(f"{camera}-Binning")
    if binning is not None:
        props["Binning"] = binning
    return props


def simulated_core(camera, *, seed: int, run: int = 0):
    """A core with the simulated camera (:mod:`.devices`: an EMCCD for a
    :class:`~emccdcal.simulate.camera.Camera`, an sCMOS or qCMOS for a
    :class:`~emccdcal.simulate.cmos.CMOSCamera`) as ``Camera`` and its shutter as
    ``Shutter``: (core, the camera device)."""
    from pymmcore_plus.experimental.unicore import UniMMCore

    from ..simulate.cmos import CMOSCamera
    from .devices import SimulatedCMOS, SimulatedEMCCD, SimulatedShutter

    core = UniMMCore()
    shutter = SimulatedShutter()
    kind = SimulatedCMOS if isinstance(camera, CMOSCamera) else SimulatedEMCCD
    device = kind(camera, shutter, seed=seed, run=run)
    core.loadPyDevice("Camera", device)
    core.loadPyDevice("Shutter", shutter)
    core.initializeAllDevices()
    core.setCameraDevice("Camera")
    core.setShutterDevice("Shutter")
    return core, device


def config_core(config: Path, adapter_paths=()):
    """A core with a Micro-Manager configuration file loaded (a regular file of text,
    checked before Micro-Manager opens it: it would wait forever on a FIFO)."""
    read_bytes(config, what="Micro-Manager configuration file")
    from pymmcore_plus import CMMCorePlus

    core = CMMCorePlus()
    if adapter_paths:
        core.setDeviceAdapterSearchPaths([str(p) for p in adapter_paths])
    try:
        core.loadSystemConfiguration(str(config))
    except Exception as exc:  # noqa: BLE001 - Micro-Manager's error, in one line
        raise InputError(f"'{config}': Micro-Manager could not load it: {one_line(exc)}") from None
    return core


def sequence(core, n: int, stop: threading.Event, what: str):
    """Frames of a sequence of ``n`` from the core's buffer, one at a time, until ``n``,
    Ctrl-C, or the consumer stops asking (the sequence is then stopped)."""
    core.startSequenceAcquisition(n, 0.0, True)
    got = 0
    try:
        while got < n and not stop.is_set():
            if core.getRemainingImageCount() > 0:
                got += 1
                yield core.popNextImage()
            elif not core.isSequenceRunning():
                if core.getRemainingImageCount() > 0:
                    continue
                overflow = getattr(core, "isBufferOverflowed", lambda: False)()
                raise AcquireError(
                    f"{what}: the camera stopped after {got} of {n} frames"
                    + (
                        ": Micro-Manager's buffer overflowed (frames came faster than they "
                        "were written; a smaller --roi, a slower frame rate or a faster disk)"
                        if overflow
                        else ""
                    )
                )
            else:
                time.sleep(0.0002)
    finally:
        core.stopSequenceAcquisition()


def prepare(core, camera, roi) -> None:
    """The core's camera set to ``camera``, auto-shutter off and the region ``roi``
    (x, y, width, height) read out; a camera or region refused is one line."""
    try:
        core.setCameraDevice(camera)
    except Exception as exc:  # noqa: BLE001 - the core's own error, in one line
        loaded = ", ".join(str(d) for d in core.getLoadedDevices())
        raise OptionError(
            f"no camera '{camera}' in the configuration (its devices: "
            f"{loaded or 'none'}): {one_line(exc)}"
        ) from None
    core.setAutoShutter(False)
    if roi is not None:
        try:
            core.setROI(*[int(v) for v in roi])
        except Exception as exc:  # noqa: BLE001 - the adapter's own error, in one line
            raise OptionError(
                f"camera '{camera}' refused the region {tuple(roi)}: {one_line(exc)}"
            ) from None


def release(core, *, unload: bool) -> None:
    """The sequence stopped, the shutter closed and, for a core made here, the devices
    unloaded (Micro-Manager aborts at exit when a camera thread outlives its core)."""
    steps = [core.stopSequenceAcquisition, lambda: core.setShutterOpen(False)]
    for step in steps + ([core.unloadAllDevices] if unload else []):
        try:
            step()
        except Exception:  # noqa: BLE001 - closing down: the first error is the one told
            pass
