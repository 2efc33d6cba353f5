"""
The EM gain from dark frames
============================

Every dark frame at EM gain holds the gain: its clock-induced-charge electrons pass the
whole register, and their multiplied events stand out of the read noise with a scale of
g/φ ADU. With φ known, :func:`emccdcal.check_gain` (``emccdcal gain-check``) fits their
shape: the gain, to compare with a calibration's, no lamp needed.
"""

# %%
# A simulated camera with some clock-induced charge (0.05 e⁻ per pixel per frame); a
# gain series calibrated with φ known, then 2000 fresh dark frames at 300×.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_gain_series(
    work / "gs", rows=8, cols=8, frames=1000, setpoints=[1, 25, 300], e_per_adu=3.859, seed=11
)
ds = emccdcal.calibrate(sim.manifest, method="gs", e_per_adu=3.859)
true_gain = {a["em_gain_setpoint"]: a["em_gain"] for a in sim.truth["acquisitions"]}[300]
camera = dict(  # the same camera: its offset at 300x, its read noise where no CIC adds
    offset=float(ds.offset.sel(setpoint=300).median()),
    read_noise=float(ds.read_noise.sel(setpoint=1).median()),
)
darks = emccdcal.simulate_frames(
    0.05, em_gain=true_gain, e_per_adu=3.859, frames=2000, rows=8, cols=8, seed=12, **camera
)
print(f"true gain at 300x: {true_gain:.2f}")

# %%
# The check (φ from the calibration), and how it compares with the calibration's gain
# at 300×: one line each.
check = emccdcal.check_gain(
    [darks], e_per_adu=float(ds.e_per_adu.median()), setpoint=300, histogram=True
)
print(check.summary())
calibrated = float(ds.em_gain.sel(setpoint=300).median())
print(f"calibration's gain at 300x: {calibrated:.2f}; true {true_gain:.2f}")

# %%
# What it fitted: the pooled histogram of the darks (offset removed) on a log scale,
# whose tail is the multiplied events.
excess = (darks - ds.offset.sel(setpoint=300).values).ravel()
fig, ax = plt.subplots(figsize=(6, 3.4), constrained_layout=True)
ax.hist(excess, bins=np.arange(-80, excess.max() + 8, 8), color="0.6")
ax.set(
    yscale="log",
    xlabel="counts − offset (ADU)",
    ylabel="frames × pixels",
    title=f"em_gain {check.em_gain:.1f} ± {check.em_gain_se:.1f} from the darks",
)
plt.show()
