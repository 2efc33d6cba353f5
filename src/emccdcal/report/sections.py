"""The report's sections as HTML: the summary, the warnings, goodness of fit, provenance,
the validation and the figures' frames (each a function of the loaded inputs)."""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import math
import platform
from pathlib import Path

import numpy as np

from .. import __version__, result
from .._output import file_sha256
from ..beads.validation import data_checks
from ..data import quality
from ..data.telegraph import MAX_STATES
from ..result import format_setpoint
from ..result.flags import PIXEL_FLAGS
from .figures.common import _estimated_phi


# --------------------------------------------------------------------------------------
# HTML pieces
# --------------------------------------------------------------------------------------
_e = html.escape

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;max-width:1200px;margin:1.5em auto;
padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ccd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0 1em}th,td{border:1px solid #ccd;padding:.25em .6em;text-align:right}
th{background:#eef}td:first-child,th:first-child{text-align:left}
figure{margin:1em 0;padding:.5em;border:1px solid #dde}figure img{max-width:100%;height:auto;display:block}
figcaption{font-size:.9em;color:#444;margin-top:.4em}code,pre{font-size:.85em}
pre{background:#f6f6f8;padding:.6em;overflow-x:auto}.warn{color:#8a3b00}.note{color:#555}
table.kv td{text-align:left}
.mono{font-family:ui-monospace,monospace;font-size:.85em;word-break:break-all}
"""


def _fmt(x, digits=4):
    """``digits`` significant digits, in fixed notation unless very large or small."""
    if x is None or not np.isfinite(float(x)):
        return "–"
    x = float(x)
    if x == 0 or not 1e-4 <= abs(x) < 1e7:
        return f"{x:.{digits}g}"
    return f"{x:.{max(0, digits - 1 - math.floor(math.log10(abs(x))))}f}"


def _table(header, rows, cls=""):
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _stats(values, se, conv):
    """Median, median per-pixel SE, SD over pixels and n, over converged finite pixels."""
    values = np.asarray(values, dtype=float)
    m = conv & np.isfinite(values)
    v = values[m]
    out = {
        "n": int(v.size),
        "median": np.median(v) if v.size else np.nan,
        "sd": np.std(v, ddof=1) if v.size > 1 else np.nan,
        "se_median": np.nan,
    }
    if se is not None:
        s = np.asarray(se, dtype=float)[m]
        s = s[np.isfinite(s)]
        out["se_median"] = np.median(s) if s.size else np.nan
    return out


def _row(name, unit, st):
    return [name, unit, _fmt(st["median"]), _fmt(st["se_median"], 2), _fmt(st["sd"], 2), st["n"]]


def _flags_html(ds) -> list[str]:
    """A note on each kind of flagged pixel the darks showed, where they were looked for."""
    notes = []
    for name, (what, meaning, _) in PIXEL_FLAGS.items():
        if name not in ds:
            continue
        flags = ds[name].transpose("row", "col").values.astype(bool)
        where = np.argwhere(flags)[:8]
        named = ", ".join(f"({int(r)}, {int(c)})" for r, c in where) + (
            ", …" if flags.sum() > 8 else ""
        )
        notes.append(
            f"<p class=note>{what}: {int(flags.sum())} of {flags.size}"
            + (f", at (row, col) {_e(named)}" if flags.any() else "")
            + (_states_html(ds) if name == "telegraph" and flags.any() else "")
            + f"; {meaning} (variable <code>{name}</code>).</p>"
        )
    return notes


def _states_html(ds) -> str:
    """How many offset states the random-telegraph pixels hold, where counted."""
    if "telegraph_states" not in ds:
        return ""
    states = ds["telegraph_states"].values
    parts = [
        f"{k}{' or more' if k == MAX_STATES else ''} at {n} pixels"
        for k in range(2, MAX_STATES + 1)
        if (n := int(np.sum(states == k)))
    ]
    return " (offset states: " + ", ".join(parts) + "; variable <code>telegraph_states</code>)"


def _summary_html(inp):
    ds = inp.ds
    conv = ds["converged"].transpose("row", "col").values.astype(bool)
    grid = lambda name, **sel: ds[name].sel(**sel).transpose("row", "col").values
    phi, phi_se = grid("e_per_adu"), grid("e_per_adu_se")
    fitted = _estimated_phi(ds)
    phi_name = "φ, ADU conversion factor" + ("" if fitted else " (given, not fitted)")
    rows = [
        _row(phi_name, "e⁻/ADU", _stats(phi, phi_se, conv)),
        _row("1/φ", "ADU/e⁻", _stats(grid("adu_per_e"), grid("adu_per_e_se"), conv)),
    ]
    pe = ds["photoelectrons"]
    dim = next((d for d in pe.dims if d not in ("row", "col")), None)
    for v in [None] if dim is None else pe[dim].values:
        sel = {} if v is None else {dim: v}
        what = (
            ""
            if v is None
            else (f" at {format_setpoint(v)}×" if dim == "setpoint" else f", level {v}")
        )
        rows.append(
            _row(
                f"photoelectrons E{what}",
                "e⁻",
                _stats(grid("photoelectrons", **sel), grid("photoelectrons_se", **sel), conv),
            )
        )
    out = [
        f"<h3>{_e(inp.label)}</h3>",
        f"<p class=verdict><strong>{_e(result.verdict_line(ds))}</strong></p>",
        (
            f"<p>{int(conv.sum())} of {conv.size} pixels converged "
            f"({ds.sizes['row']} × {ds.sizes['col']} px); statistics are over the converged "
            "pixels: median, the median per-pixel standard error (SE), and the SD over "
            "pixels.</p>"
        ),
        *(
            [f"<p class=note>Standard errors {_e(ds.attrs['standard_errors'])}.</p>"]
            if ds.attrs.get("standard_errors")
            else []
        ),
        *_flags_html(ds),
        *(
            [
                f"<p class=note>Per-pixel intervals: {_e(ds.attrs['intervals'])} "
                "(variables <code>&lt;name&gt;_lower</code>, <code>&lt;name&gt;_upper</code> in "
                "the result file).</p>"
            ]
            if ds.attrs.get("intervals")
            else []
        ),
        _table(
            ["quantity", "unit", "median", "per-pixel SE (median)", "SD over pixels", "pixels"],
            [[_e(str(c)) for c in r] for r in rows],
        ),
    ]
    if "em_gain" in ds and np.any(ds["setpoint"].values != 1):
        phi_se0 = np.where(np.isfinite(phi_se), phi_se, 0.0)
        g_rows = []
        for s in ds["setpoint"].values:
            g, g_se = grid("em_gain", setpoint=s), grid("em_gain_se", setpoint=s)
            st = _stats(g, g_se, conv)
            with np.errstate(divide="ignore", invalid="ignore"):
                tot = _stats(g / phi, np.hypot(g_se / phi, g * phi_se0 / phi**2), conv)
                inv = _stats(phi / g, np.hypot(phi_se0 / g, phi * g_se / g**2), conv)
            g_rows.append(
                [
                    f"{format_setpoint(s)}×",
                    _fmt(st["median"]),
                    _fmt(st["se_median"], 2),
                    _fmt(st["sd"], 2),
                    _fmt(st["median"] / float(s)),
                    f"{_fmt(tot['median'])} ± {_fmt(tot['se_median'], 2)}",
                    f"{_fmt(inv['median'])} ± {_fmt(inv['se_median'], 2)}",
                    st["n"],
                ]
            )
        out.append(
            _table(
                [
                    "set-point",
                    "measured gain g",
                    "per-pixel SE (median)",
                    "SD over pixels",
                    "g / set-point",
                    "g/φ (ADU/e⁻)",
                    "φ/g (e⁻/ADU)",
                    "pixels",
                ],
                g_rows,
            )
        )
        out.append(
            "<p class=note>g is dimensionless. g/φ is the overall conversion at that "
            "set-point in counts per photoelectron (ADU/e⁻), φ/g its inverse in "
            "photoelectrons per count (e⁻/ADU)"
            + (
                ""
                if fitted or np.any(phi_se > 0)
                else "; φ was given without an uncertainty, so none is included"
            )
            + ".</p>"
        )
    return "\n".join(out)


def _warnings_html(inputs, notes):
    out = []
    if notes:
        out.append(
            "<h3>Left out of this report</h3><ul>"
            + "".join(f"<li class=warn>{_e(n)}</li>" for n in notes)
            + "</ul>"
        )
    for inp in inputs:
        ws = _warnings_of(inp.ds)
        out.append(f"<h3>{_e(inp.label)}</h3>")
        out.append(
            "<ul>" + "".join(f"<li class=warn>{_e(w)}</li>" for w in ws) + "</ul>"
            if ws
            else "<p>No warnings from the calibration.</p>"
        )
        q = inp.ds.attrs.get("quality")
        if q:
            try:
                text = quality.format_report(json.loads(q))
            except (ValueError, KeyError, TypeError):
                text = q  # a report of another layout: show it as it is
            out.append(
                f"<details><summary>data-quality checks</summary><pre>{_e(text)}</pre></details>"
            )
        else:
            out.append("<p class=note>The data-quality checks were not run for this result.</p>")
    return "\n".join(out)


def _gof_html(inputs):
    out = []
    for inp in inputs:
        ds = inp.ds
        if "gof_pvalue" not in ds:
            out.append(
                f"<p>{_e(inp.label)}: no goodness-of-fit test (mean–variance methods "
                "have no likelihood).</p>"
            )
            continue
        p = ds["gof_pvalue"]
        dim = next(d for d in p.dims if d not in ("row", "col"))
        rows = []
        for v in p[dim].values:
            x = np.asarray(p.sel({dim: v}).values, dtype=float).ravel()
            x = x[np.isfinite(x)]
            label = f"{format_setpoint(v)}×" if dim == "setpoint" else str(v)
            rows.append(
                [
                    _e(label),
                    x.size,
                    _fmt(np.median(x) if x.size else np.nan, 3),
                    f"{100 * np.mean(x < 0.01):.1f} %" if x.size else "–",
                    f"{100 * np.mean(x < 0.05):.1f} %" if x.size else "–",
                ]
            )
        out.append(f"<h3>{_e(inp.label)}</h3>")
        out.append(
            _table(
                [
                    dim,
                    "pixels tested",
                    "median p",
                    "p &lt; 0.01 (1 % expected)",
                    "p &lt; 0.05 (5 % expected)",
                ],
                rows,
            )
        )
    out.append(
        "<p class=note>Binned χ² test of each pixel's counts against the fitted "
        "noise model (docs/gof.md). Under a correct model the p-values are uniform: "
        "far more small ones than expected means the model misfits that acquisition."
        "</p>"
    )
    return "\n".join(out)


def _em_model_text(attrs) -> str:
    """The register model of a result, for the provenance table."""
    from ..model.noise import EMModel, RecordedEMModel

    model = EMModel.from_attrs(attrs)
    if model is None:
        return "– (no likelihood)"
    installed = not isinstance(model, RecordedEMModel)
    return model.register.description if installed else f"{model} (not installed here)"


def _manifest_status(ds):
    path = str(ds.attrs.get("manifest_path", ""))
    if not path or not Path(path).is_file():
        return "not found"
    same = file_sha256(path) == str(ds.attrs.get("manifest_sha256", ""))
    return "found, unchanged" if same else "found, CHANGED since the calibration"


def _provenance_html(inputs, validations, command):
    import matplotlib
    import xarray

    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    mono = lambda s: f"<span class=mono>{_e(str(s))}</span>"
    rows = [
        ["report written", now],
        ["by emccdcal", _e(__version__)],
        [
            "with",
            _e(
                f"Python {platform.python_version()}, NumPy {np.__version__}, "
                f"xarray {xarray.__version__}, matplotlib {matplotlib.__version__}"
            ),
        ],
    ]
    if command:
        rows.append(["command", mono(command)])
    out = [_table(["report", ""], rows, "kv")]
    for inp in inputs:
        a = inp.ds.attrs
        rows = [
            ["file", mono(inp.path or "(in memory)")],
            ["file SHA-256", mono(inp.sha256 or "–")],
            ["method", _e(str(a.get("method", "")))],
            ["EM register model", _e(_em_model_text(a))],
            ["written by emccdcal", _e(str(a.get("emccdcal_version", "")))],
            ["created", _e(str(a.get("created", "")))],
            ["calibration time", f"{_fmt(a.get('seconds'), 3)} s"],
            ["manifest", mono(a.get("manifest_path", ""))],
            ["manifest SHA-256", mono(a.get("manifest_sha256", ""))],
            ["manifest now", _e(_manifest_status(inp.ds))],
        ]
        if a.get("options"):
            rows.append(["options", mono(a["options"])])
        out.append(_table([_e(inp.label), ""], rows, "kv"))
    for d, _doc in validations:
        rows = [
            [name, mono(file_sha256(d / name))]
            for name in ("validation.json", "intensities.nc")
            if (d / name).is_file()
        ]
        out.append(_table([f"validation {_e(str(d))}", "SHA-256"], rows, "kv"))
    return "\n".join(out)


def _validation_html(validations):
    out = []
    for d, doc in validations:
        rank = {f: i + 1 for i, f in enumerate(doc.get("ranking", []))}
        rows = [
            [
                rank.get(c.get("file"), "–"),
                _e(str(c.get("method", ""))),
                f"<span class=mono>{_e(str(c.get('file', '')))}</span>",
                len(c["beads"]),
                _fmt(c.get("sigma_means_incl_1x")),
                _fmt(c.get("sigma_means_excl_1x")),
                "<br>".join(_e(x) for x in data_checks(c)) or "–",
            ]
            for c in doc["calibrations"]
        ]
        rows.sort(key=lambda r: (r[0] == "–", r[0] if r[0] != "–" else 0))
        out.append(f"<h3>{_e(str(d))}</h3>")
        out.append(
            _table(
                [
                    "rank",
                    "method",
                    "calibration",
                    "beads",
                    "σ of means incl. 1× (dimensionless)",
                    "σ of means excl. 1× (dimensionless)",
                    "the bead data",
                ],
                rows,
            )
        )
    out.append(
        "<p class=note>Beads imaged at every set-point must have the same intensity "
        "when the calibration is right: σ of means is the spread of a bead's "
        "per-set-point mean intensities, scaled to its 1× mean (lower is better; "
        "docs of <code>emccdcal validate</code>).</p>"
    )
    return "\n".join(out)


def _figure_html(fig_id, title, caption, png):
    data = base64.b64encode(png).decode("ascii")
    return (
        f'<figure id="{fig_id}"><img src="data:image/png;base64,{data}" '
        f'alt="{_e(title)}"><figcaption><b>{_e(title)}.</b> {_e(caption)}</figcaption>'
        "</figure>"
    )


def _warnings_of(ds):
    w = ds.attrs.get("warnings", [])
    if isinstance(w, str):
        return [w] if w else []
    return [str(x) for x in np.atleast_1d(w)]
