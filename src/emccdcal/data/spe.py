"""Princeton Instruments SPE files (LightField SPE 3.0 and WinView/WinSpec SPE 2.x).

The paper's camera, a ProEM, writes SPE. Layout (Princeton Instruments, "SPE 3.0 File
Format Specification", document 4411-0140): a 4100-byte binary header, then the frames,
then (3.0) an XML footer that describes them. LightField can store per-frame metadata
(time stamps, frame counters) after each frame: frames then lie ``stride`` bytes apart,
not one frame size apart, and a reader that ignores the stride returns shifted frames
without a word. Here frames are always addressed through the footer's stride.

Only what the file records is returned as :class:`~emccdcal.data.settings.CameraSettings`,
the kind of camera among it where its model says it (a ProEM's, a PIXIS's, a KURO's:
:func:`~emccdcal.data.settings.kind_of_model`); SPE 2.x has no EM-gain field and no
model (give the set-point in the manifest).
"""

from __future__ import annotations

import functools
import math
import struct
from pathlib import Path

import numpy as np

from .. import _files
from ..errors import InputError
from .settings import CameraSettings, kind_of_model, recorded_number

__all__ = ["SUFFIXES", "HEADER_BYTES", "read_layout", "header", "settings"]

#: File name suffixes of this format.
SUFFIXES = (".spe",)

#: Bytes of the binary header; the first frame follows it.
HEADER_BYTES = 4100
_VERSION_AT = 1992  # float32: 3.0 for LightField files
_FOOTER_AT = 678  # uint64: byte offset of the XML footer (3.0)
_LASTVALUE_AT = 4098  # int16: 0x5555 in every SPE file
_PIXEL_FORMATS = {
    "MonochromeUnsigned16": np.dtype("<u2"),
    "MonochromeUnsigned32": np.dtype("<u4"),
    "MonochromeFloating32": np.dtype("<f4"),
}
# SPE 2.x: data type code at byte 108, frame width at 42, height at 656, frames at 1446.
_V2_TYPES = {
    0: np.dtype("<f4"),
    1: np.dtype("<i4"),
    2: np.dtype("<i2"),
    3: np.dtype("<u2"),
    8: np.dtype("<u4"),
}


