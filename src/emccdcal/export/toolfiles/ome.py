"""A plain OME-TIFF of a set-point's per-pixel maps, each with its standard error: writer
and the audit's reader, one plug-in.

One float32 image of C channels × rows × cols (OME axes ``CYX``) whose OME-XML names each
channel (``Channel Name``) and whose image ``Description`` is a JSON object of the
channels' units, the set-point, the sensor origin and the provenance; any OME reader
(Fiji's Bio-Formats, bioio, QuPath, napari) opens it with the names. The channels, in
the names and units of a result (docs/results.md):

- ``e_per_adu`` (e⁻/ADU) and ``adu_per_e`` (ADU/e⁻), the conversion factor both ways;
- ``em_gain`` (1 at set-point 1) and ``adu_per_e_total`` (g/φ, ADU per photoelectron);
- ``offset`` (ADU);
- ``read_noise_variance`` (ADU²) and ``read_noise_variance_e`` (e⁻²): the variance the
  read-out adds to the counts, as a dark's counts show it (the ADC's rounding included
  where the analog read noise is below 2 ADU: what localization tools' variance maps
  hold), in counts and in photoelectrons (× φ²);
- each followed by its ``_se`` where the calibration has it (φ's and g's from the fit;
  the offset's and read noise's from the dark frames' count);
- the pixels the darks flagged (:data:`emccdcal.result.flags.PIXEL_FLAGS`, 1 where
  flagged, else 0): ``stuck`` where the calibration reduced dark stacks, ``telegraph``
  where it tested for random-telegraph pixels, ``hot`` where it measured the dark
  current: the masks a user leaves out of a fit; with ``telegraph`` the offset states
  counted (``telegraph_states``: 1 for one normal, 2 to 4 at a random-telegraph pixel).
"""

from __future__ import annotations

import json

import numpy as np

from ...errors import InputError
from ...model import adc
from ...plugins import Tool
from ...result import format_setpoint
from ...result.flags import PIXEL_FLAGS
from .. import toolkit

#: The file written.
FILE = "emccdcal-maps.ome.tif"
#: The key of the description's JSON that marks the file as emccdcal's maps.
_MARK = "emccdcal_maps"


def channels(cal, s) -> list[tuple[str, np.ndarray, str]]:
    """The maps at set-point ``s``: ``(name, image (R, C), unit)``, each followed by its
    standard error where the calibration has one."""
    phi, phi_se = cal.e_per_adu, cal.e_per_adu_se
    gain, gain_se = cal.gain(s), cal.gain_se(s)
    offset, sigma = cal.dark(s)
    variance = adc.count_variance(sigma, s == 1)
    sigma_se = cal.read_noise_se.get(float(s))
    variance_se = None if sigma_se is None else 2.0 * sigma * sigma_se
    out = [("e_per_adu", phi, "e-/ADU"), ("e_per_adu_se", phi_se, "e-/ADU")]
    out += [("adu_per_e", 1.0 / phi, "ADU/e-")]
    out += [("adu_per_e_se", None if phi_se is None else phi_se / phi**2, "ADU/e-")]
    out += [("em_gain", gain, "1"), ("em_gain_se", gain_se, "1")]
    total = gain / phi
    total_se = None
    if phi_se is not None:  # g's and φ's errors taken as independent
        total_se = total * np.hypot(gain_se / gain, phi_se / phi)
    out += [("adu_per_e_total", total, "ADU/e-"), ("adu_per_e_total_se", total_se, "ADU/e-")]
    out += [("offset", offset, "ADU"), ("offset_se", cal.offset_se.get(float(s)), "ADU")]
    out += [("read_noise_variance", variance, "ADU2")]
    out += [("read_noise_variance_se", variance_se, "ADU2")]
    variance_e = variance * phi**2
    variance_e_se = None
    if variance_se is not None and phi_se is not None:
        variance_e_se = variance_e * np.hypot(variance_se / variance, 2.0 * phi_se / phi)
    out += [("read_noise_variance_e", variance_e, "e-2")]
    out += [("read_noise_variance_e_se", variance_e_se, "e-2")]
    for name in PIXEL_FLAGS:
        mask = getattr(cal, name)
        if mask is not None:
            out += [(name, mask.astype(float), "1")]
    if cal.telegraph_states is not None:
        out += [("telegraph_states", cal.telegraph_states.astype(float), "1")]
    return [(name, image, unit) for name, image, unit in out if image is not None]


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """The OME-TIFF of set-point ``s``'s maps (:data:`FILE`)."""
    import tifffile

    maps = channels(cal, s)
    data = np.stack([np.asarray(m, dtype=np.float32) for _, m, _ in maps])
    description = {
        _MARK: 1,
        "setpoint": float(s),
        "units": {n: u for n, _, u in maps},
        "sensor_origin": list(cal.origin) if cal.origin is not None else None,
        "camera_kind": cal.camera_kind,
        "emccdcal": toolkit.provenance(cal, s, qe),
    }
    metadata = {
        "axes": "CYX",
        "Name": f"emccdcal maps at {format_setpoint(s)}x",
        "Channel": {"Name": [n for n, _, _ in maps]},
        "Description": json.dumps(description),
    }
    if pixel_size_nm is not None:
        for axis in "XY":
            metadata[f"PhysicalSize{axis}"] = float(pixel_size_nm)
            metadata[f"PhysicalSize{axis}Unit"] = "nm"
    path = out / FILE
    return [
        toolkit.write_file(
            path,
            lambda p: tifffile.imwrite(
                p, data, ome=True, photometric="minisblack", metadata=metadata
            ),
        )
    ]


