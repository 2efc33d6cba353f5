"""
Plan a calibration and record it with a simulated camera
========================================================

``emccdcal plan`` computes the frames a target precision needs from the likelihood's
Fisher information; ``emccdcal acquire`` records the plan through Micro-Manager (here
its simulated EMCCD, no hardware), ``scan`` turns the recording into a manifest and
``calibrate`` fits it. These are the command line's verbs, called from Python as
``emccdcal.cli.main([...])``, which returns the command's exit status: the same words
a terminal takes. Needs the ``acquire``
extra (``pip install "emccdcal[acquire]"``).
"""

# %%
# The plan: the camera's φ, read noise and offset (from an earlier calibration or its
# data sheet), a 2 % target for the gains' standard error per pixel.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import emccdcal
from emccdcal import cli

work = Path(tempfile.mkdtemp(prefix="emccdcal-gallery-"))
assert (
    cli.main(
        [
            "plan",
            "--e-per-adu",
            "3.9",
            "--read-noise",
            "15.5",
            "--offset",
            "590",
            "--target-se",
            "2",
            "-o",
            f"{work}/plan",
        ]
    )
    == 0
)

# %%
# Record it: a 16 × 16 px region of the simulated camera, every set-point of the plan
# with its dark stack, into OME-Zarr files that record their settings.
assert (
    cli.main(
        [
            "acquire",
            f"{work}/plan/plan.toml",
            "-o",
            f"{work}/session",
            "--simulated",
            "--seed",
            "3",
            "--roi",
            "0,0,16,16",
            "--quiet",
        ]
    )
    == 0
)
print(sorted(p.name for p in (work / "session").iterdir()))

# %%
# ``scan`` groups the files by the settings they record and writes the manifest;
# ``calibrate`` fits the gain series with φ known.
assert cli.main(["scan", f"{work}/session", "-o", f"{work}/session/manifest.toml"]) == 0
assert (
    cli.main(
        [
            "calibrate",
            f"{work}/session/manifest.toml",
            "--method",
            "gs",
            "--e-per-adu",
            "3.9",
            "-o",
            f"{work}/out-session",
        ]
    )
    == 0
)

# %%
# The plan promised a standard error of the gain per pixel; the calibration reports
# the one it reached. Both, per set-point:
ds = emccdcal.load_result(work / "out-session")
relative = (ds.em_gain_se / ds.em_gain).median(dim=("row", "col")) * 100
fig, ax = plt.subplots(figsize=(5, 3.4), constrained_layout=True)
multiplied = ds.setpoint.values > 1
ax.plot(ds.setpoint[multiplied], relative[multiplied], "o-", label="reached (median)")
ax.axhline(2.0, color="k", ls="--", lw=1, label="the plan's target")
ax.set(xscale="log", xlabel="em_gain_setpoint", ylabel="SE of em_gain (%)", ylim=(0, 3))
ax.legend()
plt.show()
