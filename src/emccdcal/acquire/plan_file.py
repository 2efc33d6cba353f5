"""plan.toml: what ``emccdcal acquire`` executes and a person reads and edits.

:func:`plan_text` writes a :class:`~emccdcal.acquire.plan.Plan` as TOML, the stacks to
record with the precision predicted for each; :func:`read_plan` reads one back, edited or
not, and predicts its precision again.
"""

from __future__ import annotations


import numpy as np

from .. import _files, defaults
from .._util import check_int, check_number
from ..errors import OptionError
from .plan import (
    PLAN_METHODS,
    Plan,
    _FIRST_FRAMES,
    _camera_model,
    _offset_within_adc,
    _within_adc,
    check_camera_kind,
    predict,
)

__all__ = ["plan_text", "read_plan"]


# --------------------------------------------------------------------------------------
# plan.toml: what `acquire` executes and a person reads and edits
# --------------------------------------------------------------------------------------
def plan_text(p: Plan) -> str:
    """The plan as TOML: the stacks to record, with the precision predicted for each.

    A gain series has one ``photoelectrons`` (the light, at 1×) and an
    ``[[acquisition]]`` per set-point; an intensity series an ``[[level]]`` per light
    level at its one ``em_gain_setpoint``. ``dark_frames`` is per dark stack: one per
    set-point of a gain series, one for an intensity series.
    """
    from .. import __version__
    from .._output import toml_line

    def line(key, value, note=""):
        text = toml_line(key, round(value, 6) if isinstance(value, float) else value)
        return text + (f"  # {note}" if note else "")

    cam = p.camera
    worst = {"gs": "em_gain", "is-gain": "em_gain", "is-adu": "e_per_adu"}[p.method]
    out = [
        f"# Written by emccdcal {__version__} (emccdcal plan): the acquisition that reaches "
        f"the target at least cost,",
        "# predicted from the Fisher information of the likelihood the calibration uses.",
        "# Edit the frames or the light and run `emccdcal plan --check` on the file to see "
        "what they give.",
        line("method", p.method),
    ]
    if p.method == "gs":
        out.append(
            line(
                "photoelectrons",
                p.photoelectrons,
                "e- per pixel per frame to set the light to (at 1x)",
            )
        )
        out.append(line("dark_frames", p.dark_frames, "per set-point, shutter closed"))
    else:
        out.append(line("em_gain_setpoint", p.acquisitions[0].setpoint))
        out.append(line("dark_frames", p.dark_frames, "one dark stack, shutter closed"))
    if p.target_se == p.target_se:  # a target was set (TOML has no NaN a reader takes)
        out.append(
            line("target_se", p.target_se, f"percent: relative SE per pixel of every {worst}")
        )
    out.append(line(f"predicted_{worst}_se", p.predicted_se, "percent, per pixel (worst)"))
    if p.target_se == p.target_se:
        out.append(line("reached", p.reached))
    out.append(line("total_frames", p.total_frames, "light and dark"))
    if p.frame_rate_hz is not None:
        out.append(line("frame_rate_hz", p.frame_rate_hz, "frames per second"))
        out.append(line("seconds", p.seconds, "to record it all at that rate"))
    if p.max_frames is not None:
        out.append(line("max_frames", p.max_frames, "per stack"))
    out += [
        "",
        "[camera]  # what the plan assumed",
        line("e_per_adu", cam["e_per_adu"], "e-/ADU"),
        line("read_noise", cam["read_noise"], "ADU"),
        line("offset", cam["offset"], "ADU"),
        line("adc_bits", cam["adc_bits"]),
        line("em_model", cam["em_model"]),
    ]
    if cam.get("camera_kind") is not None:
        out.append(line("camera_kind", cam["camera_kind"]))
    if cam.get("stages") is not None:
        out.append(line("stages", cam["stages"]))
    for well in ("pixel_well", "register_well"):
        if cam.get(well) is not None:
            out.append(line(well, cam[well], "e-"))
    table = "acquisition" if p.method == "gs" else "level"
    for a in p.acquisitions:
        out += ["", f"[[{table}]]"]
        if p.method == "gs":
            out.append(line("em_gain_setpoint", a.setpoint))
        else:
            out.append(line("photoelectrons", a.photoelectrons, "e- per pixel per frame"))
        out.append(line("frames", a.frames))
        if a.setpoint != 1:
            out.append(line("assumed_em_gain", a.em_gain, "the true gain the plan assumed"))
        for name, se in a.predicted_se.items():
            if name == worst and p.method != "gs":
                continue
            out.append(line(f"predicted_{name}_se", se, "percent, per pixel"))
    return "\n".join(out) + "\n"


