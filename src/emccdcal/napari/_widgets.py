"""The plugin's dock widgets: calibrate, counts to photoelectrons, the gain check.

Each is a magicgui ``Container`` whose buttons call the library; long work runs in a
worker thread (napari's ``create_worker``), its progress relayed to the widget's bar by a
Qt signal, so that the viewer keeps drawing. Cancel sets an event that the library's
progress callback turns into :class:`emccdcal.errors.Cancelled` between blocks of
pixels. Errors a user can cause (:class:`emccdcal.errors.EmccdcalError`) and warnings
are shown in the widget as the command line prints them: one line each.
"""

from __future__ import annotations

import json
import tempfile
import threading
import warnings
from pathlib import Path

from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    Label,
    LineEdit,
    ProgressBar,
    PushButton,
    TextEdit,
    create_widget,
)
from qtpy.QtCore import QObject, QTimer, Signal

from .._output import atomic_write_text
from .. import plugins
from ..defaults import DEFAULT_EM_MODEL, DEFAULT_TOOL
from ..errors import Cancelled, EmccdcalError, OptionError, spelling

__all__ = ["CalibrateWidget", "ApplyWidget", "GainCheckWidget"]


class _Relay(QObject):
    """Carries progress from the worker thread to the widget (a queued connection)."""

    progressed = Signal(int, int)


class _Job:
    """A function run in a worker thread with progress, cancel and one-line errors."""

    def __init__(self, widget, bar: ProgressBar, status: Label, cancel: PushButton):
        self.widget, self.bar, self.status, self.cancel_button = widget, bar, status, cancel
        self.relay = _Relay()
        self.relay.progressed.connect(self._progress)
        self.cancelled = threading.Event()
        self.worker = None
        cancel.changed.connect(self.cancelled.set)
        cancel.enabled = False

    def progress(self, done, total):
        """The library's progress callback (worker thread): relay, or stop."""
        if self.cancelled.is_set():
            raise Cancelled("cancelled")
        self.relay.progressed.emit(int(done), int(total or 0))

    def _progress(self, done, total):
        self.bar.max = max(total, 1)
        self.bar.value = min(done, self.bar.max)

    def start(self, function, on_result, what: str):
        """Run ``function()`` (it may call :meth:`progress`) and hand its result and
        the warnings it raised to ``on_result`` (in the viewer's thread)."""
        from napari.qt.threading import create_worker

        def run():
            with warnings.catch_warnings(record=True) as caught, spelling(FIELD_NAMES):
                warnings.simplefilter("always")
                value = function()
            return value, list(dict.fromkeys(str(w.message) for w in caught))

        def returned(out):  # an error here would reach Qt, which may abort the viewer
            try:
                with spelling(FIELD_NAMES):
                    on_result(*out)
            except Exception as exc:  # noqa: BLE001 - shown on the widget, never raised
                self._failed(exc, reraise=False)

        self.cancelled.clear()
        self.bar.value, self.status.value = 0, f"{what}…"
        self.cancel_button.enabled = True
        # (an errored handler of our own: napari's default re-raises in the viewer)
        self.worker = create_worker(run, _start_thread=False, _connect={"errored": self._failed})
        self.worker.returned.connect(returned)
        self.worker.finished.connect(lambda: setattr(self.cancel_button, "enabled", False))
        self.worker.start()
        return self.worker

    def _failed(self, exc, reraise=True):
        if isinstance(exc, Cancelled):
            self.status.value = "cancelled: nothing was written"
        elif isinstance(exc, EmccdcalError):
            self.status.value = f"error: {exc}"
        else:  # a bug: show it, and let napari's handler keep its traceback
            self.status.value = f"error (a bug of emccdcal): {type(exc).__name__}: {exc}"
            if reraise:
                raise exc


def _status_line(**kw):
    return Label(value="", **kw)


def _reporting(widget, action):
    """A button's handler: ``action()``, an error a user can cause shown on the widget's
    status line (one line, as the command line prints it)."""

    def run(*_):
        try:
            with spelling(FIELD_NAMES):
                action()
        except EmccdcalError as exc:
            widget.status.value = f"error: {exc}"

    return run


#: The command line's options as the widgets name them, for the library's messages.
FIELD_NAMES = {
    "--setpoint G": "the set-point in the 'set-point' field",
    "--setpoint": "the 'set-point' field",
    "--accept-mismatch": "(on the command line) --accept-mismatch",
    "--e-per-adu": "the 'e-/ADU' field",
}


def _field_path(field, what: str) -> Path:
    """The path typed or chosen in a file field, or one line asking for ``what`` (an
    empty field is not the folder napari was started in)."""
    text = field.line_edit.value.strip()
    if text in ("", "."):
        raise OptionError(f"choose {what}")
    return Path(text)


