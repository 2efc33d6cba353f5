"""``emccdcal report RESULT [RESULT ...] -o report.html``: a self-contained HTML report.

One HTML file with everything embedded (figures as base64 PNG data URIs, inline CSS, no
script, no network): a summary table per result in both unit conventions (e⁻/ADU and
ADU/e⁻, the measured gain at every set-point with standard errors), the data-quality
warnings, a goodness-of-fit summary, the figures of :mod:`emccdcal.report.figures`, the bead
validation where a validation directory is given, the camera's history where a calibration
database is given (its calibrations and gain checks on one time axis, and what
``emccdcal db compare`` flags), and provenance (versions, every input
with its SHA-256, method, manifest hash, dates). ``docs/report.md`` describes it.

Sections carry stable ``id`` attributes (:data:`SECTION_IDS`) so that tools and tests can
find them. A figure that cannot be made — the raw data of a result moved or changed, no
per-set-point gains to plot — is left out with a note in the ``warnings`` section and a
:class:`ReportWarning`.

"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import math
import platform
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__, result
from .._output import OutputError, atomic_write_text, file_sha256, same_file
from .._util import progress as progress_bar
from ..beads.validation import data_checks, read_validation
from ..data import quality
from ..errors import EmccdcalWarning, InputError, OptionError
from ..result import format_setpoint
from .figures import (
    DataUnavailable,
    _estimated_phi,
    bead_consistency_figure,
    bead_intensity_figure,
    default_pixel,
    estimates_figure,
    figure_png,
    gain_figure,
    histogram_figure,
    maps_figure,
    photon_transfer_figure,
    results_gain_curve_figure,
    save_figure,
)

__all__ = ["SECTION_IDS", "REPORT_FILE", "ReportWarning", "build_report", "write_report"]

#: ``id`` of the report's top-level sections (``validation`` only with validation input,
#: ``history`` only with a calibration database).
SECTION_IDS = ("summary", "warnings", "gof", "figures", "validation", "history", "provenance")
#: File name of the report that ``calibrate --report`` and ``demo`` write.
REPORT_FILE = "report.html"


class ReportWarning(EmccdcalWarning):
    """Part of the report was left out (its data are missing); the report says why."""


@dataclass
class _Input:
    ds: object  # xarray.Dataset
    path: Path | None
    sha256: str | None
    label: str


def _refuse_twice(files) -> None:
    """A result given twice would be compared with itself: refused, naming both."""
    seen: dict = {}
    for path, digest in files:
        if digest in seen:
            raise OptionError(
                f"{path} is given twice (also as {seen[digest]}); give each result once"
            )
        seen[digest] = path


def _load_input(item, i):
    if hasattr(item, "data_vars"):  # in memory: its file, where it was read or written
        source = item.encoding.get("source")
        return _Input(
            item,
            Path(source).resolve() if source else None,
            item.encoding.get("sha256"),
            f"result {i + 1} ({item.attrs.get('method', '?')})",
        )
    ds = result.load(item)
    p = Path(item)
    p = p / result.CALIBRATION_FILE if p.is_dir() else p
    return _Input(ds, p.resolve(), ds.encoding["sha256"], f"result {i + 1} ({ds.attrs['method']})")


def _warnings_of(ds):
    w = ds.attrs.get("warnings", [])
    if isinstance(w, str):
        return [w] if w else []
    return [str(x) for x in np.atleast_1d(w)]


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


# --------------------------------------------------------------------------------------
# The camera's history (a calibration database)
# --------------------------------------------------------------------------------------
def _history(inputs, db, serial=None):
    """The history of each camera the results are of: (blocks, figure jobs).

    Each block is (HTML, the figure group that follows it or None). A camera is its
    serial (``serial``, else the one its files record) and read-out state; a result
    without a serial, or a camera the database does not hold, gets a note instead.
    """
    from ..export import database
    from .figures import gain_history_figure

    cameras, parts, jobs = {}, [], []
    for inp in inputs:
        camera = result.camera_of(inp.ds, inp.path or inp.label)
        if serial is not None:
            camera["serial"] = serial
        if not camera.get("serial"):
            parts.append(
                (
                    f"<p class=note>{_e(inp.label)}: its files record no camera "
                    "serial number, so its history cannot be looked up (give it)."
                    "</p>",
                    None,
                )
            )
            continue
        key = (str(camera["serial"]), database.readout_text(camera))
        cameras.setdefault(key, []).append(inp)
    for k, ((who, readout), mine) in enumerate(cameras.items()):
        state = f"camera {who}" + (f" ({readout})" if readout else "")
        try:
            found, findings = database.compare(who, db=db, readout=readout)
        except OptionError as exc:
            parts.append((f"<p class=note>{_e(state)}: {_e(str(exc))}.</p>", None))
            continue
        checked = database.checks(db=db, camera=who, readout=found[-1].readout)
        digests = {inp.sha256 for inp in mine if inp.sha256}
        rows = [
            [
                _e(e.date[:10]),
                "calibration" + (" (this result)" if digests & set(e.sha256.split(",")) else ""),
                _e(e.register),
                _e(
                    ", ".join(
                        f"{format_setpoint(s)}×: {_fmt(m)} ± {_fmt(se or 0, 2)}"
                        for s, (m, se, _) in sorted(e.gains.items())
                    )
                ),
            ]
            for e in found
        ]
        rows += [
            [
                _e(c.date[:10]),
                "gain check (dark frames)",
                _e(c.register),
                _e(f"{format_setpoint(c.setpoint)}×: {_fmt(c.em_gain)} ± {_fmt(c.se, 2)}"),
            ]
            for c in checked
        ]
        rows.sort(key=lambda r: r[0])
        flagged = (
            "<ul>" + "".join(f"<li class=warn>{_e(f.message)}</li>" for f in findings) + "</ul>"
            if findings
            else "<p>Nothing flagged: no change between calibrations, no check or trend "
            "beyond 3 standard errors.</p>"
        )
        parts.append(
            (
                f"<h3>{_e(state)}</h3>\n"
                + _table(["date", "kind", "register", "gain ± SE per set-point"], rows)
                + "\n"
                + flagged,
                f"history-{k + 1}",
            )
        )
        jobs.append(
            (
                f"history-{k + 1}",
                f"fig-history-{k + 1}",
                f"Gain history of {state}",
                (
                    "The sensor's gain at each set-point against the date, relative to the "
                    "first calibration (filled: calibrations, median over pixels with its "
                    "SE; open: gain checks from dark frames with their SE)."
                ),
                lambda found=found, checked=checked, who=who: gain_history_figure(
                    found, camera=who, checks=checked
                ),
            )
        )
    parts.append(
        (
            f"<p class=note>From the calibration database <span class=mono>"
            f"{_e(str(db))}</span> (emccdcal db compare; docs/gain-check.md).</p>",
            None,
        )
    )
    return parts, jobs


# --------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------
def _jobs(inputs, validations, pixel):
    """(group, figure id, title, caption, make) for every figure of the report."""
    jobs = []
    for i, inp in enumerate(inputs):
        ds, g = inp.ds, f"result-{i + 1}"
        px = pixel if pixel is not None else default_pixel(ds)
        where = f"pixel (row {px[0]}, col {px[1]})"
        jobs += [
            (
                g,
                f"fig-{g}-histograms",
                f"{inp.label}: counts and fitted pmf",
                (
                    f"Histogram of the counts of {where} in each acquisition (re-read from the raw "
                    "data) with the noise model at that pixel's fitted parameters."
                ),
                lambda ds=ds, px=px: histogram_figure(ds, px),
            ),
            (
                g,
                f"fig-{g}-histograms-log",
                f"{inp.label}: counts and fitted pmf, log scale",
                "The same on a logarithmic scale, to judge the tails.",
                lambda ds=ds, px=px: histogram_figure(ds, px, log=True),
            ),
            (
                g,
                f"fig-{g}-photon-transfer",
                f"{inp.label}: photon-transfer curve",
                (
                    f"Variance above read noise against offset-subtracted mean for {where}, one "
                    "point per acquisition with sampling SEs; solid lines: mean–variance fits, "
                    "dashed: the slopes implied by this result's fit."
                ),
                lambda ds=ds, px=px: photon_transfer_figure(ds, px),
            ),
            (
                g,
                f"fig-{g}-maps",
                f"{inp.label}: maps",
                (
                    "Per-pixel estimates, dark maps, convergence and goodness-of-fit p-values "
                    "over the sensor."
                ),
                lambda ds=ds: maps_figure(ds),
            ),
        ]
    datasets = [inp.ds for inp in inputs]
    labels = [inp.label for inp in inputs]
    jobs += [
        (
            "compare",
            "fig-estimates",
            "Distributions of the per-pixel estimates",
            (
                "Histograms over the converged pixels of φ and of the gain at each set-point, "
                "one line per result."
            ),
            lambda: estimates_figure(datasets, labels=labels),
        ),
        (
            "compare",
            "fig-gain",
            "Measured gain against set-point",
            (
                "Median over converged pixels with the median per-pixel SE as error bars; "
                "dotted: gain equal to the set-point."
            ),
            lambda: gain_figure(datasets, labels=labels),
        ),
    ]
    multiplied = {
        float(s) for ds in datasets if "em_gain" in ds for s in ds["setpoint"].values if s != 1
    }
    if len(multiplied) >= 2:  # a curve needs two set-points; without them, no figure
        jobs.append(
            (
                "compare",
                "fig-gain-curve",
                "Gain curve",
                (
                    "The measured gains of all results (median over converged pixels, SE of that "
                    "median) fitted as a smooth monotone function of the set-point, with its 95 % "
                    "band (docs/exports.md; emccdcal gain-curve predicts set-points not measured)."
                ),
                lambda: results_gain_curve_figure(datasets),
            )
        )
    for k, (d, _doc) in enumerate(validations):
        g = f"validation-{k + 1}"
        jobs += [
            (
                g,
                f"fig-{g}-intensities",
                f"Bead intensities per set-point ({d.name})",
                (
                    "Per-frame fitted intensity of one bead at each set-point under each "
                    "calibration; they coincide when the calibration is right."
                ),
                lambda d=d: bead_intensity_figure(d),
            ),
            (
                g,
                f"fig-{g}-consistency",
                f"Bead consistency ({d.name})",
                (
                    "Per-bead mean intensity relative to 1×, and the consistency metric of each "
                    "calibration."
                ),
                lambda d=d: bead_consistency_figure(d),
            ),
        ]
    return jobs


def build_report(
    results,
    *,
    validation=(),
    pixel=None,
    figures_dir=None,
    progress=True,
    command=None,
    db=None,
    camera=None,
):
    """The HTML text of a report of one or more calibration results: what
    :func:`write_report` writes, with the same parameters.
    """
    if isinstance(results, (str, Path)) or hasattr(results, "data_vars"):
        results = [results]  # one result, as calibrate() returns it or as a path
    if not results:
        raise OptionError("no calibration result given")
    inputs = [_load_input(r, i) for i, r in enumerate(results)]
    _refuse_twice([(inp.path, inp.sha256) for inp in inputs if inp.path is not None])
    notes = {}  # reason -> figure titles left out
    validations = []
    for d in map(Path, validation):
        try:
            validations.append((d, read_validation(d)[0]))
        except FileNotFoundError as exc:
            notes.setdefault(f"bead validation left out: {exc}", [])
    jobs = _jobs(inputs, validations, pixel)
    history, history_jobs = _history(inputs, db, camera) if db is not None else ([], [])
    jobs = progress_bar(jobs + history_jobs, enabled=progress, desc="report", unit="figure")
    figures = {}
    for group, fig_id, title, caption, make in jobs:
        try:
            fig = make()
        except (DataUnavailable, InputError, FileNotFoundError) as exc:
            notes.setdefault(str(exc), []).append(title)
            continue
        if figures_dir is not None:
            save_figure(fig, Path(figures_dir) / fig_id)
        figures.setdefault(group, []).append(_figure_html(fig_id, title, caption, figure_png(fig)))
    messages = [
        f"left out {len(t)} figure(s) ({'; '.join(t)}): {r}" if t else r for r, t in notes.items()
    ]
    for m in messages:
        warnings.warn(m, ReportWarning, stacklevel=2)

    def fig_section(group, heading):
        body = "\n".join(figures.get(group, [])) or "<p class=note>No figure (see warnings).</p>"
        return f'<section id="figures-{group}"><h3>{_e(heading)}</h3>\n{body}</section>'

    parts = [fig_section(f"result-{i + 1}", inp.label) for i, inp in enumerate(inputs)]
    parts.append(fig_section("compare", "All results compared"))
    title = "emccdcal calibration report: " + ", ".join(
        str(inp.ds.attrs.get("method")) for inp in inputs
    )
    sections = [
        ("summary", "Summary", "\n".join(_summary_html(inp) for inp in inputs)),
        ("warnings", "Warnings", _warnings_html(inputs, messages)),
        ("gof", "Goodness of fit", _gof_html(inputs)),
        ("figures", "Figures", "\n".join(parts)),
    ]
    if validations:
        vparts = [_validation_html(validations)] + [
            fig_section(f"validation-{k + 1}", f"Figures: {d}")
            for k, (d, _) in enumerate(validations)
        ]
        sections.append(("validation", "Bead validation", "\n".join(vparts)))
    if db is not None:
        sections.append(
            (
                "history",
                "Camera history",
                "\n".join(
                    text + ("" if group is None else "\n" + fig_section(group, "Gain history"))
                    for text, group in history
                ),
            )
        )
    sections.append(("provenance", "Provenance", _provenance_html(inputs, validations, command)))
    toc = " · ".join(f'<a href="#{sid}">{_e(h)}</a>' for sid, h, _ in sections)
    body = "\n".join(
        f'<section id="{sid}"><h2>{_e(h)}</h2>\n{content}</section>' for sid, h, content in sections
    )
    inputs_line = "; ".join(
        f"{_e(inp.label)}: <span class=mono>{_e(str(inp.path or '(in memory)'))}</span>"
        for inp in inputs
    )
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<meta name="generator" content="emccdcal {_e(__version__)}">'
        f'<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>\n"
        f"<header><h1>{_e(title)}</h1><p>{inputs_line}</p><nav>{toc}</nav></header>\n"
        f"{body}\n</body></html>\n"
    )


def write_report(
    results,
    out,
    *,
    validation=(),
    pixel=None,
    figures_dir=None,
    progress=True,
    command=None,
    db=None,
    camera=None,
) -> Path:
    """Write the HTML report of one or more calibration results to ``out``, atomically.

    Each result's verdict and medians first, then the warnings, goodness of fit, figures,
    bead validation, camera history and the provenance of every input (docs/report.md).

    Parameters
    ----------
    results : xarray.Dataset, str or Path, or a sequence of them
        Results as :func:`emccdcal.calibrate` returns them, or ``calibration.nc`` files
        (or their directories).
    out : str or Path
        The HTML file (its directory is created); an existing directory gets
        ``report.html`` inside it.
    validation : sequence of (str or Path), optional
        Bead-validation directories (``emccdcal validate -o DIR``: ``validation.json``,
        ``intensities.nc``). One without ``validation.json`` is left out with a note.
    pixel : (int, int), optional
        Sensor (row, col) index (pixel) of the single-pixel figures; default the centre
        (:func:`emccdcal.report.figures.default_pixel`).
    figures_dir : str or Path, optional
        Also write every figure there as PNG and SVG (``<figure id>.png``/``.svg``).
    progress : bool, optional
        A progress bar over the figures (default): in a notebook or on a terminal; none
        in a pipe.
    command : str, optional
        The command line, recorded in the provenance.
    db : str or Path, optional
        A calibration database (:mod:`emccdcal.export.database`): the report then shows
        the history of each result's camera (its calibrations and gain checks, and the
        findings of :func:`~emccdcal.export.database.compare`).
    camera : str, optional
        The cameras' serial number where their files record none (with ``db``).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ValueError
        An input that is not an emccdcal result or is from an incompatible version
        (:func:`emccdcal.result.load`, naming the file), or a malformed validation file.
    FileNotFoundError
        A result file that does not exist.

    Warns
    -----
    ReportWarning
        For each part left out, once per reason.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> emccdcal.write_report(ds, f"{work}/report.html", progress=False).name
    'report.html'
    """
    out = Path(out)
    if out.is_dir():
        out = out / REPORT_FILE
    read = result.result_files(results if isinstance(results, (list, tuple)) else [results])
    if any(f.exists() and same_file(out, f) for f in read):  # never over a result it reads
        raise OutputError(f"{out}: is a result this report reads, an input of this run")
    text = build_report(
        results,
        validation=validation,
        pixel=pixel,
        figures_dir=figures_dir,
        progress=progress,
        command=command,
        db=db,
        camera=camera,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, text)
    return out
