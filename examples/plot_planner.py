"""
How many frames? The planner against the target precision
=========================================================

:func:`emccdcal.plan` finds the fewest frames that reach a target standard error per
pixel for every gain, from the Fisher information of the likelihood (the same model
the calibration fits), given the camera's φ, read noise and offset. Tighter targets cost
frames as 1/target²; the plan also says how bright the light should be.
"""

# %%
# Plans for targets from 0.25 % to 4 % per pixel, for the paper's camera.
import matplotlib.pyplot as plt
import numpy as np

import emccdcal

targets = [0.25, 0.5, 1, 2, 4]
plans = [emccdcal.plan(e_per_adu=3.859, read_noise=15.5, offset=588, target_se=t) for t in targets]
for t, p in zip(targets, plans):
    frames = {f"{a.setpoint:g}x": a.frames for a in p.acquisitions}
    print(
        f"target {t:>4} %: {frames}, darks {p.dark_frames}, light {p.acquisitions[0].photoelectrons:.0f} e-"
    )

# %%
# The frames of the 1× and of each multiplied set-point, against the target: the line
# of slope −2 is frames ∝ 1/target².
fig, ax = plt.subplots(figsize=(5.5, 3.6), constrained_layout=True)
for i, label in ((0, "1x"), (1, "each multiplied set-point")):
    ax.plot(targets, [p.acquisitions[i].frames for p in plans], "o-", label=label)
ax.plot(targets, [p.dark_frames for p in plans], "s--", label="darks per set-point")
ref = plans[0].acquisitions[0].frames * (targets[0] / np.asarray(targets)) ** 2
ax.plot(targets, ref, "k:", lw=1, label="∝ 1/target²")
ax.set(xscale="log", yscale="log", xlabel="target SE per pixel (%)", ylabel="frames")
ax.legend(fontsize="small")
plt.show()