def _optional_float(text: str, what: str):
    text = text.strip()
    if not text:
        return None
    try:
        return float(text)
    except ValueError:
        raise OptionError(f"{what}: expected a number, got {text!r}") from None


# --------------------------------------------------------------------------------------
# Calibrate
# --------------------------------------------------------------------------------------
class CalibrateWidget(Container):
    """A folder of camera files (or a manifest): what ``scan`` finds, the method and the
    register model, a run with progress and cancel, the result as layers, its report,
    and its export to a localization tool."""

    def __init__(self, napari_viewer=None):
        from ..defaults import LIKELIHOOD_METHODS, METHODS

        self.viewer = napari_viewer
        # any file: a folder is typed or pasted (a dialog picks files or folders, not both)
        self.source = FileEdit(label="folder or manifest", mode="r")
        self.scan_button = PushButton(text="Scan")
        self.found = TextEdit(label="found", value="")
        self.found.native.setReadOnly(True)
        self.method = ComboBox(label="method", choices=list(METHODS), value="gs")
        self.em_model = ComboBox(
            label="register", choices=list(plugins.names(plugins.REGISTERS)), value=DEFAULT_EM_MODEL
        )
        self.stages = LineEdit(label="stages", value="")
        self.e_per_adu = LineEdit(label="e-/ADU (or a result)", value="")
        self.out = FileEdit(label="output folder", mode="d")
        self.run_button = PushButton(text="Calibrate")
        self.cancel_button = PushButton(text="Cancel")
        self.bar = ProgressBar(label="pixels", value=0, max=1)
        self.status = _status_line()
        self.warnings = TextEdit(label="warnings", value="")
        self.warnings.native.setReadOnly(True)
        self.report_button = PushButton(text="Write the report")
        self.tool = ComboBox(
            label="export to",
            choices=list(plugins.names(plugins.TOOLS)),
            value=DEFAULT_TOOL,
        )
        self.setpoint = LineEdit(label="set-point", value="")
        self.export_button = PushButton(text="Export")
        super().__init__(
            widgets=[
                self.source,
                self.scan_button,
                self.found,
                self.method,
                self.em_model,
                self.stages,
                self.e_per_adu,
                self.out,
                self.run_button,
                self.cancel_button,
                self.bar,
                self.status,
                self.warnings,
                self.report_button,
                self.tool,
                self.setpoint,
                self.export_button,
            ]
        )
        self._likelihood = set(LIKELIHOOD_METHODS)
        self.job = _Job(self, self.bar, self.status, self.cancel_button)
        self.result = None  # the result's folder, once a run completed
        self._temporary = None  # the output folder we chose, where none was given
        self._written = set()  # files this widget wrote (it may replace only those)
        self.scan_button.changed.connect(_reporting(self, self.scan))
        self.run_button.changed.connect(_reporting(self, self.run))
        self.report_button.changed.connect(_reporting(self, self.write_report))
        self.export_button.changed.connect(_reporting(self, self.export))
        if napari_viewer is not None:  # the sample data name their manifest
            for layer in napari_viewer.layers:
                if "emccdcal_manifest" in layer.metadata:
                    self.source.value = layer.metadata["emccdcal_manifest"]

    def _manifest(self, out: Path) -> Path:
        """The manifest to calibrate: the one chosen, or one ``scan`` writes for a
        folder (into the run's output folder ``out``, beside its result)."""
        from ..data.scan import manifest_text, scan

        source = _field_path(self.source, "a folder of camera files or a manifest")
        if source.is_file():
            return source
        session = scan(source)
        path = out / "manifest.toml"
        self._write(path, [source], lambda: atomic_write_text(path, manifest_text(session, path)))
        return path

    def _out(self) -> Path:
        """The output folder: the one given, else a new temporary one for each run."""
        given = str(self.out.value)
        if given in ("", ".") or Path(given) == self._temporary:
            self._temporary = Path(tempfile.mkdtemp(prefix="emccdcal-calibration-"))
            self.out.value = self._temporary
        return Path(self.out.value)

    def _write(self, path: Path, inputs, write, kind: str = "file"):
        """``write()`` under the package's output policy: never over an input, nor over
        a file this widget did not write; published only when complete."""
        from .._output import Output

        with Output(path, kind=kind, inputs=inputs, overwrite=path in self._written):
            value = write()
        self._written.add(path)
        return value

    def scan(self):
        """Show what the folder (or manifest) holds."""
        from ..data.manifest import read_manifest
        from ..data.scan import scan

        source = _field_path(self.source, "a folder of camera files or a manifest")
        if source.is_file():
            m = read_manifest(source)
            lines = [
                f"manifest: {len(m.acquisitions)} acquisition(s), {m.shape[0]} × {m.shape[1]} px"
            ]
            lines += [
                f"  {a.frames_path.name}: set-point {a.em_gain_setpoint:g}, {a.n_frames} frames"
                for a in m.acquisitions
            ]
        else:
            lines = scan(source).summary()
        self.found.value = "\n".join(lines)

    def run(self):
        """Calibrate in a worker thread; the result opens as layers."""
        from ..calibration import calibrate

        folder = self._out()  # once a run: the manifest and the result side by side
        manifest = self._manifest(folder)
        out = folder / "result"
        method = self.method.value
        options = {}
        if method in self._likelihood:
            stages = self.stages.value.strip()
            options = {"em_model": self.em_model.value, "stages": int(stages) if stages else None}
        phi = self.e_per_adu.value.strip()
        e_per_adu = None if not phi else (float(phi) if _is_number(phi) else Path(phi))

        def work():
            return calibrate(
                manifest,
                method,
                out=out,
                e_per_adu=e_per_adu,
                progress=self.job.progress,
                **options,
            )

        return self.job.start(work, self._done, f"calibrating ({method})")

    def _done(self, ds, caught):
        self.result = Path(self.out.value) / "result"
        self.warnings.value = "\n".join(caught)
        status = (
            f"done: {int(ds.converged.sum())} of {ds.converged.size} pixels converged; "
            f"{self.result}"
        )
        if self.viewer is None:
            self.status.value = status
            return
        from ._layers import result_layers

        # one layer at a time, the event loop running in between (each takes a moment
        # to draw its thumbnail and colour bar)
        pending = result_layers(ds, prefix=f"{ds.attrs['method']}: ")
        self.status.value = "adding the result's layers…"

        def add_next():
            if not pending:
                self.status.value = status
                return
            data, kwargs, _ = pending.pop(0)
            self.viewer.add_image(data, **kwargs).colorbar.visible = True
            QTimer.singleShot(0, add_next)

        add_next()

    def _need_result(self) -> Path:
        if self.result is None:
            raise OptionError("calibrate first: there is no result to use yet")
        return self.result

    def write_report(self):
        """``report.html`` of the result, beside it."""
        from ..report.html import write_report

        result = self._need_result()
        path = result.parent / "report.html"
        self._write(path, [result], lambda: write_report([result], path))
        self.status.value = f"wrote {path}"

    def export(self):
        """The result in the chosen localization tool's own file."""
        from ..export.tools import export

        setpoint = _optional_float(self.setpoint.value, "set-point")
        result = self._need_result()
        out = result.parent / f"export-{self.tool.value}"
        files = self._write(
            out,
            [result],
            lambda: export(result, self.tool.value, out, setpoint=setpoint),
            kind="folder",
        )
        self.status.value = "wrote " + ", ".join(str(f) for f in files)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# --------------------------------------------------------------------------------------
