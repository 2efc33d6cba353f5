"""The napari plugin (extra ``napari``): its manifest, reader, sample data and widgets.

A viewer needs OpenGL: the tests start their own X server (Xvfb, with Mesa's software
OpenGL) on a display it picks, and stop it at the end. Without napari (``pip install
'.[napari-test]'``) or without Xvfb (Debian's ``xvfb``; ``.ci/run`` installs both) they
skip with the reason. ``EMCCDCAL_DOC_FIGURES=1`` also copies the screenshots they take
into docs/figures/napari/.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari", reason="napari is not installed (extra [napari-test])")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed (extra [napari-test])")

from camera_files import write_fits, write_micromanager_tiff, write_spe, write_zarr  # noqa: E402

from emccdcal import cli  # noqa: E402
from emccdcal.data.stacks import load_stack  # noqa: E402

pytestmark = pytest.mark.skipif(
    shutil.which("Xvfb") is None, reason="no Xvfb on this machine (Debian package 'xvfb')"
)
DOC_FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures" / "napari"


@pytest.fixture(scope="session")
def display():
    """An X server of our own (Xvfb, no TCP) for the session's Qt application."""
    read, write = os.pipe()
    server = subprocess.Popen(
        ["Xvfb", "-displayfd", str(write), "-screen", "0", "1400x1000x24", "-nolisten", "tcp"],
        pass_fds=[write],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    if not number:
        server.kill()
        pytest.skip("Xvfb did not start")
    saved = {k: os.environ.get(k) for k in ("DISPLAY", "QT_QPA_PLATFORM")}
    os.environ.update(DISPLAY=f":{number}", QT_QPA_PLATFORM="xcb")
    # Qt aborts the process when its platform plugin cannot load (missing xcb libraries):
    # try it in a child first, so that such a machine skips instead of losing a worker.
    probe = subprocess.run(
        [
            sys.executable,
            "-c",
            "from qtpy.QtWidgets import QApplication\n"
            "from qtpy.QtGui import QOpenGLContext\napp = QApplication([])\n"
            "assert QOpenGLContext().create(), 'no OpenGL context'",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    if probe.returncode != 0:
        server.terminate()
        server.wait(10)
        os.environ.update({k: v for k, v in saved.items() if v is not None})
        pytest.skip(f"Qt cannot open the X display: {probe.stderr.strip()[-300:]}")
    yield f":{number}"
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
    server.terminate()
    server.wait(10)


@pytest.fixture(scope="session")
def qapp(display, qapp_args, qapp_cls):
    """pytest-qt's application, made once the display is there."""
    from qtpy.QtWidgets import QApplication

    return QApplication.instance() or qapp_cls(qapp_args)


def _screenshot(viewer, name, tmp_path):
    path = tmp_path / f"{name}.png"
    viewer.screenshot(path=str(path), canvas_only=False, flash=False)
    assert path.stat().st_size > 10_000
    if os.environ.get("EMCCDCAL_DOC_FIGURES"):
        DOC_FIGURES.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, DOC_FIGURES / path.name)
    return path


# --------------------------------------------------------------------------------------
# Manifest and discovery; nothing imported by the package or the command line
# --------------------------------------------------------------------------------------
def test_the_manifest_is_valid_and_napari_finds_the_plugin():
    run = subprocess.run(
        [sys.executable, "-m", "npe2", "validate", "emccdcal"], capture_output=True, text=True
    )
    assert run.returncode == 0 and "valid" in run.stdout, run.stdout + run.stderr
    from npe2 import PluginManager

    manager = PluginManager()
    manager.discover()
    assert "emccdcal" in manager.iter_manifests() or "emccdcal" in {
        m.name for m in manager.iter_manifests()
    }
    widgets = {w.display_name for w in manager.iter_widgets()}
    assert {"Calibrate", "Counts to photoelectrons", "Gain check (dark frames)"} <= widgets


def test_emccdcal_and_its_command_line_never_import_napari_or_qt():
    code = (
        "import sys, emccdcal, emccdcal.cli\n"
        "from emccdcal import calibrate, load_result\n"
        "try:\n    emccdcal.cli.main(['gain-check', '--help'])\nexcept SystemExit:\n    pass\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in "
        "('napari', 'PyQt6', 'PyQt5', 'PySide6', 'qtpy', 'magicgui', 'vispy')]\n"
        "assert not bad, bad\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


# --------------------------------------------------------------------------------------
# The reader
# --------------------------------------------------------------------------------------
def _stack(em_gain=300, frames=6, seed=1):
    rng = np.random.default_rng(seed)
    return rng.integers(400, 700, size=(frames, 8, 10)).astype(np.uint16)


@pytest.mark.parametrize("kind", ["spe", "sif", "ome.tif", "fits", "zarr"])
def test_the_reader_opens_each_format_lazily_with_its_settings(kind, tmp_path):
    from emccdcal.napari._reader import get_reader

    data = _stack()
    if kind == "spe":
        path = write_spe(tmp_path / "s.spe", data, em_gain=300)
    elif kind == "sif":
        path = Path(__file__).with_name("data") / "sif" / "test.sif"
    elif kind == "ome.tif":
        path = write_micromanager_tiff(tmp_path / "s.ome.tif", data, em_gain=300, roi="64-32-10-8")
    elif kind == "fits":
        pytest.importorskip("astropy")
        path = write_fits(tmp_path / "s.fits", data, em_gain=300)
    else:
        pytest.importorskip("zarr")
        path = write_zarr(tmp_path / "s.zarr", data, em_gain=300)
    reader = get_reader(str(path))
    assert reader is not None
    (layer,) = reader(str(path))
    array, kwargs, kind_ = layer
    assert kind_ == "image" and type(array).__module__.startswith("dask")
    np.testing.assert_array_equal(np.asarray(array), np.asarray(load_stack(path)))
    camera = kwargs["metadata"]["camera"]
    if kind != "sif":
        assert camera["em_gain_setpoint"] == 300
    if kind == "ome.tif":  # the region it records of the sensor: where the layer lies
        assert kwargs["translate"] == (0, 32, 64) and kwargs["scale"] == (1, 1, 1)
    assert get_reader(str(tmp_path / "notes.txt")) is None


# --------------------------------------------------------------------------------------
# The widgets
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The plugin's sample data (a simulated gain series) and its calibration by the
    command line: (layers, manifest, result folder)."""
    from emccdcal.napari._sample import gain_series

    base = tmp_path_factory.mktemp("napari")
    layers = gain_series(base / "sample")
    manifest = Path(layers[0][1]["metadata"]["emccdcal_manifest"])
    assert cli.main(["calibrate", str(manifest), "-o", str(base / "cli"), "-q"]) == 0
    return layers, manifest, base / "cli"


def _wait(qtbot, widget, timeout=180_000):
    """Until the widget's job has ended and the widget said so."""
    qtbot.waitUntil(lambda: not widget.status.value.endswith("…"), timeout=timeout)


@pytest.mark.slow
def test_the_calibrate_widget_matches_the_command_line_and_keeps_the_viewer_drawing(
    sample, make_napari_viewer, qtbot, tmp_path
):
    """The sample data calibrated by the widget: the layers hold the command line's
    numbers; the event loop keeps running while the worker fits (a timer's ticks); the
    report and a Picasso file written from the widget."""
    from qtpy.QtCore import QTimer

    from emccdcal import load_result
    from emccdcal.napari._widgets import CalibrateWidget

    layers, manifest, cli_result = sample
    viewer = make_napari_viewer()
    for data, kwargs, _ in layers:
        viewer.add_image(data, **kwargs)
    widget = CalibrateWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Calibrate")
    assert Path(widget.source.value) == manifest  # the sample names its manifest
    widget.scan()
    assert "5 acquisition(s)" in widget.found.value
    widget.out.value = tmp_path / "widget"
    ticks = []
    timer = QTimer()
    timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
    timer.start(20)
    t0 = time.perf_counter()
    ended = []
    widget.run().returned.connect(lambda *_: ended.append(time.perf_counter()))
    # the worker's run: until its result reaches the viewer (the result's layers then
    # take napari a moment each to draw, under software OpenGL up to a second: drawing,
    # not the widget's work)
    qtbot.waitUntil(
        lambda: bool(ended) or widget.status.value.startswith("error"), timeout=180_000
    )  # (the status may say "adding" before the signal)
    timer.stop()
    assert ended, widget.status.value
    elapsed = ended[0] - t0
    ticks = [t for t in ticks if t <= ended[0]]
    _wait(qtbot, widget)
    assert widget.status.value.startswith("done"), widget.status.value
    # the viewer's event loop ran throughout: ticks every 20 ms, no gap of a second
    gaps = np.diff(ticks)
    print(
        f"event loop during the run: {len(ticks)} ticks in {elapsed:.1f} s, longest gap "
        f"{1000 * gaps.max():.0f} ms (at {ticks[int(np.argmax(gaps))] - t0:.1f} s), median "
        f"{1000 * np.median(gaps):.0f} ms"
    )
    assert len(ticks) > 0.5 * elapsed / 0.02 and gaps.max() < 1.0
    ours, theirs = load_result(widget.result), load_result(cli_result)
    for s in (5, 25, 100, 300):
        layer = viewer.layers[f"gs: gain at {s}x"]
        want = np.where(theirs.converged, theirs.em_gain.sel(setpoint=s), np.nan)
        np.testing.assert_array_equal(layer.data, want)
        np.testing.assert_array_equal(ours.em_gain.sel(setpoint=s), theirs.em_gain.sel(setpoint=s))
    assert viewer.layers["gs: gain at 300x"].colorbar.visible
    widget.write_report()
    assert (tmp_path / "widget" / "report.html").is_file()
    widget.setpoint.value = "300"
    widget.export()
    assert (tmp_path / "widget" / "export-picasso" / "picasso-config.yaml").is_file()
    _screenshot(viewer, "calibrate", tmp_path)


@pytest.mark.slow
def test_a_run_cancelled_midway_ends_quietly(sample, make_napari_viewer, qtbot, tmp_path):
    from emccdcal.napari._widgets import CalibrateWidget

    _, manifest, _ = sample
    widget = CalibrateWidget(make_napari_viewer())
    widget.source.value = manifest
    widget.out.value = tmp_path / "w"
    widget.run()
    qtbot.waitUntil(lambda: widget.bar.value > 0, timeout=60_000)
    widget.cancel_button.changed.emit(True)  # the Cancel button
    _wait(qtbot, widget)
    assert widget.status.value == "cancelled: nothing was written"
    assert widget.result is None and not (tmp_path / "w" / "result" / "calibration.nc").exists()


@pytest.mark.slow  # the sample data's calibration, built once for the widget tests
def test_the_calibrate_widget_writes_over_nothing_it_did_not_write(
    sample, qapp, tmp_path, monkeypatch
):
    """A folder scanned into an output folder that holds the user's manifest.toml (or
    report.html, or an export): refused with one line, the files untouched; a widget
    without an output folder takes a new temporary one for each run."""
    from emccdcal.napari._widgets import CalibrateWidget, _reporting

    _, manifest, result = sample
    widget = CalibrateWidget()
    widget.source.value = manifest.parent / "gain-GS"  # a folder: scanned into the output
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "manifest.toml").write_text("# the user's own\n")
    widget.out.value = mine
    _reporting(widget, widget.run)()
    assert widget.status.value.startswith("error:") and "manifest.toml" in widget.status.value
    assert (mine / "manifest.toml").read_text() == "# the user's own\n"
    widget.result = result  # as if a run had written it there
    (result.parent / "report.html").write_text("theirs")
    _reporting(widget, widget.write_report)()
    assert widget.status.value.startswith("error:") and "report.html" in widget.status.value
    assert (result.parent / "report.html").read_text() == "theirs"
    (result.parent / "report.html").unlink()
    widget.write_report()  # once written by the widget, it may replace it
    widget.write_report()
    assert "wrote" in widget.status.value
    import tempfile

    # the widget's own temporary folders, made where this test cleans up
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    fresh = CalibrateWidget()  # no output folder chosen
    first = fresh._out()
    assert first != fresh._out() and first.name.startswith("emccdcal-calibration-")
    # a folder calibrated without an output folder: its manifest and result side by side
    made = lambda: set(Path(tempfile.gettempdir()).glob("emccdcal-calibration-*"))  # noqa: E731
    before = made()
    run = CalibrateWidget()
    run.source.value = manifest.parent / "gain-GS"
    run.job.start = lambda work, done, what: None  # the setting-up only, not the fit
    run.run()
    (folder,) = made() - before
    assert (folder / "manifest.toml").is_file() and Path(run.out.value) == folder


@pytest.mark.slow
def test_the_apply_widget_gives_what_apply_gives(sample, make_napari_viewer, tmp_path):
    """A movie opened through the reader, converted by the widget: the photoelectrons
    (and, with a QE, the photons) of ``emccdcal apply``."""
    import tifffile

    from emccdcal.napari._widgets import ApplyWidget
    from emccdcal.simulate.camera import simulate_frames

    _, _, result = sample
    movie = write_micromanager_tiff(
        tmp_path / "movie.ome.tif",
        simulate_frames(40.0, 260.0, 3.859, 560.0, 15.5, frames=20, rows=32, cols=32, seed=3),
        em_gain=300,
    )
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(movie), plugin="emccdcal")
    widget = ApplyWidget(viewer)
    widget.reset_choices()
    widget.layer.value = layer
    widget.result.value = result
    for qe, suffix in ((None, "e-"), (0.8, "photons")):
        widget.qe.value = "" if qe is None else str(qe)
        out = widget.convert()
        assert out.name == f"movie.ome.tif ({suffix})", widget.status.value
        args = ["apply", str(result), str(movie), "-o", str(tmp_path / f"{suffix}.tif"), "-q"]
        assert cli.main(args + ([] if qe is None else ["--qe", str(qe)])) == 0
        np.testing.assert_array_equal(
            np.asarray(out.data), tifffile.imread(tmp_path / f"{suffix}.tif")
        )


@pytest.mark.slow
def test_the_gain_check_widget_on_a_dark_layer(sample, make_napari_viewer, qtbot, tmp_path):
    from emccdcal.napari._widgets import GainCheckWidget

    _, manifest, result = sample
    viewer = make_napari_viewer()
    (layer,) = viewer.open(
        str(manifest.parent / "gain-GS" / "300x-gain_no-signal.tif"), plugin="emccdcal"
    )
    widget = GainCheckWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Gain check")
    widget.reset_choices()
    widget.layer.value = layer
    widget.result.value = result
    widget.setpoint.value = "300"
    widget.run()
    _wait(qtbot, widget)
    assert widget.status.value == "done", widget.status.value
    assert "em_gain" in widget.answer.value and "calibration of" in widget.answer.value
    _screenshot(viewer, "gain-check", tmp_path)


def test_every_widget_error_path_is_one_line_on_the_widget(sample, make_napari_viewer, qtbot):
    """A layer with no file and no set-point, a missing calibration, another camera's
    darks: each one line on the widget's status in the widget's words (its fields, not
    the command line's flags), the status never left at "…", nothing reaching Qt."""
    from emccdcal.napari._widgets import ApplyWidget, GainCheckWidget

    _, _, result = sample
    viewer = make_napari_viewer()
    plain = viewer.add_image(np.full((30, 32, 32), 600, np.uint16), name="plain")
    check = GainCheckWidget(viewer)
    check.reset_choices()
    check.layer.value, check.result.value = plain, result
    check.button.native.click()
    assert check.status.value.startswith("error:"), check.status.value
    assert "'set-point' field" in check.status.value and "--setpoint" not in check.status.value
    check.result.line_edit.value, check.setpoint.value = "", "300"
    check.button.native.click()
    assert check.status.value == "error: give e-/ADU or a calibration of the camera"
    camera = viewer.add_image(
        np.full((30, 32, 32), 600, np.uint16),
        name="cam-b",
        metadata={"camera": {"serial": "CAM-B"}},
    )
    check.reset_choices()
    check.layer.value, check.result.value = camera, result
    check.button.native.click()  # the sample's calibration records no camera: said
    _wait(qtbot, check)
    assert not check.status.value.endswith("…")
    from emccdcal.napari._widgets import CalibrateWidget

    docked = CalibrateWidget(viewer)  # docked before any sample or folder was chosen
    docked.run_button.native.click()
    assert docked.status.value == "error: choose a folder of camera files or a manifest"
    convert = ApplyWidget(viewer)
    convert.reset_choices()
    convert.layer.value, convert.result.value = plain, result
    convert.button.native.click()
    assert (
        convert.status.value.startswith("error:") and "'set-point' field" in convert.status.value
    ), convert.status.value


def test_every_widget_taking_a_calibration_checks_the_camera(make_napari_viewer, qtbot, tmp_path):
    """The identity guarantee holds in the plugin as on the command line: each widget with
    a calibration field refuses CAM-A's calibration on a layer of CAM-B's frames (a new
    widget with a calibration field and no probe here fails)."""
    import inspect

    from magicgui.widgets import Container
    from test_export import true_result

    from emccdcal.napari import _widgets

    cal = true_result(tmp_path / "cal", camera={"serial": "CAM-A"})
    takes = {
        name
        for name, cls in inspect.getmembers(_widgets, inspect.isclass)
        if issubclass(cls, Container)
        and cls.__module__ == _widgets.__name__
        and "result" in inspect.getsource(cls.__init__)
    }
    probes = {"ApplyWidget": "button", "GainCheckWidget": "button"}
    # the Calibrate widget's calibration is φ for a series, checked by calibrate itself
    # (tests/test_guarantees.py probes calibrate)
    assert takes - {"CalibrateWidget"} == set(probes), takes
    viewer = make_napari_viewer()
    frames = viewer.add_image(
        np.full((30, 8, 8), 600, np.uint16),
        name="cam-b",
        metadata={"camera": {"serial": "CAM-B"}, "emccdcal": {"em_gain_setpoint": 100.0}},
    )
    for name, button in probes.items():
        widget = getattr(_widgets, name)(viewer)
        widget.reset_choices()
        widget.layer.value, widget.result.value = frames, cal
        widget.setpoint.value = "100"
        getattr(widget, button).native.click()
        _wait(qtbot, widget)
        assert widget.status.value.startswith("error:"), (name, widget.status.value)
        assert "CAM-B" in widget.status.value and "CAM-A" in widget.status.value, (
            name,
            widget.status.value,
        )
