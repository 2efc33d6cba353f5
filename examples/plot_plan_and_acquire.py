"""
Plan a calibration and record it with a simulated camera
========================================================

:func:`emccdcal.plan` computes the frames a target precision needs from the
likelihood's Fisher information; :func:`emccdcal.record` records the plan through
Micro-Manager (here its simulated EMCCD, no hardware), :func:`emccdcal.scan` turns the
recording into a manifest and :func:`emccdcal.calibrate` fits it: the command line's
``plan``, ``acquire``, ``scan`` and ``calibrate``. Needs the ``acquire`` extra
(``pip install '.[acquire]'`` in the source folder).
"""

# %%
# The plan: the camera's φ, read noise and offset (from an earlier calibration or its
# data sheet), a 2 % target for the gains' standard error per pixel.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
plan = emccdcal.plan(e_per_adu=3.9, read_noise=15.5, offset=590, target_se=2)
for stack in plan.acquisitions:
    print(f"{stack.setpoint:>5g}x  {stack.frames:5d} frames of {stack.photoelectrons:.0f} e-")
print(f"darks: {plan.dark_frames} frames per set-point")

# %%
# Record it: a 16 × 16 px region of the simulated camera, every set-point of the plan
# with its dark stack, into OME-Zarr files that record their settings.
emccdcal.record(plan, work / "session", simulated_seed=3, roi=(0, 0, 16, 16), progress=False)
print(sorted(p.name for p in (work / "session").iterdir()))

# %%
# ``scan`` groups the files by the settings they record and writes the manifest;
# ``calibrate`` fits the gain series with φ known.
manifest = emccdcal.scan(work / "session")
ds = emccdcal.calibrate(manifest, method="gs", e_per_adu=3.9)
print(ds.attrs["verdict"])

# %%
# The plan promised a standard error of the gain per pixel; the calibration reports
# the one it reached. Both, per set-point:
relative = (ds.em_gain_se / ds.em_gain).median(dim=("row", "col")) * 100
fig, ax = plt.subplots(figsize=(5, 3.4), constrained_layout=True)
multiplied = ds.setpoint.values > 1
ax.plot(ds.setpoint[multiplied], relative[multiplied], "o-", label="reached (median)")
ax.axhline(2.0, color="k", ls="--", lw=1, label="the plan's target")
ax.set(xscale="log", xlabel="em_gain_setpoint", ylabel="SE of em_gain (%)", ylim=(0, 3))
ax.legend()
plt.show()
