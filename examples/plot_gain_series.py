"""
Calibrate a gain series and look at the maps
============================================

Simulate a camera with known truth, record a gain series (one illumination, several EM
gain set-points, a dark stack per set-point), and calibrate it with the paper's ``gs``
method: the true EM gain at every set-point, per pixel, with standard errors.
"""

# %%
# A small gain series: 8 × 8 pixels, 1500 frames per set-point, φ = 4 e⁻/ADU.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_gain_series(
    work / "gs", rows=8, cols=8, frames=1500, setpoints=[1, 10, 50, 200], e_per_adu=4.0, seed=7
)
print(sim.manifest.read_text())

# %%
# Calibrate. φ is known here (the manifest could carry it; the next example measures
# it), so ``gs`` fits one light and one gain per set-point, per pixel.
ds = emccdcal.calibrate(sim.manifest, method="gs", e_per_adu=4.0)
print(ds.em_gain.median(dim=("row", "col")).to_series())

# %%
# Truth against estimate, per set-point: the medians over pixels, and the spread of
# the per-pixel estimates against their standard errors.
truth = {a["em_gain_setpoint"]: a["em_gain"] for a in sim.truth["acquisitions"]}
for sp in ds.setpoint.values:
    g = ds.em_gain.sel(setpoint=sp)
    se = ds.em_gain_se.sel(setpoint=sp)
    print(
        f"{sp:>5g}x  truth {truth[sp]:8.3f}  median {float(g.median()):8.3f}"
        f"  spread {float(g.std()):.3f}  median SE {float(se.median()):.3f}"
    )

# %%
# The maps: the gain at the highest set-point and its standard error, pixel by pixel.
top = ds.setpoint.values.max()
fig, axes = plt.subplots(1, 2, figsize=(8, 3.4), constrained_layout=True)
for ax, name in zip(axes, ("em_gain", "em_gain_se")):
    im = ax.imshow(ds[name].sel(setpoint=top), cmap="viridis")
    ax.set_title(f"{name} at {top:g}x")
    fig.colorbar(im, ax=ax)
plt.show()

# %%
# The gain against the set-point: the camera's setting is not the true gain.
fig, ax = plt.subplots(figsize=(5, 3.4), constrained_layout=True)
median = ds.em_gain.median(dim=("row", "col"))
ax.errorbar(
    ds.setpoint, median, yerr=ds.em_gain_se.median(dim=("row", "col")), fmt="o", label="estimate"
)
ax.plot(list(truth), list(truth.values()), "x", label="truth")
ax.set(xscale="log", yscale="log", xlabel="em_gain_setpoint", ylabel="em_gain")
ax.legend()
plt.show()
