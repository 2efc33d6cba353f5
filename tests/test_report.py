"""Figures and the HTML report: content checked against the data, not just drawn."""

from __future__ import annotations

import base64
import hashlib
import io as _io
import json
import re
import warnings
from html.parser import HTMLParser
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import tifffile
import xarray as xr
from conftest import DEMO_COLS as COLS
from conftest import DEMO_ROWS as ROWS

from emccdcal._output import read_netcdf, write_netcdf
from emccdcal import calibrate, cli, result, write_report
from emccdcal.beads import validation
from emccdcal.data.manifest import read_manifest
from emccdcal.model import noise
from emccdcal.report import figures
from emccdcal.report import html as report_html
from emccdcal.report import sections as report_sections

PIXEL = (1, 2)  # not the centre, not on the diagonal


def write_validation(d, setpoints=(1, 5, 25), n_beads=3, frames=200, seed=0):
    """A validation directory in the contract of, with known numbers."""
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    truth = np.array([1000.0, 2000.0, 1500.0])[:n_beads]
    scale = {"A.nc": [1.0, 1.0, 1.0], "B.nc": [1.0, 0.9, 1.1]}  # B is inconsistent
    cals, cubes = [], []
    for file, sc in scale.items():
        cube = truth[:, None, None] * np.array(sc)[None, :, None] + rng.normal(
            0, 30, (n_beads, len(setpoints), frames)
        )
        cubes.append(cube)
        beads = []
        for b in range(n_beads):
            means = {str(s): float(cube[b, j].mean()) for j, s in enumerate(setpoints)}
            ses = {
                str(s): float(cube[b, j].std(ddof=1) / np.sqrt(frames))
                for j, s in enumerate(setpoints)
            }
            rel = np.array(list(means.values())) / means["1"]
            beads.append(
                {
                    "row": 10.0 + b,
                    "col": 20.0 + b,
                    "mean_intensity": means,
                    "mean_intensity_se": ses,
                    "sigma_means_incl_1x": float(rel.std(ddof=1)),
                    "sigma_means_excl_1x": float(rel[1:].std(ddof=1)),
                }
            )
        cals.append(
            {
                "file": file,
                "method": "gs" if file == "A.nc" else "mv-gain",
                "beads": beads,
                "sigma_means_incl_1x": float(np.mean([b["sigma_means_incl_1x"] for b in beads])),
                "sigma_means_excl_1x": float(np.mean([b["sigma_means_excl_1x"] for b in beads])),
            }
        )
    # what validate found about the bead data (validation.data_checks)
    cals[1]["blinking"] = {"frames_off": {"1": 3, "5": 0, "25": 0}, "beads": 1, "modelled": True}
    (d / "validation.json").write_text(
        json.dumps({"calibrations": cals, "ranking": ["A.nc", "B.nc"]})
    )
    write_netcdf(
        xr.Dataset(
            {
                "intensity": (
                    ("calibration", "bead", "setpoint", "frame"),
                    np.stack(cubes),
                    {"units": "e-"},
                )
            },
            coords={"calibration": list(scale), "setpoint": np.array(setpoints, float)},
        ),
        d / "intensities.nc",
    )
    return d, np.stack(cubes)


