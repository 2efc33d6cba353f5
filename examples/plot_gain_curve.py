"""
The gain curve: the true gain between set-points
================================================

The true EM gain differs from the set-point, and a calibration measures it at a few
set-points only. :func:`emccdcal.fit_gain_curve` fits ln g as a smooth, rising function
of ln(set-point) through the measured gains and their errors, and predicts the gain, with
a 95 % band, at set-points never measured.
"""

# %%
# A gain series at five set-points, calibrated with φ known.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_gain_series(
    work / "gs",
    rows=6,
    cols=6,
    frames=800,
    setpoints=[1, 5, 25, 100, 300],
    seed=41,
    progress=False,
)
ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)

# %%
# The curve, straight from the result; a prediction at 50× and 200×.
curve = emccdcal.fit_gain_curve(ds)
print(f"chi2 {curve.chi2:.2f} on {curve.dof} degrees of freedom")
for s, g, se in zip(*(curve.predict([50, 200])[k] for k in ("setpoint", "gain", "se_of_median"))):
    print(f"{s:>5g}x: em_gain {g:.2f} ± {se:.2f}")

# %%
# The measured gains (median over pixels, with its standard error), the curve and its
# band, and the set-point itself for comparison.
grid = np.geomspace(2, 400, 100)
band = curve.predict(grid)
truth = {a["em_gain_setpoint"]: a["em_gain"] for a in sim.truth["acquisitions"]}
fig, ax = plt.subplots(figsize=(5.5, 3.6), constrained_layout=True)
ax.fill_between(grid, band["lower"], band["upper"], alpha=0.3, label="95 % band")
ax.plot(grid, band["gain"], "C0-", lw=1, label="gain curve")
ax.errorbar(
    curve.setpoints, curve.gains, 1.96 * curve.gain_se, fmt="ko", ms=4, label="measured (median)"
)
ax.plot(list(truth)[1:], list(truth.values())[1:], "rx", label="truth")
ax.plot(grid, grid, "k:", lw=1, label="em_gain = set-point")
ax.set(xscale="log", yscale="log", xlabel="em_gain_setpoint", ylabel="em_gain")
ax.legend(fontsize="small")
plt.show()