def _ome(path):
    """(channel names, description JSON, image) of an OME-TIFF of our maps, or None."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        xml = tif.ome_metadata
        if not xml:
            return None
        root = toolkit.load_xml(path, what="OME-XML", text=xml.encode("utf-8"))
        ns = {"ome": root.tag[1 : root.tag.index("}")]} if root.tag.startswith("{") else {}
        prefix = "ome:" if ns else ""
        text = root.findtext(f".//{prefix}Image/{prefix}Description", namespaces=ns)
        try:
            described = toolkit.load_json(path, what="description", text=text or "")
        except InputError:  # another OME-TIFF's free text
            return None
        if not isinstance(described, dict) or _MARK not in described:
            return None
        names = [c.get("Name") for c in root.iterfind(f".//{prefix}Image//{prefix}Channel", ns)]
        data = tif.asarray()
    return names, described, data


def read(path, setpoint):
    """The audit's reading of our OME-TIFF of maps (None: not one)."""
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    found = _ome(path)
    if found is None:
        return None
    names, described, data = found
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3 or len(names) != data.shape[0]:
        raise InputError(f"'{path}': {len(names)} channel names for an image of shape {data.shape}")
    image = dict(zip(names, np.asarray(data, dtype=float)))
    needed = ("offset", "adu_per_e_total", "read_noise_variance")
    missing = [n for n in needed if n not in image]
    if missing:
        raise InputError(f"'{path}': no channel {', '.join(missing)}: not a set of maps to audit")
    at = described.get("setpoint")
    if at is not None and setpoint is not None and float(at) != float(setpoint):
        raise InputError(
            f"'{path}': its maps are of set-point {format_setpoint(at)}x, "
            f"not {format_setpoint(setpoint)}x"
        )
    origin = described.get("sensor_origin")
    maps = {
        "offset": image["offset"],
        "adu_per_e_total": image["adu_per_e_total"],
        "variance": image["read_noise_variance"],
    }
    return toolkit.per_pixel_reading(
        "ome-tiff", "maps", path, maps, None if origin is None else tuple(map(int, origin)),
        names=("offset", "adu_per_e_total"), gain_note="g/phi", partial=True,
    )  # fmt: skip


TOOL = Tool("ome-tiff", "OME-TIFF maps", write, None, None, read_file=read)
