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

import warnings
from dataclasses import dataclass
from pathlib import Path


from .. import __version__, result
from .._output import OutputError, atomic_write_text, same_file
from .._util import progress as progress_bar
from ..beads.validation import read_validation
from ..errors import EmccdcalWarning, InputError, OptionError
from ..result import format_setpoint
from .sections import (
    _fmt,
    _table,
    _summary_html,
    _warnings_html,
    _gof_html,
    _provenance_html,
    _validation_html,
    _figure_html,
    _e,
    _CSS,
)
from .figures import (
    DataUnavailable,
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
