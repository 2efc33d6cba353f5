# The lazy public API of emccdcal (__init__.py imports each name on first use), spelled
# out for type checkers and IDEs. Keep it in step with emccdcal._API (a test checks).
from . import acquire as acquire
from . import beads as beads
from . import calibration as calibration
from . import data as data
from . import export as export
from . import fit as fit
from . import model as model
from . import report as report
from . import result as result
from . import simulate as simulate
from .beads.cots_calibration import cots_calibrate as cots
from .beads.validation import validate as validate
from .calibration import calibrate as calibrate
from .acquire.plan import plan as plan
from .acquire.record import acquire as record
from .data.manifest import Manifest as Manifest
from .data.manifest import read_manifest as read_manifest
from .data.scan import scan_folder as scan
from .data.settings import CameraSettings as CameraSettings
from .export.audit import audit as audit
from .fit.darkgain import check_gain as check_gain
from .result import Calibration as Calibration
from .data.quality import check_manifest as check
from .errors import EmccdcalError as EmccdcalError
from .errors import EmccdcalWarning as EmccdcalWarning
from .export.gain_curve import fit_gain_curve as fit_gain_curve
from .export.movie import apply as apply_calibration
from .export.tools import export as export_calibration
from .sampling import sample_posterior as sample_posterior
from .model import noise as noise
from .report.html import write_report as write_report
from .result import load as load_result
from .result import load_calibration as load_calibration
from .simulate.beads import simulate_beads as simulate_beads
from .simulate.camera import Camera as Camera
from .simulate.camera import simulate_frames as simulate_frames
from .simulate.series import simulate_gain_series as simulate_gain_series
from .simulate.series import simulate_intensity_series as simulate_intensity_series

__version__: str
__all__ = [
    "__version__",
    "cots",
    "validate",
    "calibrate",
    "read_manifest",
    "scan",
    "plan",
    "record",
    "check_gain",
    "audit",
    "Calibration",
    "Manifest",
    "CameraSettings",
    "check",
    "EmccdcalError",
    "EmccdcalWarning",
    "fit_gain_curve",
    "apply_calibration",
    "export_calibration",
    "sample_posterior",
    "noise",
    "write_report",
    "load_result",
    "load_calibration",
    "simulate_beads",
    "Camera",
    "simulate_frames",
    "simulate_gain_series",
    "simulate_intensity_series",
]
