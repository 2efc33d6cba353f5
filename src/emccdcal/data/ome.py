"""Camera settings an OME-XML header records (an OME-TIFF from any writer).

The OME data model (schema 2016-06) describes the camera as an ``Instrument``'s
``Detector``: its ``Type`` (``CCD``, ``EMCCD``, ``CMOS``, ``IntensifiedCCD``, ``EBCCD`` …),
``Model`` and ``SerialNumber``; an image's ``Channel`` names the detector it was recorded
with in its ``DetectorSettings`` (with the ``Binning``, ``"2x2"``), and each ``Plane`` its
``ExposureTime`` (with ``ExposureTimeUnit``, seconds by default). The model names the kind
where it is one :func:`emccdcal.data.settings.kind_of_model` knows (an ORCA-Quest's
``C15550`` is a qCMOS, where its type says only ``CMOS``); else the type does. Nothing
here is an EM set-point: the model has no field that says one.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

from .settings import CameraSettings, kind_of_model, recorded_number

__all__ = ["settings_of"]

#: The kind of camera each OME detector type is (the others are not cameras this
#: package calibrates, or say nothing of one).
_TYPE_KINDS = {
    "EMCCD": "emccd",
    "CCD": "ccd",
    "CMOS": "scmos",
    "IntensifiedCCD": "iccd",
    "EBCCD": "iccd",
}
#: Milliseconds per unit of time the schema allows for an exposure.
_MS_PER = {"s": 1e3, "ms": 1.0, "µs": 1e-3, "us": 1e-3, "ns": 1e-6, "min": 6e4, "h": 3.6e6}


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def settings_of(xml: str) -> CameraSettings:
    """:class:`CameraSettings` from an OME-XML document's first image and its detector:
    empty where it names none, or is not XML.

    >>> xml = ('<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06">'
    ...        '<Instrument ID="Instrument:0"><Detector ID="Detector:0" Type="CMOS" '
    ...        'Model="C15550-20UP" SerialNumber="000123"/></Instrument>'
    ...        '<Image ID="Image:0"><Pixels><Channel><DetectorSettings ID="Detector:0" '
    ...        'Binning="2x2"/></Channel><Plane TheT="0" ExposureTime="20" '
    ...        'ExposureTimeUnit="ms"/></Pixels></Image></OME>')
    >>> s = settings_of(xml)
    >>> s.camera_kind, s.model, s.serial, s.binning, s.exposure_ms
    ('qcmos', 'C15550-20UP', '000123', (2, 2), 20.0)
    """
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError:
        return CameraSettings()
    elements = {}
    for element in root.iter():
        elements.setdefault(_local(element.tag), []).append(element)
    detectors = {d.get("ID"): d for d in elements.get("Detector", [])}
    used = elements.get("DetectorSettings", [])
    detector = detectors.get(used[0].get("ID")) if used else None
    if detector is None and len(detectors) == 1:
        detector = next(iter(detectors.values()))
    model = serial = kind = binning = None
    if detector is not None:
        model, serial = detector.get("Model"), detector.get("SerialNumber")
        kind = kind_of_model(model) or _TYPE_KINDS.get(detector.get("Type"))
    if used and used[0].get("Binning", "").count("x") == 1:
        x, y = used[0].get("Binning").split("x")
        binning = (int(x), int(y)) if x.isdigit() and y.isdigit() else None
    planes = elements.get("Plane", [])
    exposure = recorded_number(planes[0].get("ExposureTime")) if planes else None
    if exposure is not None:
        per = _MS_PER.get(planes[0].get("ExposureTimeUnit", "s"))
        exposure = None if per is None else exposure * per
    return CameraSettings(
        exposure_ms=exposure,
        serial=serial,
        model=model,
        binning=binning,
        camera_kind=kind,
    )
