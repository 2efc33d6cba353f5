"""
φ from an intensity series, chained into the gains
==================================================

The ADU conversion factor φ (``e_per_adu``, e⁻/ADU) is measured at 1× from an
intensity series (method ``is-adu``), then handed to the gain series: its standard
error enters every gain's, since a gain fit measures g/φ.
"""

# %%
# Two series of one simulated camera (φ = 3.859 e⁻/ADU, the paper's ProEM): an
# intensity series at 1× and a gain series.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
camera = dict(rows=6, cols=6, e_per_adu=3.859)
adu = emccdcal.simulate_intensity_series(work / "adu", frames=1000, seed=1, **camera)
gs = emccdcal.simulate_gain_series(
    work / "gs", frames=1500, setpoints=[1, 25, 300], seed=2, **camera
)

# %%
# Step 1: φ per pixel from the 1× intensity series, one intensity per level.
phi = emccdcal.calibrate(adu.manifest, method="is-adu", out=work / "out-adu")
print(
    f"e_per_adu: median {float(phi.e_per_adu.median()):.4f} e-/ADU "
    f"(truth {adu.truth['e_per_adu']}), median SE {float(phi.e_per_adu_se.median()):.4f}"
)

# %%
# Step 2: the gains, with φ taken from step 1's result, its error included.
chained = emccdcal.calibrate(gs.manifest, method="gs", e_per_adu=work / "out-adu")
print(chained.attrs["e_per_adu_source"])
exact = emccdcal.calibrate(gs.manifest, method="gs", e_per_adu=3.859)  # φ known exactly
for sp in chained.setpoint.values[1:]:
    print(
        f"{sp:>4g}x: gain SE with φ's error {float(chained.em_gain_se.sel(setpoint=sp).median()):.3f}"
        f", with φ exact {float(exact.em_gain_se.sel(setpoint=sp).median()):.3f}"
    )

# %%
# The photon-transfer view of step 1: every level's variance against its mean, per
# pixel, over the line of slope 1/φ that the fit implies at 1×.
from emccdcal.data.stacks import load_stack  # noqa: E402

m = emccdcal.read_manifest(adu.manifest)
fig, ax = plt.subplots(figsize=(5, 3.6), constrained_layout=True)
for a in m.acquisitions:
    frames = load_stack(a.frames_path).astype(float) - a.offset
    ax.plot(frames.mean(axis=0).ravel(), frames.var(axis=0).ravel(), ".", ms=3, label=a.level)
mean = np.linspace(0, ax.get_xlim()[1], 50)
noise2 = float(np.median(m.acquisitions[0].read_noise)) ** 2
ax.plot(
    mean, noise2 + mean / float(phi.e_per_adu.median()), "k-", lw=1, label="read noise² + mean/φ"
)
ax.set(xlabel="mean − offset (ADU)", ylabel="variance (ADU²)")
ax.legend(fontsize=7, ncol=2)
plt.show()