def read_layout(path: Path):
    """Shape (frames, rows, cols), dtype, data offset, frame stride (bytes) and settings.

    Parsed once per file version (path, size, modification time): a calibration asks
    for it for every tile.

    Raises
    ------
    InputError
        One line naming the file: not an SPE file, a footer offset outside the file,
        XML that does not describe the frames, a stride smaller than a frame, or frames
        that do not fit before the footer (a truncated file).
    """
    st = path.stat()
    return _read_layout(path, str(path.resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=128)
def _read_layout(path: Path, resolved: str, size: int, mtime_ns: int):
    with open(resolved, "rb") as fh:
        head = fh.read(HEADER_BYTES)
        if len(head) < HEADER_BYTES:
            raise InputError(
                f"'{path}': {size} bytes, too short for an SPE header ({HEADER_BYTES} bytes)"
            )
        if struct.unpack_from("<H", head, _LASTVALUE_AT)[0] != 0x5555:
            raise InputError(f"'{path}': not an SPE file (no 0x5555 at byte {_LASTVALUE_AT})")
        version = struct.unpack_from("<f", head, _VERSION_AT)[0]
        if version >= 3:
            footer_at = struct.unpack_from("<Q", head, _FOOTER_AT)[0]
            if not HEADER_BYTES <= footer_at < size:
                raise InputError(
                    f"'{path}': SPE 3.0 footer offset {footer_at} is outside "
                    f"the file ({size} bytes): damaged or truncated"
                )
            fh.seek(footer_at)
            return _layout_v3(path, fh.read(), footer_at)
    return _layout_v2(path, head, size)


def _layout_v3(path, xml_bytes, footer_at):
    try:
        root = _files.load_xml(path, text=xml_bytes, what="SPE 3.0 XML footer")
    except InputError as exc:
        raise InputError(
            f"'{path}': SPE 3.0 XML footer is not valid XML: {str(exc).split(': ', 1)[-1]}"
        ) from None
    frame = root.find("{*}DataFormat/{*}DataBlock[@type='Frame']")
    if frame is None:
        raise InputError(
            f"'{path}': SPE 3.0 XML footer has no DataFormat/DataBlock of type 'Frame'"
        )
    regions = frame.findall("{*}DataBlock[@type='Region']")
    if len(regions) != 1:
        raise InputError(
            f"'{path}': SPE 3.0 frames hold {len(regions)} regions; "
            "one region per frame is supported"
        )
    try:
        count = int(frame.get("count"))
        stride = int(frame.get("stride"))
        width, height = int(regions[0].get("width")), int(regions[0].get("height"))
        fmt = regions[0].get("pixelFormat") or frame.get("pixelFormat")
    except (TypeError, ValueError):
        raise InputError(
            f"'{path}': SPE 3.0 XML footer: the Frame and Region blocks need "
            "count, stride, width and height"
        ) from None
    if fmt not in _PIXEL_FORMATS:
        raise InputError(
            f"'{path}': SPE 3.0 pixel format {fmt!r} is not supported ({', '.join(_PIXEL_FORMATS)})"
        )
    dtype = _PIXEL_FORMATS[fmt]
    frame_bytes = width * height * dtype.itemsize
    if count < 1 or width < 1 or height < 1:
        raise InputError(
            f"'{path}': SPE 3.0 XML footer describes {count} frames of {height} × {width} pixels"
        )
    if stride < frame_bytes:
        raise InputError(
            f"'{path}': SPE 3.0 frame stride {stride} bytes is smaller than a "
            f"frame of {height} × {width} {fmt} ({frame_bytes} bytes)"
        )
    if HEADER_BYTES + count * stride > footer_at:
        whole = (footer_at - HEADER_BYTES) // stride
        raise InputError(
            f"'{path}': truncated: the SPE 3.0 footer describes {count} frames "
            f"of {stride} bytes but {whole} fit before it"
        )
    return (count, height, width), dtype, HEADER_BYTES, stride, _settings_v3(root)


def _text(root, path):
    node = root.find(path)
    return None if node is None or node.text is None else node.text.strip()


def _number(root, path):
    return recorded_number(_text(root, path))


def _settings_v3(root) -> CameraSettings:
    exp = "{*}DataHistories/{*}DataHistory/{*}Origin/{*}Experiment"
    cam = exp + "/{*}Devices/{*}Cameras/{*}Camera"
    bits = _number(root, cam + "/{*}Adc/{*}BitDepth")
    reading = _number(root, cam + "/{*}Sensor/{*}Temperature/{*}Reading")
    system = root.find(exp + "/{*}System/{*}Cameras/{*}Camera")
    model = None if system is None else system.get("model")
    kind = kind_of_model(model)
    mapping = root.find("{*}Calibrations/{*}SensorMapping")
    roi = binning = None
    if mapping is not None:
        try:
            roi = tuple(int(mapping.get(k)) for k in ("x", "y", "width", "height"))
            binning = (int(mapping.get("xBinning", 1)), int(mapping.get("yBinning", 1)))
        except (TypeError, ValueError):
            roi = binning = None
    return CameraSettings(
        # only an EMCCD's gain field is an EM set-point (an intensifier's is not)
        em_gain_setpoint=_number(root, cam + "/{*}Adc/{*}EMGain")
        if kind in (None, "emccd")
        else None,
        camera_kind=kind,
        analog_gain=_text(root, cam + "/{*}Adc/{*}AnalogGain"),
        amplifier=_text(root, cam + "/{*}Adc/{*}Quality"),
        readout_rate_mhz=_number(root, cam + "/{*}Adc/{*}Speed"),
        adc_bits=None if bits is None else int(bits),
        temperature_c=(
            reading
            if reading is not None
            else _number(root, cam + "/{*}Sensor/{*}Temperature/{*}SetPoint")
        ),
        exposure_ms=_number(root, cam + "/{*}ShutterTiming/{*}ExposureTime"),
        serial=None if system is None else system.get("serialNumber"),
        model=model,
        roi=roi,
        binning=binning,
    )


def _layout_v2(path, head, size):
    code = struct.unpack_from("<h", head, 108)[0]
    if code not in _V2_TYPES:
        raise InputError(f"'{path}': SPE 2.x data type code {code} is not supported")
    dtype = _V2_TYPES[code]
    width = struct.unpack_from("<H", head, 42)[0]
    height = struct.unpack_from("<H", head, 656)[0]
    count = struct.unpack_from("<i", head, 1446)[0]
    if count < 1 or width < 1 or height < 1:
        raise InputError(
            f"'{path}': SPE 2.x header describes {count} frames of {height} × {width} pixels"
        )
    exposure_s = struct.unpack_from("<f", head, 10)[0]
    temperature = struct.unpack_from("<f", head, 36)[0]
    bits = struct.unpack_from("<h", head, 194)[0]
    settings = CameraSettings(
        exposure_ms=1000.0 * exposure_s if math.isfinite(exposure_s) and exposure_s > 0 else None,
        temperature_c=temperature if math.isfinite(temperature) and temperature != 0 else None,
        adc_bits=int(bits) if 0 < bits <= 32 else None,
    )
    frame_bytes = width * height * dtype.itemsize
    return (count, height, width), dtype, HEADER_BYTES, frame_bytes, settings


def header(path: Path):
    """Shape, dtype, data offset and frame stride (the readers' common interface)."""
    return read_layout(path)[:4]


def settings(path: Path) -> CameraSettings:
    """The camera settings the file records."""
    return read_layout(path)[4]
