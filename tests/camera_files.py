"""Camera files written in the tests, from the formats' published layouts."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

SPE_FORMATS = {
    np.dtype("uint16"): "MonochromeUnsigned16",
    np.dtype("uint32"): "MonochromeUnsigned32",
    np.dtype("float32"): "MonochromeFloating32",
}


def write_spe(
    path,
    frames,
    *,
    em_gain=None,
    analog_gain="High",
    quality="ElectronMultiplied",
    speed_mhz=10.0,
    bit_depth=16,
    exposure_ms=10.0,
    temperature=-70.0,
    serial="12345678",
    model="ProEM+: 512B",
    roi=(0, 0),
    binning=(1, 1),
    frame_metadata=True,
    footer_offset=None,
    stride=None,
    xml_text=None,
) -> Path:
    """An SPE 3.0 file as LightField writes it (Princeton Instruments document 4411-0140):
    a 4100-byte header, the frames, each followed by a 64-bit time stamp and a 64-bit
    frame counter when ``frame_metadata``, and the XML footer. ``footer_offset``,
    ``stride`` and ``xml_text`` override what is written, to make damaged files."""
    frames = np.asarray(frames)
    n, height, width = frames.shape
    fmt = SPE_FORMATS[frames.dtype]
    frame_bytes = height * width * frames.dtype.itemsize
    meta = 16 if frame_metadata else 0
    real_stride = frame_bytes + meta
    body = bytearray()
    for i, frame in enumerate(frames):
        body += np.ascontiguousarray(frame, dtype=frames.dtype.newbyteorder("<")).tobytes()
        if frame_metadata:
            body += struct.pack("<qq", 1_000_000 * i + 17, i + 1)  # time stamp, counter
    header = bytearray(4100)
    struct.pack_into("<H", header, 42, width)
    struct.pack_into(
        "<h",
        header,
        108,
        {"MonochromeUnsigned16": 3, "MonochromeUnsigned32": 8, "MonochromeFloating32": 0}[fmt],
    )
    struct.pack_into("<H", header, 656, height)
    struct.pack_into("<i", header, 1446, n)
    struct.pack_into("<f", header, 1992, 3.0)
    struct.pack_into("<H", header, 4098, 0x5555)
    footer_at = 4100 + len(body)
    struct.pack_into("<Q", header, 678, footer_at if footer_offset is None else footer_offset)
    gain = "" if em_gain is None else f"<EMGain>{em_gain:g}</EMGain>"
    xml = (
        xml_text
        if xml_text is not None
        else f"""<?xml version="1.0" encoding="utf-8"?>
<SpeFormat version="3.0" xmlns="http://www.princetoninstruments.com/spe/2009">
  <DataFormat>
    <DataBlock type="Frame" version="3.0" count="{n}" pixelFormat="{fmt}" size="{frame_bytes}" stride="{real_stride if stride is None else stride}">
      <DataBlock type="Region" version="3.0" count="1" pixelFormat="{fmt}" size="{frame_bytes}" stride="{frame_bytes}" calibrations="1" width="{width}" height="{height}" />
    </DataBlock>
    {'<MetaBlock type="TimeStamp" event="ExposureStarted" version="3.0" resolution="1000000" bitDepth="64" /><MetaBlock type="FrameTrackingNumber" version="3.0" bitDepth="64" />' if frame_metadata else ""}
  </DataFormat>
  <Calibrations>
    <SensorMapping id="1" x="{roi[0]}" y="{roi[1]}" width="{width * binning[0]}" height="{height * binning[1]}" xBinning="{binning[0]}" yBinning="{binning[1]}" />
  </Calibrations>
  <DataHistories><DataHistory><Origin softwareName="LightField" softwareVersion="6.16">
    <Experiment xmlns="http://www.princetoninstruments.com/experiment/2009">
      <Devices><Cameras><Camera>
        <Adc>{gain}<Quality>{quality}</Quality><AnalogGain>{analog_gain}</AnalogGain><Speed>{speed_mhz:g}</Speed><BitDepth>{bit_depth}</BitDepth></Adc>
        <ShutterTiming><ExposureTime>{exposure_ms:g}</ExposureTime></ShutterTiming>
        <Sensor><Temperature><SetPoint>{temperature:g}</SetPoint><Reading>{temperature:g}</Reading></Temperature></Sensor>
      </Camera></Cameras></Devices>
      <System><Cameras><Camera serialNumber="{serial}" model="{model}" /></Cameras></System>
    </Experiment>
  </Origin></DataHistory></DataHistories>
