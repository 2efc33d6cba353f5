"""Names and default values the command line shows, declared once and light to import.

Every verb's ``--help`` names its choices and defaults; declaring them here, with no
import beyond the standard library, lets ``emccdcal VERB --help`` answer without loading
NumPy, SciPy or xarray. The modules that use them import them from here (and re-export
them where they always have), so each value has one home.
"""

from __future__ import annotations

# -- methods and the engine (emccdcal.calibration, emccdcal.fit) ------------------------
#: The maximum-likelihood methods (:mod:`emccdcal.fit.layouts`).
LIKELIHOOD_METHODS = ("is-adu", "is-gain", "gs", "gs-no1x", "gs-hierarchical")
#: Every calibration method, mean-variance ones first.
METHODS = ("mv-adu", "mv-gain") + LIKELIHOOD_METHODS
#: The methods ``emccdcal plan`` plans an acquisition for (:mod:`emccdcal.acquire.plan`).
PLAN_METHODS = ("gs", "is-adu", "is-gain")
#: Kinds of camera a manifest and a result name (``camera_kind``): an EMCCD, and cameras
#: without an EM register, whose calibration is an intensity series at 1×.
CAMERA_KINDS = ("emccd", "scmos", "qcmos", "ccd")
WITHOUT_EM_REGISTER = ("scmos", "qcmos", "ccd")
#: Kinds a camera file may record: those, and an intensified camera (ICCD), whose gain is
#: an image intensifier's, which no model here describes.
RECORDED_KINDS = (*CAMERA_KINDS, "iccd")
#: The cameras without an EM register that ``emccdcal simulate cmos`` has presets of.
SIMULATED_CMOS = ("scmos", "qcmos")


def default_method(camera_kind):
    """The method a calibration uses when none is named: ``is-adu`` (φ from an intensity
    series) for a camera without an EM register, else ``gs`` (the gain series)."""
    return "is-adu" if camera_kind in WITHOUT_EM_REGISTER else "gs"


#: Where a fit's likelihood is computed (``calibrate --device``): the CPU (NumPy), an
#: NVIDIA GPU (CuPy, else PyTorch), JAX's first device (its GPU, else the CPU), or
#: array-api-strict (the CPU through the array API standard alone: a check that the hot
#: path needs nothing else, slower).
DEVICES = ("cpu", "cuda", "jax", "array-api-strict")
#: Interval kinds: ``estimate ± 1.96 SE`` only, or profile-likelihood bounds too.
INTERVALS = ("wald", "profile")
#: Pixels fitted together: large enough to amortise Python overhead, small enough that
#: the FFT windows of a block (pixels × window × derivatives) stay within a few hundred MB
#: and that two threads share the blocks evenly (128 fitted a 32 × 32 gain series 11 %
#: faster than 256 on two cores; docs/benchmarks.md).
DEFAULT_BLOCK = 128
#: Pixels per tile. A tile's histograms take up to 16 bytes × frames per pixel and
#: acquisition at high gain (about 80 kB for 5000 frames), so 1024 pixels of five
#: acquisitions stay within about 400 MB (docs/benchmarks.md).
DEFAULT_TILE_PIXELS = 1024

# -- the EM register (emccdcal.model) ---------------------------------------------------
#: The register models by name.
EM_MODELS = ("gamma", "cascade")
#: The register model of a run that neither its caller nor its manifest names: the exact
#: register, a real camera's (``em_model="gamma"`` reproduces the paper's numbers).
DEFAULT_EM_MODEL = "cascade"
#: The localization tool a graphical front offers first (the most used of those emccdcal
#: exports to); any registered tool can be chosen.
DEFAULT_TOOL = "picasso"
#: The paper's register approximation, under which its published numbers are reproduced.
PAPER_EM_MODEL = "gamma"
#: Stages of the register used by default: Hirsch et al.'s simulations (docs/simulation.md).
#: The length matters little: on the published ProEM data the gains move 0.04 % between
#: 512 and 4096 stages (docs/cascade.md).
DEFAULT_STAGES = 536

#: Most stages a register model takes (real registers have 400-1100; the cascade's cost
#: grows with the length).
MAX_STAGES = 16384