def read_plan(path) -> Plan:
    """A plan file (:func:`plan_text`), edited or not, with its precision predicted again
    for what it now says.

    Raises
    ------
    InputError
        Not a plan, or a value out of range, naming the file and the key.
    """
    from pathlib import Path

    from ..errors import InputError

    path = Path(path)
    doc = _files.load_toml(path, what="plan")

    def need(table, key, where):
        if key not in table:
            raise InputError(f"'{path}': {where} has no {key}")
        return table[key]

    try:
        method = need(doc, "method", "the plan")
        if method not in PLAN_METHODS:
            raise OptionError(f"method {method!r} is not one of {', '.join(PLAN_METHODS)}")
        cam = _table(need(doc, "camera", "the plan"), "[camera]")
        camera = {
            "e_per_adu": check_number(
                "e_per_adu", need(cam, "e_per_adu", "[camera]"), positive=True
            ),
            "read_noise": check_number(
                "read_noise", need(cam, "read_noise", "[camera]"), positive=True
            ),
            "offset": check_number("offset", need(cam, "offset", "[camera]"), minimum=0),
            "adc_bits": check_int(
                "adc_bits", need(cam, "adc_bits", "[camera]"), minimum=2, maximum=32
            ),
            "em_model": str(cam.get("em_model", defaults.DEFAULT_EM_MODEL)),
            "stages": None
            if cam.get("stages") is None
            else check_int("stages", cam["stages"], minimum=1, maximum=defaults.MAX_STAGES),
            **{
                well: None
                if cam.get(well) is None
                else check_number(well, cam[well], positive=True)
                for well in ("pixel_well", "register_well")
            },
        }
        camera["camera_kind"] = cam.get("camera_kind")
        check_camera_kind(camera["camera_kind"], method)
        _offset_within_adc(camera)
        model = _camera_model(camera)
        camera["stages"] = model.stages if model.register.uses_stages else None
        table = "acquisition" if method == "gs" else "level"
        rows = doc.get(table) or []
        if not isinstance(rows, list):
            raise OptionError(f"{table} must be [[{table}]] tables, not {type(rows).__name__}")
        rows = [_table(r, f"each [[{table}]]") for r in rows]
        if not rows:
            raise OptionError(f"no [[{table}]] tables")
        frames = [check_int("frames", need(r, "frames", f"[[{table}]]"), minimum=2) for r in rows]
        if method == "gs":
            light = [
                check_number(
                    "photoelectrons", need(doc, "photoelectrons", "the plan"), positive=True
                )
            ] * len(rows)
            sps = [
                check_number(
                    "em_gain_setpoint", need(r, "em_gain_setpoint", "[[acquisition]]"), minimum=1.0
                )
                for r in rows
            ]
        else:
            s = check_number("em_gain_setpoint", doc.get("em_gain_setpoint", 1.0), minimum=1.0)
            light = [
                check_number(
                    "photoelectrons", need(r, "photoelectrons", "[[level]]"), positive=True
                )
                for r in rows
            ]
            sps = [s] * len(rows)
        gains = [
            1.0
            if s == 1
            else check_number("assumed_em_gain", r.get("assumed_em_gain", s), minimum=1.0)
            for s, r in zip(sps, rows)
        ]
        dark = check_int("dark_frames", need(doc, "dark_frames", "the plan"), minimum=2)
        target = (
            float("nan")
            if doc.get("target_se") is None
            else check_number("target_se", doc["target_se"], positive=True)
        )
        rate = doc.get("frame_rate_hz")
        rate = None if rate is None else check_number("frame_rate_hz", rate, positive=True)
        most = doc.get("max_frames")
        most = None if most is None else check_int("max_frames", most, minimum=_FIRST_FRAMES)
        if len(set(sps)) < len(sps) and method == "gs":
            raise OptionError("a set-point is listed twice among the [[acquisition]] tables")
        _within_adc(sps, gains, light, camera)
        return predict(
            method,
            sps,
            gains,
            light,
            frames,
            dark,
            camera,
            target,
            frame_rate_hz=rate,
            max_frames=most,
        )
    except OptionError as exc:
        raise InputError(f"'{path}': {exc}") from None
    except np.linalg.LinAlgError:  # a light or a frame count that carries no information
        raise InputError(
            f"'{path}': its light and frames determine no estimate (the information is "
            "singular): is the light far too faint, or are the frames too few?"
        ) from None


def _table(value, where: str) -> dict:
    """A TOML table of a plan, or a one-line error naming where it should be."""
    if not isinstance(value, dict):
        raise OptionError(f"{where} must be a table, not {type(value).__name__} {value!r}")
    return value