# Counts to photoelectrons
# --------------------------------------------------------------------------------------
def _calibration(result: str, camera: str, db: str, setpoint):
    """A calibration from a result, or from the database's entry for the camera."""
    from ..export import database
    from ..result import load_calibration

    if camera.strip():
        if setpoint is None:
            raise OptionError("the database's calibration of a camera needs the set-point")
        return database.calibration(camera.strip(), setpoint, db=db.strip() or None)
    if not result.strip() or result.strip() == ".":
        raise OptionError("choose a calibration: a result, or a camera in the database")
    return load_calibration(result.strip())


def _chosen(widget, what: str):
    """The widget's image layer (or a one-line error asking for ``what``), the camera
    settings its file recorded, the set-point typed (or None) and the one to use."""
    layer = widget.layer.value
    if layer is None:
        raise OptionError(f"choose {what}")
    settings = _settings_of(layer)
    given = _optional_float(widget.setpoint.value, "set-point")
    return layer, settings, given, given if given is not None else settings.em_gain_setpoint


def _settings_of(layer):
    """The camera settings an image layer's file recorded (none for another layer)."""
    from ..data.settings import CameraSettings

    recorded = layer.metadata.get("camera", {}) if layer is not None else {}
    if not isinstance(recorded, dict):
        return CameraSettings()
    known = {k: v for k, v in recorded.items() if k in CameraSettings.names()}
    return CameraSettings.from_record(known, layer.name)