# -- the ranges a named quantity is taken as meant in ---------------------------------
#: Inclusive (lowest, highest, unit) of each quantity a user or a file gives, checked by
#: ``_util.check_number`` / ``check_int`` wherever the name is checked: a value outside
#: is refused before any work, as a number in another unit or one that would make a
#: computation run for hours (a read noise of 1e-300 ADU, 10^8 stages, a target SE of
#: 1e-9 %).
#: Most acquisitions one fit takes together: the per-pixel information of a series grows
#: as the cube of their number (2000 set-points asked for 60 GiB); real series have 3–12.
MAX_ACQUISITIONS = 64

BOUNDS = {
    "e_per_adu": (1e-3, 1e3, "e-/ADU"),
    "read_noise": (1e-3, 1e5, "ADU"),
    "photoelectrons": (0.0, 1e8, "e-"),
    "em_gain": (0.5, 1e5, ""),
    "assumed_em_gain": (1.0, 1e5, ""),
    "em_gain_setpoint": (1.0, 1e5, ""),
    "setpoint": (1.0, 1e5, ""),
    "setpoints": (1.0, 1e5, ""),
    "stages": (1, MAX_STAGES, "stages"),
    "frames": (1, 10**9, "frames"),
    "dark_frames": (1, 10**9, "frames"),
    "max_frames": (1, 10**9, "frames"),
    "width": (0.05, 100.0, "px"),
    "target_se": (1e-2, 100.0, "%"),
    "rows": (1, 65536, "px"),
    "cols": (1, 65536, "px"),
    # the command line's other numbers (every numeric option is one of these quantities)
    "offset": (-1e6, 1e7, "ADU"),
    "offset_drop": (-1e4, 1e4, "ADU per decade"),
    "offset_spread": (0.0, 1e4, "ADU"),
    "adc_bits": (1, 32, "bit"),
    "well": (1.0, 1e9, "e-"),
    "frame_rate": (1e-6, 1e6, "Hz"),
    "percent": (0.0, 1e4, "%"),
    "fraction": (0.0, 1.0, ""),
    "probability": (1e-12, 1.0, ""),
    "seed": (0, 2**128 - 1, ""),  # NumPy's SeedSequence draws 128-bit ones
    "id": (1, 2**63 - 1, ""),
    "pixels": (1, 2**31, "px"),
    "workers": (1, 4096, ""),
    "prior_sd": (1e-6, 1e8, "e-"),
    "steps": (1, 10**8, "steps"),
    "walkers": (2, 10**5, ""),
    "sds": (0.1, 1e3, "SD"),
    "half_size": (1, 1000, "px"),
    "distance": (0.0, 1e5, "px"),
    "beads": (0, 10**6, ""),
    "background": (0.0, 1e8, "e-"),
    "cic": (0.0, 100.0, "e-"),
    "qe": (1e-3, 1.0, ""),
    "pixel_size": (1e-3, 1e7, "nm"),
    "tool_gain": (1e-6, 1e6, ""),
    "days": (0.0, 1e6, "days"),
    "exposure": (1e-9, 1e6, "s"),
    "dark_current": (0.0, 1e9, "e-/s"),
    "offset_states": (2, 8, "states"),
}
#: The quantity (a key of :data:`BOUNDS`) of each command-line option whose name is not
#: one; the command line checks every numeric option against its range before any work.
OPTION_QUANTITY = {
    "pixel_well": "well",
    "register_well": "well",
    "light_tolerance": "percent",
    "drift_threshold": "percent",
    "tolerance": "percent",
    "drift_alpha": "probability",
    "tile_pixels": "pixels",
    "block_size": "pixels",
    "mu_sd": "prior_sd",
    "sigma_sd": "prior_sd",
    "max_steps": "steps",
    "k": "sds",
    "snr": "sds",
    "z": "sds",
    "threshold": "sds",
    "min_separation": "distance",
    "margin": "distance",
    "halo_width": "width",
    "blink_frames": "frames",
    "detect_setpoint": "setpoint",
    "repeat": "setpoint",
    "predict": "setpoint",
    "levels": "photoelectrons",
    "offsets": "offset",
    "offset_tolerance": "offset_spread",
    "bleaching": "fraction",
    "halo": "fraction",
    "blinking": "fraction",
    "rts_fraction": "fraction",
    "hot_fraction": "fraction",
    "rts_states": "offset_states",
    "read_noise_e": "read_noise",
    "target_read_noise_se": "percent",
    "drift": "fraction",
    "max_age": "days",
    "dark_exposures": "exposure",
}

#: The record of an acquisition session in its folder (``acquire`` writes, ``scan`` reads).
SESSION_FILE = "session.json"

