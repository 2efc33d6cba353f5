"""
The bead test: is a calibration right?
======================================

The paper's validation: image the same isolated beads at every EM gain set-point and
turn each bead's counts into photoelectrons with a calibration. A right calibration
gives every bead the same intensity at every set-point (bleaching aside); a wrong gain
at one set-point shows as a step there. ``emccdcal validate`` fits every bead in every
frame by maximum likelihood under each calibration and ranks them by the spread of the
beads' mean intensities over the set-points.
"""

# %%
# Simulated bead movies with known truth: 4 beads of 3000 e⁻ per frame on a 48 × 48 px
# sensor, at three set-points; the simulator also writes the true calibration.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal
from emccdcal import result

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_beads(
    work / "beads",
    beads=4,
    photoelectrons=3000.0,
    rows=48,
    cols=48,
    frames=20,
    dark_frames=200,
    setpoints=(1, 10, 100),
    seed=5,
)
truth = work / "beads" / "truth_calibration.nc"

# %%
# A second calibration, wrong in the way a new user's often is: the camera's set-points
# taken for the true gains.
nominal = result.load(truth)
nominal["em_gain"] = nominal.em_gain * 0 + nominal.setpoint
result.save(nominal, work / "nominal")

# %%
# Validate both; the ranking puts the most consistent first.
doc = emccdcal.validate(sim.manifest, [str(truth), str(work / "nominal")], out=work / "validation")


def name(entry):
    return "nominal" if "nominal" in entry["file"] else "truth"


print("ranking:", ["nominal" if "nominal" in f else "truth" for f in doc["ranking"]])
for entry in doc["calibrations"]:
    print(
        f"{name(entry):>8}: spread of the beads' mean intensities over the set-points "
        f"{entry['sigma_means_incl_1x']:.4f}"
    )

# %%
# Every bead's mean intensity at every set-point, relative to its own mean, under each
# calibration: flat for the true one, steps for the nominal gains.
fig, axes = plt.subplots(1, 2, figsize=(8, 3.4), sharey=True, constrained_layout=True)
for ax, entry in zip(axes, doc["calibrations"]):
    for bead in entry["beads"]:
        keys = list(bead["mean_intensity"])
        means = np.array([bead["mean_intensity"][k] for k in keys], dtype=float)
        ax.plot([f"{k}x" for k in keys], means / np.nanmean(means), "o-", lw=0.8)
    ax.set(title=name(entry), xlabel="em_gain_setpoint")
axes[0].set_ylabel("bead intensity / its mean")
plt.show()