@pytest.fixture(scope="module")
def runs(demo_run):
    """Result directories of is-adu and gs (the demo's) and mv-adu; the demo's run."""
    run, _ = demo_run
    d = run["outdir"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calibrate(d / "adu-series" / "manifest.toml", "mv-adu", out=d / "result-mv-adu")
    return {m: d / f"result-{m}" for m in ("is-adu", "gs", "mv-adu")}, run


@pytest.fixture(scope="module")
def loaded(runs):
    return {m: result.load(p) for m, p in runs[0].items()}


def _visible_axes(fig):
    return [ax for ax in fig.axes if ax.get_visible()]


def _check_units(fig):
    """Every visible axis (colour bars included) has a label ending in '(unit)'."""
    for ax in _visible_axes(fig):
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            if ax.get_label() == "<colorbar>" and not label:
                continue  # the unlabelled long side of a colour bar
            assert re.search(r"\(.+\)$", label), f"axis label without unit: {label!r}"


# --------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------
def test_histogram_figure_shows_the_pixels_counts_and_its_fitted_pmf(loaded, runs):
    ds = loaded["gs"]
    stacks = sorted(
        (runs[1]["outdir"] / "gain-series").glob("gain-GS/*x-gain.tif"),
        key=lambda p: float(p.name.split("x")[0]),
    )
    fig = figures.histogram_figure(ds, PIXEL)
    axes = _visible_axes(fig)
    assert len(axes) == 5
    _check_units(fig)
    r, c = PIXEL
    for ax, sp, stack in zip(axes, ds.setpoint.values, stacks):
        # the data: exactly this pixel's counts, as probability per ADU
        (patch,) = [p for p in ax.patches]
        heights, edges = patch.get_data()[:2]
        counts = tifffile.imread(stack)[:, r, c]
        expect = np.histogram(counts, bins=edges)[0] / (counts.size * np.diff(edges))
        np.testing.assert_allclose(heights, expect)
        # the model: the noise model at this pixel's fitted parameters, under the
        # calibration's register (the default, the exact cascade)
        (line,) = ax.lines
        k = line.get_xdata()
        assert ds.attrs["em_model"] == "cascade"
        p = noise.pmf(
            k,
            float(ds.photoelectrons[r, c]),
            float(ds.em_gain.sel(setpoint=sp)[r, c]),
            float(ds.e_per_adu[r, c]),
            float(ds.offset.sel(setpoint=sp)[r, c]),
            float(ds.read_noise.sel(setpoint=sp)[r, c]),
            em_model=noise.EMModel.from_attrs(ds.attrs),
        )
        np.testing.assert_allclose(line.get_ydata(), p, rtol=1e-9)
        # ... and it describes the data: its mean within 4 SE of the counts' mean
        w = p / p.sum()
        assert abs((w * k).sum() - counts.mean()) < 4 * counts.std() / np.sqrt(counts.size)
    log = figures.histogram_figure(ds, PIXEL, log=True)
    assert all(ax.get_yscale() == "log" for ax in _visible_axes(log))


def test_photon_transfer_points_and_lines(loaded, runs):
    ds = loaded["is-adu"]
    r, c = PIXEL
    fig = figures.photon_transfer_figure(ds, PIXEL)
    _check_units(fig)
    (ax,) = _visible_axes(fig)
    points = [ln for ln in ax.lines if ln.get_marker() == "o"]
    x, y = points[0].get_xdata(), points[0].get_ydata()
    levels = [str(v) for v in ds.level.values]
    files = {
        a.level: a.frames_path
        for a in read_manifest(runs[1]["outdir"] / "adu-series" / "manifest.toml").acquisitions
    }
    for i, lev in enumerate(levels):
        counts = tifffile.imread(files[lev])[:, r, c].astype(float)
        s0 = float(ds.offset.sel(level=lev)[r, c])
        sig = float(ds.read_noise.sel(level=lev)[r, c])
        assert x[i] == pytest.approx(counts.mean() - s0)
        assert y[i] == pytest.approx(counts.var(ddof=1) - sig**2)
    solid, dashed = [ln for ln in ax.lines if ln.get_marker() != "o" and len(ln.get_xdata())]
    slope = lambda ln: np.diff(ln.get_ydata())[0] / np.diff(ln.get_xdata())[0]
    assert slope(solid) == pytest.approx(1 / 3.859, rel=0.2)  # mean-variance, truth 3.859
    assert slope(dashed) == pytest.approx(1 / float(ds.e_per_adu[r, c]))  # this fit's φ
    # a gain series: one point per set-point; dashed slope F²(g)·g/φ of the fit, F² of
    # the calibration's register (below 2 for the exact cascade, the default)
    gs = loaded["gs"]
    (ax,) = _visible_axes(figures.photon_transfer_figure(gs, PIXEL))
    dashed = [ln for ln in ax.lines if ln.get_linestyle() == "--" and len(ln.get_xdata())]
    g = gs.em_gain.values[1:, r, c]
    f2 = noise.excess_noise_factor(g, em_model=noise.EMModel.from_attrs(gs.attrs))
    assert np.all(f2 < 2)
    np.testing.assert_allclose([slope(ln) for ln in dashed[1:]], f2 * g / float(gs.e_per_adu[r, c]))


def test_estimates_figure_compares_methods(loaded):
    ds_list = [loaded["is-adu"], loaded["mv-adu"], loaded["gs"]]
    fig = figures.estimates_figure(ds_list)
    _check_units(fig)
    axes = _visible_axes(fig)
    assert [ax.get_title() for ax in axes] == ["ADU conversion factor φ"] + [
        f"EM gain at set-point {s}×" for s in (5, 25, 100, 300)
    ]
    # φ: is-adu and mv-adu (gs holds φ fixed); each histogram holds every converged pixel
    assert len(axes[0].patches) == 2
    legend = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert legend == [f"{m} (n = {int(loaded[m].converged.sum())})" for m in ("is-adu", "mv-adu")]
    legend5 = [t.get_text() for t in axes[1].get_legend().get_texts()]
    assert legend5[0].startswith("gs (n = ") and "set-point 5×" in legend5  # marked, nearby
    with pytest.raises(figures.DataUnavailable):
        figures.estimates_figure([loaded["gs"].drop_vars(["em_gain", "em_gain_se"])])


def test_maps_figure_draws_the_result_in_sensor_orientation(loaded):
    ds = loaded["gs"]
    fig = figures.maps_figure(ds)
    _check_units(fig)
    images = {ax.get_title(): ax.images[0].get_array() for ax in _visible_axes(fig) if ax.images}
    np.testing.assert_array_equal(images["g at 5×"], ds.em_gain.sel(setpoint=5).values)
    assert images["g at 5×"].shape == (ROWS, COLS)
    np.testing.assert_array_equal(
        images["gof p-value, 300×"], ds.gof_pvalue.sel(setpoint=300).values
    )
    assert f"converged: {int(ds.converged.sum())}/{ROWS * COLS}" in images
    assert "φ (given, not fitted)" in images  # gs holds φ
    # one dark for every level of the 1× series: one map, not six copies
    titles = [ax.get_title() for ax in _visible_axes(figures.maps_figure(loaded["is-adu"]))]
    assert "offset S0, every acquisition" in titles and "φ" in titles


def test_gain_figure_points_are_medians_with_se(loaded):
    gs = loaded["gs"]
    fig = figures.gain_figure([loaded["is-adu"], gs])  # is-adu has no gain: left out
    _check_units(fig)
    ax, ax2 = _visible_axes(fig)
    pts = [ln for ln in ax.lines if ln.get_marker() == "o"]
    assert len(pts) == 1
    conv = gs.converged.values
    med = np.median(gs.em_gain.values[:, conv], axis=1)
    np.testing.assert_allclose(pts[0].get_ydata(), med)
    np.testing.assert_allclose(pts[0].get_xdata(), gs.setpoint.values)
    ident = [ln for ln in ax.lines if ln.get_label() == "g = set-point"]
    np.testing.assert_allclose(ident[0].get_xdata(), ident[0].get_ydata())
    ratio = next(ln for ln in ax2.lines if ln.get_marker() == "o").get_ydata()
    np.testing.assert_allclose(ratio, med / gs.setpoint.values)
    with pytest.raises(figures.DataUnavailable):
        figures.gain_figure([loaded["is-adu"]])


def test_bead_figures_follow_the_validation_contract(tmp_path):
    d, cubes = write_validation(tmp_path / "val")
    fig = figures.bead_intensity_figure(d, bead=1)
    _check_units(fig)
    axes = _visible_axes(fig)
    assert len(axes) == 2  # one per calibration
    for ax, cube in zip(axes, cubes):
        hists = ax.patches
        assert len(hists) == 3  # one per set-point
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert legend == [f"{s}×: mean {cube[1, j].mean():.4g}" for j, s in enumerate((1, 5, 25))]
    fig = figures.bead_consistency_figure(d)
    _check_units(fig)
    ax, ax2 = _visible_axes(fig)
    doc = json.loads((d / "validation.json").read_text())
    for line, cal in zip([ln for ln in ax.lines if ln.get_marker() == "o"], doc["calibrations"]):
        rel = np.array(
            [
                [b["mean_intensity"][k] / b["mean_intensity"]["1"] for k in ("1", "5", "25")]
                for b in cal["beads"]
            ]
        )
        np.testing.assert_allclose(line.get_ydata(), rel.mean(axis=0))
    bars = [p.get_height() for p in ax2.patches]
    assert bars == pytest.approx(
        [c["sigma_means_incl_1x"] for c in doc["calibrations"]]
        + [c["sigma_means_excl_1x"] for c in doc["calibrations"]]
    )
    # a bead without data at a set-point (null) is left out of that set-point only
    doc["calibrations"][0]["beads"][0]["mean_intensity"]["25"] = None
    (d / "validation.json").write_text(json.dumps(doc))
    ax = _visible_axes(figures.bead_consistency_figure(d))[0]
    line = next(ln for ln in ax.lines if ln.get_marker() == "o")
    beads = doc["calibrations"][0]["beads"][1:]
    assert line.get_ydata()[2] == pytest.approx(
        np.mean([b["mean_intensity"]["25"] / b["mean_intensity"]["1"] for b in beads])
    )
    # frames whose fit did not converge are not shown
    ds = read_netcdf(d / "intensities.nc")
    ds["converged"] = xr.ones_like(ds.intensity, dtype=bool)
    ds["converged"][0, 1, 0, :50] = False
    write_netcdf(ds, d / "intensities.nc")
    shown = validation.read_validation(d)[1]
    assert int(np.isnan(shown[0, 1, 0]).sum()) == 50 and int(np.isnan(shown).sum()) == 50


def test_read_validation_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="validation.json"):
        validation.read_validation(tmp_path)
    (tmp_path / "validation.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"validation\.json: not a bead-validation file"):
        validation.read_validation(tmp_path)
    (tmp_path / "validation.json").write_text('{"calibrations": [{"file": "a"}]}')
    with pytest.raises(ValueError, match="not a bead-validation file"):
        validation.read_validation(tmp_path)
    (tmp_path / "validation.json").write_text('{"calibrations": []}')
    assert validation.read_validation(tmp_path)[1] is None  # intensities.nc is optional
    with pytest.raises(figures.DataUnavailable, match="intensities.nc"):
        figures.bead_intensity_figure(tmp_path)


def test_save_figure_writes_png_and_svg(loaded, tmp_path):
    png, svg = figures.save_figure(figures.gain_figure([loaded["gs"]]), tmp_path / "sub" / "gain")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert b"<svg" in svg.read_bytes()[:1000]
    assert sorted(p.name for p in png.parent.iterdir()) == ["gain.png", "gain.svg"]  # no temp left


# --------------------------------------------------------------------------------------
# The HTML report
# --------------------------------------------------------------------------------------
class _Parse(HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.imgs, self.tags, self.refs = [], [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if "id" in a:
            self.ids.append(a["id"])
        if tag == "img":
            self.imgs.append(a)
        self.refs += [v for k, v in a.items() if k in ("src", "href") and v]


@pytest.fixture(scope="module")
def full_report(runs):
    return runs[1]["report"].read_text(encoding="utf-8")


def test_demo_writes_a_self_contained_report_with_every_section_and_figure(
    full_report, runs, demo_run
):
    text = full_report
    run = runs[1]
    assert run["report"] == run["outdir"] / "report.html"
    assert demo_run[1].rstrip().endswith(f"report: {run['report']}")
    p = _Parse()
    p.feed(text)
    for sid in ("summary", "warnings", "gof", "figures", "provenance"):
        assert sid in p.ids
    assert "validation" not in p.ids  # no validation input: no such section
    want = [
        f"fig-result-{i}-{k}"
        for i in (1, 2)
        for k in ("histograms", "histograms-log", "photon-transfer", "maps")
    ]
    want += ["fig-estimates", "fig-gain", "fig-gain-curve"]
    assert set(want) <= set(p.ids)
    assert len(p.imgs) == len(want)
    for img in p.imgs:
        assert img["src"].startswith("data:image/png;base64,")
        pixels = matplotlib.image.imread(_io.BytesIO(base64.b64decode(img["src"].split(",", 1)[1])))
        assert pixels.shape[0] > 100 and pixels[..., :3].std() > 0.05  # decodes, not blank
    # nothing to fetch: no link, script or external reference
    assert not {"link", "script", "iframe"} & set(p.tags)
    assert all(r.startswith(("data:", "#")) for r in p.refs)
    assert "Left out of this report" not in text


def test_report_summary_and_provenance_hold_the_numbers(full_report, loaded, runs):
    text = full_report
    ds = loaded["is-adu"]
    phi = np.median(ds.e_per_adu.values[ds.converged.values])
    assert "e⁻/ADU" in text and "ADU/e⁻" in text
    assert f"<td>{report_sections._fmt(phi)}</td>" in text
    inv = np.median(ds.adu_per_e.values[ds.converged.values])  # median of 1/φ over pixels
    assert f"<td>1/φ</td><td>ADU/e⁻</td><td>{report_sections._fmt(inv)}</td>" in text
    gs = loaded["gs"]
    conv = gs.converged.values
    for s in (5, 25, 100, 300):
        g = np.median(gs.em_gain.sel(setpoint=s).values[conv])
        assert f"<td>{s}×</td><td>{report_sections._fmt(g)}</td>" in text
    for method in ("is-adu", "gs"):
        f = runs[0][method] / "calibration.nc"
        assert hashlib.sha256(f.read_bytes()).hexdigest() in text
        assert loaded[method].attrs["manifest_sha256"] in text
    from emccdcal import __version__

    assert f"<td>by emccdcal</td><td>{__version__}</td>" in text
    assert "found, unchanged" in text


def test_report_leaves_out_raw_data_figures_when_manifest_is_gone(loaded, tmp_path):
    moved = loaded["mv-adu"].copy()
    moved.attrs["manifest_path"] = str(tmp_path / "gone" / "manifest.toml")
    vdir, _ = write_validation(tmp_path / "val")
    with pytest.warns(report_html.ReportWarning) as rec:
        text = report_html.build_report([moved], validation=[vdir, tmp_path / "no-such-dir"])
    msgs = [str(w.message) for w in rec if issubclass(w.category, report_html.ReportWarning)]
    assert len(msgs) == 3  # one per reason, not one per figure
    assert "no-such-dir/validation.json: no such file" in msgs[0]
    assert msgs[1].startswith("left out 3 figure(s) (result 1 (mv-adu): counts and fitted pmf; ")
    assert msgs[1].endswith(
        "gone/manifest.toml: manifest of the mv-adu result not found "
        "(moved or deleted?); the raw data cannot be read"
    )
    assert "EM gain above 1×" in msgs[2]
    p = _Parse()
    p.feed(text)
    assert "fig-result-1-histograms" not in p.ids and "fig-result-1-photon-transfer" not in p.ids
    assert {
        "fig-result-1-maps",
        "fig-estimates",
        "validation",
        "fig-validation-1-intensities",
        "fig-validation-1-consistency",
    } <= set(p.ids)
    assert "not found (moved or deleted?)" in text and "Left out of this report" in text
    # validation: ranking table (A.nc first), what it found of the data, the files' hashes
    assert text.index("A.nc") < text.index("B.nc")
    assert "1 bead(s) blinking, 3 frame(s) off (on level taken)" in text
    assert hashlib.sha256((vdir / "intensities.nc").read_bytes()).hexdigest() in text


def test_raw_data_figures_refuse_a_changed_manifest(loaded):
    changed = loaded["gs"].copy()
    changed.attrs["manifest_sha256"] = "0" * 64
    with pytest.raises(figures.DataUnavailable, match="has changed since the gs calibration"):
        figures.histogram_figure(changed)
    with pytest.raises(ValueError, match=r"pixel \(9, 0\) is not in the result"):
        figures.photon_transfer_figure(loaded["gs"], (9, 0))


def test_report_cli_quiet_warns_once_and_rejects_bad_inputs(loaded, tmp_path, capsys):
    moved = loaded["mv-adu"].copy()
    moved.attrs["manifest_path"] = str(tmp_path / "nowhere.toml")
    result.save(moved, tmp_path / "res")
    out = tmp_path / "r.html"
    assert (
        cli.main(
            [
                "report",
                str(tmp_path / "res"),
                "-o",
                str(out),
                "--quiet",
                "--figures-dir",
                str(tmp_path / "figs"),
            ]
        )
        == 0
    )
    o, e = capsys.readouterr()
    assert o == "" and e.count("nowhere.toml") == 1 and e.startswith("warning: ")
    assert 'id="summary"' in out.read_text()
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == [
        f"fig-{n}.{x}" for n in ("estimates", "result-1-maps") for x in ("png", "svg")
    ]
    assert oct(out.stat().st_mode & 0o777) == "0o644"
    # not ours / not NetCDF / incompatible version / missing: one line, exit code 2
    (tmp_path / "text.nc").write_text("hello")
    write_netcdf(xr.Dataset({"x": ("a", [1.0])}), tmp_path / "other.nc")
    future = loaded["gs"].copy()
    future.attrs["emccdcal_version"] = "9.0.0"
    write_netcdf(future, tmp_path / "future.nc")
    for name, msg in (
        ("text.nc", "not an emccdcal result file"),
        ("other.nc", "not an emccdcal calibration result"),
        ("future.nc", "written by emccdcal 9.0.0, which is not compatible"),
        ("missing.nc", "no such file"),
    ):
        assert cli.main(["report", str(tmp_path / name), "-o", str(tmp_path / "x.html")]) == 2
        o, e = capsys.readouterr()
        assert e.count("\n") == 1 and name in e and msg in e, e
    assert not (tmp_path / "x.html").exists()
    assert cli.main(["report", str(tmp_path / "res"), "-o", str(out), "--pixel", "1"]) == 2
    assert "ROW,COL" in capsys.readouterr().err


@pytest.mark.slow
def test_calibrate_report_flag_writes_report_beside_result(runs, tmp_path, capsys):
    manifest = runs[1]["outdir"] / "adu-series" / "manifest.toml"
    code = cli.main(
        [
            "calibrate",
            str(manifest),
            "--method",
            "mv-adu",
            "-o",
            str(tmp_path / "o"),
            "--report",
            "--quiet",
            "--no-checks",
        ]
    )
    assert code == 0
    text = (tmp_path / "o" / "report.html").read_text()
    assert 'id="fig-result-1-photon-transfer"' in text and 'id="provenance"' in text
    # mv-adu has no gain: that figure is left out, said once on stderr
    err = capsys.readouterr().err
    assert err.count("EM gain above 1×") == 1


@pytest.mark.slow
def test_summary_says_what_the_standard_errors_include(tmp_path):
    from emccdcal import calibrate
    from emccdcal.report.html import write_report
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", rows=2, cols=2, frames=300, setpoints=(1, 100), seed=3, progress=False
    )
    calibrate(sim.manifest, "gs", out=tmp_path / "out", intervals="profile", checks=False)
    html = write_report([tmp_path / "out"], tmp_path / "r.html").read_text()
    assert "Standard errors include the errors of the offset and read-noise maps" in html
    assert "profile likelihood, 95 %" in html


def test_write_report_from_python_never_writes_over_a_result_it_reads(runs, tmp_path):
    """A notebook's ``write_report(ds, path)`` with the result's own file as ``path``
    (the Dataset as loaded, or the file given): refused, the result intact."""
    import shutil

    from emccdcal.errors import OptionError

    src = next(iter(runs[0].values()))
    shutil.copytree(src, tmp_path / "r")
    nc = tmp_path / "r" / result.CALIBRATION_FILE
    before = nc.read_bytes()
    for given in (result.load(nc), nc, tmp_path / "r"):
        with pytest.raises(OptionError, match="an input of this run"):
            write_report(given, nc, progress=False)
    assert nc.read_bytes() == before