</SpeFormat>"""
    )
    path = Path(path)
    path.write_bytes(bytes(header) + bytes(body) + xml.encode("utf-8"))
    return path


def write_fits(
    path,
    frames,
    *,
    em_gain=None,
    exposure_s=0.01,
    temperature=-70.0,
    readtime=1e-7,
    preamp=2.0,
    serial="X-1234",
    head="DU897_BV",
    binning=(1, 1),
    amplifier="Electron Multiplying",
):
    """A FITS stack with the cards Andor Solis writes; uint16 counts are stored as int16
    with BZERO = 32768, as the standard requires (astropy does that by itself)."""
    from astropy.io import fits

    hdu = fits.PrimaryHDU(np.asarray(frames))
    cards = {
        "EXPOSURE": exposure_s,
        "TEMP": temperature,
        "READTIME": readtime,
        "PREAMP": preamp,
        "OUTPTAMP": amplifier,
        "SERNO": serial,
        "HEAD": head,
        "HBIN": binning[0],
        "VBIN": binning[1],
    }
    if em_gain is not None:
        cards["GAIN"] = em_gain
    for key, value in cards.items():
        hdu.header[key] = value
    hdu.writeto(path, overwrite=True)
    return Path(path)


def write_zarr(path, frames, *, em_gain=None, **settings):
    """A Zarr store of the stack, a chunk per frame, its settings in attribute "emccdcal"."""
    import zarr

    frames = np.asarray(frames)
    z = zarr.open(
        str(path), mode="w", shape=frames.shape, dtype=frames.dtype, chunks=(1,) + frames.shape[1:]
    )
    z[:] = frames
    if em_gain is not None:
        settings["em_gain_setpoint"] = em_gain
    z.attrs["emccdcal"] = settings
    return Path(path)


def micromanager_properties(
    style="andor",
    *,
    em_gain=300,
    readout="17.000 MHz",
    temperature=-70,
    exposure_ms=10.0,
    preamp="Gain 2",
    roi="0-0-6-5",
):
    """One frame's Micro-Manager properties as an Andor, a Photometrics or a Hamamatsu
    (DCAM: an ORCA-Quest, no EM register) camera writes them."""
    if style == "hamamatsu":
        return {
            "Camera": "HamamatsuHam_DCAM",
            "HamamatsuHam_DCAM-CameraName": "C15550-20UP",
            "HamamatsuHam_DCAM-CameraID": "S/N: 000123",
            "HamamatsuHam_DCAM-ReadoutSpeed": "Ultra quiet",
            "Exposure-ms": str(exposure_ms),
            "BitDepth": "16",
            "ROI": roi,
            "Binning": "1x1",
        }
    if style == "andor":
        return {
            "Camera": "Andor",
            "Andor-Gain": str(em_gain),
            "Andor-EMSwitch": "On",
            "Andor-Pre-Amp-Gain": preamp,
            "Andor-ReadoutMode": readout,
            "Andor-Output_Amplifier": "Electron Multiplying",
            "Andor-CCDTemperature": str(temperature),
            "Andor-Camera": "| iXon Ultra 897 | DU897_BV | 9876 |",
            "Exposure-ms": str(exposure_ms),
            "BitDepth": "16",
            "ROI": roi,
            "Binning": "1",
        }
    return {
        "Camera": "Photometrics",
        "Photometrics-MultiplierGain": str(em_gain),
        "Photometrics-Gain": "1",
        "Photometrics-ReadoutRate": readout,
        "Photometrics-Port": "Multiplication gain",
        "Photometrics-BitDepth": "16",
        "Photometrics-CCDTemperature": str(temperature),
        "Photometrics-SerialNumber": "A17C",
        "Photometrics-ChipName": "Evolve512",
        "Exposure-ms": str(exposure_ms),
        "ROI": roi,
        "Binning": "1x1",
    }


def write_micromanager_tiff(path, frames, *, em_gain=None, style="andor", ome=True, **kw):
    """A Micro-Manager OME-TIFF: every frame carries its properties in tag 51123."""
    import json

    import tifffile

    base = micromanager_properties(style, em_gain=300 if em_gain is None else em_gain, **kw)
    tifffile.imwrite(
        path,
        np.asarray(frames),
        ome=ome,
        photometric="minisblack",
        extratags=[(51123, "s", 0, json.dumps(base), False)],
    )
    return Path(path)


def multi_frame_sif(src, dst, frames):
    """A multi-frame Andor SIF derived from a real one-frame file: its header with the
    frame count, total length and one time stamp per frame changed, then ``frames``
    (float32, the file's frame shape), then the file's trailer. The layout is the one
    sif-parser reads (an image-structure line ``65541 x0 y1 x1 y0 frames subimages total
    length``, a sub-image line, a time stamp per frame, a ``0`` flag, the data)."""
    import re

    import sif_parser

    raw = Path(src).read_bytes()
    _, info = sif_parser.np_open(str(src), lazy="memmap")
    offset, image = info["offset"], info["ImageLength"]
    frames = np.asarray(frames, dtype="<f4")
    assert info["NumberOfFrames"] == 1 and frames[0].size == image
    match = list(re.finditer(rb"(6554[13] -?\d+ -?\d+ -?\d+ -?\d+) 1 1 \d+ \d+", raw[:offset]))[-1]
    n = len(frames)
    structure = match.group(1) + f" {n} 1 {image * n} {image}".encode()
    tail = raw[match.end() : offset]
    subimage = tail[: tail.index(b"\n", 1) + 1]
    stamps = b"".join(f"{1000 * k}\n".encode() for k in range(n))
    header = raw[: match.start()] + structure + subimage + stamps + b"0\n"
    Path(dst).write_bytes(header + frames.tobytes() + raw[offset + 4 * image :])
    return Path(dst)


def write_ome_tiff(path, frames, *, detector_type, model, serial="S1", exposure_ms=50.0):
    """An OME-TIFF from a writer other than Micro-Manager: no properties tag, its camera
    only in the OME-XML, as an ``Instrument``'s ``Detector`` (``Type``, ``Model``,
    ``SerialNumber``) that the channel's ``DetectorSettings`` name, and each plane's
    ``ExposureTime``."""
    import tifffile

    frames = np.asarray(frames)
    tifffile.imwrite(path, frames, ome=True, photometric="minisblack", metadata={"axes": "TYX"})
    xml = tifffile.TiffFile(path).ome_metadata
    head, rest = xml.split("<Image ", 1)
    detector = (
        f'<Instrument ID="Instrument:0"><Detector ID="Detector:0:0" Type="{detector_type}" '
        f'Model="{model}" SerialNumber="{serial}"/></Instrument>'
    )
    rest = rest.replace("<LightPath/>", '<DetectorSettings ID="Detector:0:0" Binning="1x1"/>'
                        "<LightPath/>", 1)  # fmt: skip
    planes = "".join(
        f'<Plane TheZ="0" TheC="0" TheT="{t}" ExposureTime="{exposure_ms:g}" '
        'ExposureTimeUnit="ms"/>'
        for t in range(len(frames))
    )
    rest = rest.replace("</Pixels>", planes + "</Pixels>", 1)
    tifffile.tiffcomment(path, head + detector + "<Image " + rest)
    return Path(path)
