"""emccdcal's own formats of every set-point: a JSON of the numbers, FITS and TIFF maps
(written only: no tool reads them back for an audit).
"""

from __future__ import annotations

from pathlib import Path
import json

import numpy as np

from ...errors import OptionError
from ...result import format_setpoint, pixel_statistics
from ...plugins import Tool
from .. import toolkit


def _all_values(cal):
    """:func:`camera_values` at every set-point with an offset; φ and g alone elsewhere."""
    doc = {}
    for s in cal.setpoints:
        if s in cal.offset:
            doc[format_setpoint(s)] = toolkit.camera_values(cal, s)
        else:
            doc[format_setpoint(s)] = {
                "e_per_adu": pixel_statistics(cal.e_per_adu),
                "em_gain": pixel_statistics(cal.gain(s)),
            }
    return doc


def write_json(cal, s, v, out, qe, pixel_size_nm, name):
    """Everything, every set-point, in our own names and units."""
    doc = {
        "emccdcal": toolkit.provenance(cal, None, qe),
        "camera": cal.camera,
        "units": {
            "e_per_adu": "e-/ADU",
            "em_gain": "1",
            "adu_per_e_total": "ADU/e-",
            "offset": "ADU",
            "read_noise": "ADU",
            "read_noise_e": "e-",
        },
        "statistics": "median over converged pixels; spread: robust spread 1.4826*MAD; "
        "se_of_median: standard error of that median, "
        "sqrt(pi/2)*spread/sqrt(n); n pixels (docs/results.md)",
        "by_setpoint": _all_values(cal),
    }
    if pixel_size_nm is not None:
        doc["pixel_size_nm"] = pixel_size_nm
    return [toolkit.write_text(out / "emccdcal-camera.json", json.dumps(doc, indent=2) + "\n")]


def _maps(cal):
    """Every per-pixel map: (name, image, unit)."""
    yield "e_per_adu", cal.e_per_adu, "e-/ADU"
    if cal.e_per_adu_se is not None:
        yield "e_per_adu_se", cal.e_per_adu_se, "e-/ADU"
    for s in cal.setpoints:
        tag = format_setpoint(s) + "x"
        if s in cal.em_gain:
            yield f"em_gain_{tag}", cal.gain(s), "1"
            yield f"em_gain_se_{tag}", cal.gain_se(s), "1"
        if s in cal.offset:
            yield f"offset_{tag}", cal.offset[s], "ADU"
            yield f"read_noise_{tag}", cal.read_noise[s], "ADU"


def write_fits(cal, s, v, out, qe, pixel_size_nm, name):
    """One FITS file, an image extension per map (``EXTNAME``, ``BUNIT``)."""
    try:
        from astropy.io import fits
    except ImportError:
        raise OptionError("--to fits needs astropy: " + toolkit.install_hint("fits")) from None
    prov = toolkit.provenance(cal, None, qe)
    primary = fits.PrimaryHDU()
    primary.header["CREATOR"] = f"emccdcal {prov['emccdcal_version']}"
    primary.header["METHOD"] = prov["method"]
    primary.header["EMMODEL"] = prov["em_model"]
    primary.header["CALDATE"] = prov["created"]
    for i, r in enumerate(prov["results"]):
        primary.header[f"RESULT{i}"] = Path(r["file"]).name
        primary.header[f"SHA256{i}"] = r["sha256"][:64]
    if cal.origin is not None:
        primary.header["ORIGROW"], primary.header["ORIGCOL"] = cal.origin
    hdus = [primary]
    for key, image, unit in _maps(cal):
        hdu = fits.ImageHDU(np.asarray(image, dtype=np.float32), name=key.upper()[:68])
        hdu.header["BUNIT"] = unit
        hdus.append(hdu)
    path = out / "emccdcal-maps.fits"
    return [toolkit.write_file(path, lambda p: fits.HDUList(hdus).writeto(p))]


def write_tiff_maps(cal, s, v, out, qe, pixel_size_nm, name):
    """One float32 TIFF per map, its units and provenance in the description (JSON)."""
    prov = toolkit.provenance(cal, None, qe)
    return [
        toolkit.write_tiff(out / f"{key}.tif", image, {"quantity": key, "units": unit, **prov})
        for key, image, unit in _maps(cal)
    ]


JSON = Tool("json", "emccdcal JSON", write_json, all_setpoints=True)
FITS = Tool("fits", "FITS maps", write_fits, all_setpoints=True)
TIFF_MAPS = Tool("tiff-maps", "TIFF maps", write_tiff_maps, all_setpoints=True)
