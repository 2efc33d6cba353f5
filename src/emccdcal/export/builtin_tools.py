"""emccdcal's own localization tools and formats as plug-ins (:class:`emccdcal.plugins.Tool`),
registered in its ``pyproject.toml`` under ``emccdcal.tools`` as another package's are:
each pairs the tool's writer (:mod:`emccdcal.export.tools`) with the reader and the
recogniser of its file that an audit uses (:mod:`emccdcal.export.audit`).

Each recognises its own files only (by a suffix, or by keys no other tool's file has), so
the order in which an audit asks does not matter.
"""

from __future__ import annotations

from ..plugins import Tool
from . import audit, tools

__all__ = ["PICASSO", "PYME", "DECODE", "THUNDERSTORM", "SMAP", "GDSC", "STORM_ANALYSIS",
           "JSON", "FITS", "TIFF_MAPS"]


def _suffix(path) -> str:
    return path.suffix.lower()


def _keys(doc) -> set:
    return set(doc) if isinstance(doc, dict) else set()


PICASSO = Tool(
    "picasso", "Picasso", tools._picasso,
    lambda path, text, doc, setpoint, tool_gain: audit._picasso(doc, path, setpoint, tool_gain),
    lambda path, text, doc: "Cameras" in _keys(doc))
PYME = Tool(
    "pyme", "PYME", tools._pyme,
    lambda path, text, doc, setpoint, tool_gain: audit._pyme(
        doc if isinstance(doc, dict) and doc else audit._pyme_md(text or ""), path),
    lambda path, text, doc: _suffix(path) == ".md" or (
        isinstance(doc, dict)
        and "Camera.ElectronsPerCount" in {".".join(k) for k, _ in audit._leaves(doc)}))
DECODE = Tool(
    "decode", "DECODE", tools._decode,
    lambda path, text, doc, setpoint, tool_gain: audit._decode(doc, path),
    lambda path, text, doc: isinstance(doc, dict) and next(
        audit._find_tables(doc, ("e_per_adu", "em_gain")), None) is not None)
THUNDERSTORM = Tool(
    "thunderstorm", "ThunderSTORM", tools._thunderstorm,
    lambda path, text, doc, setpoint, tool_gain: audit._thunderstorm(text or "", path),
    lambda path, text, doc: text is not None and "Camera setup" in text and "run(" in text)
SMAP = Tool(
    "smap", "SMAP", tools._smap,
    lambda path, text, doc, setpoint, tool_gain: audit._smap(doc, path),
    lambda path, text, doc: _suffix(path) == ".mat" or (isinstance(doc, dict) and next(
        audit._find_tables(doc, ("conversion", "emgain")), None) is not None))
GDSC = Tool(
    "gdsc", "gdsc-smlm", tools._gdsc,
    lambda path, text, doc, setpoint, tool_gain: audit._gdsc(doc, path),
    lambda path, text, doc: bool(_keys(doc) & {"intensityCalibration",
                                               "intensity_calibration"}))
STORM_ANALYSIS = Tool(
    "storm-analysis", "storm-analysis", tools._storm_analysis,
    lambda path, text, doc, setpoint, tool_gain: audit._storm_analysis(path),
    lambda path, text, doc: _suffix(path) == ".xml")
JSON = Tool("json", "emccdcal JSON", tools._json, all_setpoints=True)
FITS = Tool("fits", "FITS maps", tools._fits, all_setpoints=True)
TIFF_MAPS = Tool("tiff-maps", "TIFF maps", tools._tiff_maps, all_setpoints=True)
