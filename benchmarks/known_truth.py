"""Known-truth studies: two very different cameras, simulated with their true maps, and
the statistics that judge estimates against the truth.

Used by the test suite (every method must recover the truth) and by the studies in
``benchmarks/`` (coverage, profile intervals), so that both judge alike; not part of
the package (the tests find it through pytest's ``pythonpath``).
:data:`CAMERAS` are the paper's ProEM and a camera with a large φ and read noise;
:func:`simulate_camera` writes a gain series, a 1× and an EM intensity series of one,
with manifests that carry the true offset and read-noise maps. As in the paper's own
simulation study, the register is the gamma model, simulated and fitted (the manifests
say ``em_model = "gamma"``); the exact register's recovery is studied on its own
(``tests/test_cascade_likelihood.py``, ``benchmarks/cascade_study.py``).
"""

from __future__ import annotations

import re

import numpy as np

from emccdcal import defaults
from emccdcal.fit import layouts
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

__all__ = [
    "CAMERAS",
    "ROWS",
    "COLS",
    "FRAMES",
    "STUDY_REGISTER",
    "simulate_camera",
    "truth_manifest",
    "median_band",
    "coverage",
    "result_bounds",
    "hierarchical_options",
]

#: The two cameras: the paper's and an "other" one (φ 12 e-/ADU, σ 40 ADU, E 60 e-).
CAMERAS = {
    "paper": dict(
        e_per_adu=3.859,
        read_noise=15.5,
        offset=587.7,
        photoelectrons=370.0,
        setpoints=(1, 5, 25, 100, 300),
        em_gain=(1, 4.78, 22.95, 90.06, 261.6),
        levels=(2000, 4000, 8000, 16000, 32000, 64000),
        is_gain_setpoint=25,
        is_gain=22.95,
        is_gain_levels=(50, 100, 200, 400, 800, 1600),
    ),
    "other": dict(
        e_per_adu=12.0,
        read_noise=40.0,
        offset=1000.0,
        photoelectrons=60.0,
        setpoints=(1, 10, 50, 200, 1000),
        em_gain=(1, 9.1, 44.0, 180.0, 870.0),
        levels=(20000, 40000, 80000, 160000, 320000, 600000),
        is_gain_setpoint=200,
        is_gain=180.0,
        is_gain_levels=(5, 10, 20, 40, 80, 160),
    ),
}
ROWS = COLS = 32  # 1024 pixels
FRAMES = 2000


def truth_manifest(sim, read_noise, em_model=None):
    """Rewrite a simulated manifest with the true offset and read-noise maps (and the
    register model ``em_model``, where given).

    The true maps are exact: their ``dark_frames`` lines go (the maps' own errors are
    tested in ``test_map_errors.py``).
    """
    import tifffile

    truth = sim.truth
    pattern = tifffile.imread(sim.outdir / truth["offset_pattern"]["file"]).astype(float)
    text = sim.manifest.read_text()
    sigma = float(np.sqrt(read_noise**2 + 1.0 / 12.0))  # rounding to integer counts
    for i, acq in enumerate(truth["acquisitions"]):
        true_map = sim.outdir / f"true-offset-{i}.tif"
        tifffile.imwrite(true_map, (acq["offset"] + pattern).astype(np.float64))
        text = text.replace(f'offset = "{acq["offset_map"]}"', f'offset = "{true_map.name}"')
        text = text.replace(f'read_noise = "{acq["read_noise_map"]}"', f"read_noise = {sigma!r}")
    text = re.sub(r"\ndark_frames = .*", "", text)
    if em_model is not None:
        text = f'em_model = "{em_model}"\n' + text
    path = sim.outdir / "manifest-truth.toml"
    path.write_text(text)
    return path


#: The register of the study: the paper's gamma model, simulated and fitted.
STUDY_REGISTER = defaults.PAPER_EM_MODEL


def simulate_camera(base, cam):
    """The three series of a camera (gain series, 1× and EM intensity series), with
    manifests that carry the true maps and the study's register model
    (:data:`STUDY_REGISTER`); also used by ``benchmarks/coverage_study.py``."""
    common = dict(
        rows=ROWS,
        cols=COLS,
        frames=FRAMES,
        dark_frames=10,
        e_per_adu=cam["e_per_adu"],
        read_noise=cam["read_noise"],
        offset=cam["offset"],
        multiplication=STUDY_REGISTER,
    )
    gs = simulate_gain_series(
        base / "gs",
        setpoints=cam["setpoints"],
        em_gain=cam["em_gain"],
        photoelectrons=cam["photoelectrons"],
        seed=31,
        **common,
    )
    adu = simulate_intensity_series(base / "adu", levels=cam["levels"], seed=14, **common)
    isg = simulate_intensity_series(
        base / "isg",
        levels=cam["is_gain_levels"],
        setpoint=cam["is_gain_setpoint"],
        em_gain=cam["is_gain"],
        seed=13,
        **common,
    )
    return {
        k: truth_manifest(s, cam["read_noise"], STUDY_REGISTER)
        for k, s in (("gs", gs), ("adu", adu), ("isg", isg))
    }


def median_band(estimate, undefined=None):
    """Median over every pixel and its 3σ band by order statistics: the sample values at
    ranks N/2 ± 3·√N/2, free of the distribution's shape.

    ``undefined`` (+inf or −inf) ranks the pixels whose estimate is NaN above or below
    every number (a mean–variance slope ≤ 0 means g below any positive value and E beyond
    any), so the median is that of every pixel, not of the defined ones only.
    """
    estimate = np.ravel(estimate)
    ranked = np.sort(
        np.where(np.isnan(estimate), np.nan if undefined is None else undefined, estimate)
    )
    n, half = ranked.size, 1.5 * np.sqrt(ranked.size)  # 3 SDs of a Binomial(n, ½) rank
    return (
        np.median(ranked),
        ranked[int(np.floor(n / 2 - half))],
        ranked[int(np.ceil(n / 2 + half))],
    )


def coverage(estimate, se, truth, bounds=None):
    """Fraction of 95 % intervals covering the truth: ``bounds`` (lower, upper) where the
    result has them, else estimate ± 1.96 SE."""
    if bounds is None:
        return float(np.mean(np.abs(np.ravel(estimate) - truth) <= 1.959964 * np.ravel(se)))
    lower, upper = (np.ravel(b) for b in bounds)
    return float(np.mean((lower <= truth) & (truth <= upper)))


def result_bounds(ds, name, **sel):
    """``(<name>_lower, <name>_upper)`` at ``sel`` when the result carries them, else None."""
    if f"{name}_lower" not in ds:
        return None
    return tuple(ds[f"{name}_{side}"].sel(**sel).values for side in ("lower", "upper"))


def hierarchical_options(cam):
    """The authors' hyperprior scales (25 e⁻ for their ~370 e⁻) in proportion to a camera's
    illumination: 25 e⁻ absolute is 7 % of E on the paper's camera but 42 % on the "other"
    one, a prior that hardly pools. The coverage study measures the authors'
    absolute scales too (their 10x gain is biased there, docs/validation.md)."""
    sd = layouts.HIERARCHICAL_DEFAULTS["sigma_sd"] * cam["photoelectrons"] / 370.0
    return {"mu_sd": sd, "sigma_sd": sd}
