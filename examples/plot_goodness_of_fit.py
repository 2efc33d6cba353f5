"""
Goodness of fit, and the verdict
================================

Every likelihood fit says, per pixel and acquisition, whether the noise model explains
the counts (``gof_pvalue``). A model the data reject at most pixels of an acquisition
makes the calibration's verdict doubtful, naming the acquisition and what to check. Here
the paper's gamma approximation of the EM register is fitted to a camera whose register
is a real cascade, beside the exact model.
"""

# %%
# A gain series of a real (cascade) register at low gains, where the gamma
# approximation is furthest from it; both models fitted.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_gain_series(
    work / "gs", rows=6, cols=6, frames=5000, setpoints=[1, 2, 5, 100], seed=61, progress=False
)
phi = sim.truth["e_per_adu"]
fits = {
    model: emccdcal.calibrate(sim.manifest, e_per_adu=phi, em_model=model, progress=False)
    for model in ("cascade", "gamma")
}
for model, ds in fits.items():
    print(f"{model}: {ds.attrs['verdict'][:160]}")

# %%
# The p-value maps at 2×: uniform for a model that fits, piled near 0 for one that
# does not.
fig, axes = plt.subplots(1, 2, figsize=(8, 3.4), constrained_layout=True)
for ax, (model, ds) in zip(axes, fits.items()):
    p = ds.gof_pvalue.sel(setpoint=2)
    im = ax.imshow(np.log10(p), vmin=-6, vmax=0, cmap="magma")
    ax.set_title(f"{model}: log10 p at 2x ({int((p < 0.01).sum())} px < 0.01)")
fig.colorbar(im, ax=axes, label="log10 gof_pvalue")
plt.show()
