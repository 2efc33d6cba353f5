"""
The gain over weeks, from dark frames
=====================================

An EM register ages: its gain at a set-point falls with the charge it has multiplied.
A lamp calibration is an afternoon's work; dark frames are a minute's. Here a camera
whose gain at 300× falls by 2 % a week is checked every week from 2000 dark frames
(:func:`emccdcal.check_gain`, φ from the calibration), and the trend is read against
the calibration of week 0.
"""

# %%
# Week 0: the calibration (a gain series, φ known). Each week after: darks only.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_gain_series(
    work / "gs", rows=8, cols=8, frames=800, setpoints=[1, 300], seed=71, progress=False
)
phi = sim.truth["e_per_adu"]
ds = emccdcal.calibrate(sim.manifest, e_per_adu=phi, progress=False)
g0 = {a["em_gain_setpoint"]: a["em_gain"] for a in sim.truth["acquisitions"]}[300]
calibrated = float(ds.em_gain.sel(setpoint=300).median())
offset = float(ds.offset.sel(setpoint=300).median())
read_noise = float(ds.read_noise.sel(setpoint=1).median())

weeks = np.arange(0, 8)
checks = []
for week in weeks:
    true_gain = g0 * 0.98**week
    darks = emccdcal.simulate_frames(
        0.05,
        em_gain=true_gain,
        e_per_adu=phi,
        offset=offset,
        read_noise=read_noise,
        frames=2000,
        rows=8,
        cols=8,
        seed=100 + int(week),
    )
    checks.append(emccdcal.check_gain([darks], e_per_adu=phi, setpoint=300, progress=False))
    print(f"week {week}: {checks[-1].summary()}")

# %%
# Each week's gain with its 95 % interval, the truth, and the calibration of week 0.
gains = np.array([c.em_gain for c in checks])
errors = 1.96 * np.array([c.em_gain_se for c in checks])
fig, ax = plt.subplots(figsize=(5.5, 3.6), constrained_layout=True)
ax.errorbar(weeks, gains, errors, fmt="o", label="from darks (95 %)")
ax.plot(weeks, g0 * 0.98**weeks, "k--", lw=1, label="truth")
ax.axhline(calibrated, color="C2", lw=1, label="calibration, week 0")
ax.set(xlabel="week", ylabel="em_gain at 300x")
ax.legend(fontsize="small")
plt.show()