# -- using a calibration (emccdcal.result, emccdcal.export) -----------------------------
#: What must agree between a calibration and the frames it is used on (where both
#: record it), with how to name it.
IDENTITY_FIELDS = {
    "serial": "camera serial",
    "model": "camera model",
    "amplifier": "output amplifier",
    "readout_rate_mhz": "read-out rate (MHz)",
    "analog_gain": "analog (pre-amplifier) gain",
    "adc_bits": "ADC bits",
    "binning": "binning",
}
#: Relative photon bias beyond which an audit says a tool's numbers are off.
AUDIT_TOLERANCE = 0.02
#: Photon-counting threshold of ``apply``, in read-noise standard deviations.
PHOTON_THRESHOLD = 5.0

# -- a phi given from elsewhere, against the data (emccdcal.calibration) ----------------
#: A given φ is refused where it differs from what a 1x acquisition's photon transfer
#: says by more than this many standard errors (on a log scale: φ and its inverse alike)...
PHI_Z = 5.0
#: ... the SE counted at least this (relative): what the photon-transfer estimate may
#: be off by beyond its sampling error (a nonlinear ADC, a light that flickers frame to
#: frame), so that a sensor of many pixels does not refuse a φ for a 1 % difference.
PHI_SYSTEMATIC = 0.02
#: Most pixels and frames of the 1x acquisition read for the check.
PHI_CHECK_PIXELS, PHI_CHECK_FRAMES = 4096, 4000

# -- data-quality checks (emccdcal.data.quality) ----------------------------------------
#: Family-wise significance of the drift test over a run's acquisitions.
DRIFT_ALPHA = 0.01
#: Smallest |drift| over an acquisition, in % of the mean level, that is a finding.
DEFAULT_DRIFT_THRESHOLD = 0.1
#: Robust standard deviations from the median pixel mean that make a pixel hot or dead.
DEFAULT_K = 5.0

# -- beads (emccdcal.beads, emccdcal.model.psf) -----------------------------------------
#: Expected spot standard deviation (pixel): detection, starting value, validate and cots.
PSF_WIDTH = 1.3
#: Half-size of a bead's fitting window (pixel): a (2h + 1)² box.
BEAD_HALF_SIZE = 4

# -- the posterior sampler (emccdcal.fit.posterior) -------------------------------------
PRIORS = ("log-uniform", "uniform")
DEFAULT_MAX_STEPS = 20000
DEFAULT_FIRST_STEPS = 1500

# -- simulation and the demo (emccdcal.simulate, emccdcal.demo) -------------------------
#: The demo's seed.
DEMO_SEED = 20211
#: Default offset at set-point 1, ADU, and its drop per decade of set-point, ADU: a line
#: in log10(set-point) through the sample data's dark means at 1× (587.7) and 300×
#: (566.2); it gives 581.6, 575.6, 570.3 at 5×, 25×, 100× (data: 583.9, 575.9, 570.9).
DEFAULT_OFFSET = 587.7
DEFAULT_OFFSET_DROP = 8.68
#: Defaults of the camera simulator (:class:`emccdcal.simulate.camera.Camera`).
CAMERA_SIMULATION = {
    "rows": 32,
    "cols": 32,
    "frames": 5000,
    "dark_frames": None,  # as many as frames
    "photoelectrons": 370.0,
    "e_per_adu": 3.859,
    "offset": DEFAULT_OFFSET,
    "offset_drop": DEFAULT_OFFSET_DROP,
    "offset_spread": 0.5,
    "read_noise": 15.5,
    "multiplication": "cascade",
    "stages": DEFAULT_STAGES,
    "cic": 0.0,
    "drift": 0.0,
    "adc_bits": 16,
    "cascade_method": "pmf",
}
#: Defaults of the bead simulation (``docs/beads.md``).
BEAD_SIMULATION = {
    "beads": 10,
    "photoelectrons": 5000.0,
    "width": PSF_WIDTH,
    "background": 10.0,
    "min_separation": 12.0,
    "margin": 6.0,
    "bleaching": 0.0,
    "halo": 0.0,
    "halo_width": None,
    "blinking": 0.0,
    "blink_frames": 5.0,
}
#: The default camera of a bead simulation, where it differs from the camera simulator's.
BEAD_CAMERA = {"rows": 64, "cols": 64, "frames": 500, "dark_frames": 2000}