class ApplyWidget(Container):
    """An image layer of raw counts into a new layer of photoelectrons (or photons with
    a QE) by a calibration, placed where the recorded region puts it."""

    def __init__(self, napari_viewer=None):
        self.viewer = napari_viewer
        self.layer = create_widget(annotation="napari.layers.Image", label="image (ADU)")
        self.result = FileEdit(label="calibration", mode="r")
        self.camera = LineEdit(label="or camera (database)", value="")
        self.db = LineEdit(label="database", value="")
        self.setpoint = LineEdit(label="set-point (default: recorded)", value="")
        self.qe = LineEdit(label="QE (photons)", value="")
        self.button = PushButton(text="Convert")
        self.status = _status_line()
        super().__init__(
            widgets=[
                self.layer,
                self.result,
                self.camera,
                self.db,
                self.setpoint,
                self.qe,
                self.button,
                self.status,
            ]
        )
        self.button.changed.connect(_reporting(self, self.convert))

    def convert(self):
        """Add the converted layer (lazy where the image is: a Dask array stays one)."""
        from ..export.movie import conversion

        layer, settings, given, setpoint = _chosen(self, "an image layer of raw counts")
        cal = _calibration(self.result.line_edit.value, self.camera.value, self.db.value, setpoint)
        data = layer.data
        shape = tuple(int(v) for v in data.shape)
        if len(shape) == 2:
            data, shape = data[None], (1,) + shape
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            convert = conversion(
                cal,
                layer.name,
                settings,
                shape,
                setpoint=given,
                qe=_optional_float(self.qe.value, "QE"),
            )
        unit = "photons" if "qe" in convert.meta else "e-"
        out = self.viewer.add_image(
            convert(data),
            name=f"{layer.name} ({unit})",
            translate=layer.translate,
            colormap="inferno",
            metadata={
                "units": convert.meta["units"],
                "emccdcal": json.loads(json.dumps(convert.meta, default=str)),
            },
        )
        self.status.value = "; ".join([f"added '{out.name}'"] + [str(w.message) for w in caught])
        return out


# --------------------------------------------------------------------------------------
# The gain check
# --------------------------------------------------------------------------------------
class GainCheckWidget(Container):
    """The EM gain of dark frames (an image layer), with φ from a calibration or given,
    against that calibration."""

    def __init__(self, napari_viewer=None):
        self.viewer = napari_viewer
        self.layer = create_widget(annotation="napari.layers.Image", label="dark frames")
        self.result = FileEdit(label="calibration", mode="r")
        self.e_per_adu = LineEdit(label="or e-/ADU", value="")
        self.setpoint = LineEdit(label="set-point (default: recorded)", value="")
        self.region = LineEdit(label="rows,cols (R0:R1,C0:C1)", value="")
        self.fit_cic = CheckBox(label="fit register CIC", value=False)
        self.button = PushButton(text="Check the gain")
        self.cancel_button = PushButton(text="Cancel")
        self.bar = ProgressBar(label="passes", value=0, max=1)
        self.status = _status_line()
        self.answer = TextEdit(label="result", value="")
        self.answer.native.setReadOnly(True)
        super().__init__(
            widgets=[
                self.layer,
                self.result,
                self.e_per_adu,
                self.setpoint,
                self.region,
                self.fit_cic,
                self.button,
                self.cancel_button,
                self.bar,
                self.status,
                self.answer,
            ]
        )
        self.job = _Job(self, self.bar, self.status, self.cancel_button)
        self.button.changed.connect(_reporting(self, self.run))

    def run(self):
        from .._util import parse_region
        from ..export.gain_check import compare, e_per_adu_of, verdict
        from ..fit.darkgain import check_gain
        from ..result import load_calibration

        from .. import identity

        layer, settings, _, setpoint = _chosen(self, "a layer of dark frames")
        result = self.result.line_edit.value.strip()
        cal = load_calibration(result) if result not in ("", ".") else None
        if cal is not None and setpoint is None:
            raise OptionError(
                f"{layer.name}: the layer records no set-point: type it in "
                "the 'set-point' field to compare with the calibration"
            )
        identity.check(
            None if cal is None else cal.identity(),
            [(layer.name, settings)],
            label="" if cal is None else cal.label,
            setpoint=setpoint,
            what="dark frames",
        )
        phi = _optional_float(self.e_per_adu.value, "e-/ADU")
        if phi is None:
            if cal is None:
                raise OptionError("give e-/ADU or a calibration of the camera")
            phi = e_per_adu_of(cal)
        region = parse_region(self.region.value) if self.region.value.strip() else None
        data = layer.data
        bits = settings.adc_bits

        def work():
            check = check_gain(
                [data],
                phi,
                setpoint=setpoint,
                region=region,
                fit_register_cic=self.fit_cic.value,
                adc_max=2**bits - 1 if bits else None,
                progress=self.job.progress,
            )
            return check, (compare(check, cal) if cal is not None and setpoint else None)

        def done(out, caught):
            check, against = out
            lines = [check.summary()] + ([verdict(against)] if against else []) + caught
            self.answer.value = "\n".join(lines)
            self.status.value = "done"

        return self.job.start(work, done, "checking the gain")
