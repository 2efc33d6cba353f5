"""
Photon transfer: φ from the variance, and from the likelihood
=============================================================

The classic way to φ is the photon-transfer curve: at EM gain off, a pixel's variance
grows with its mean as mean / φ + read noise². :func:`emccdcal.calibrate` fits it two
ways: ``mv-adu``, the slope of that line (the mean–variance method, with Fieller bounds), and
``is-adu``, the likelihood of every count (the default for φ): here they agree within
their standard errors.
"""

# %%
# An intensity series at 1×: six levels of a flat light, dark maps beside them.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import tifffile

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_intensity_series(
    work / "is", rows=8, cols=8, frames=600, e_per_adu=3.859, seed=31, progress=False
)
mle = emccdcal.calibrate(sim.manifest, method="is-adu", progress=False)
mv = emccdcal.calibrate(sim.manifest, method="mv-adu", progress=False)
for name, ds in (("is-adu", mle), ("mv-adu", mv)):
    print(
        f"{name}: e_per_adu {float(ds.e_per_adu.median()):.4f} "
        f"± {float(ds.e_per_adu_se.median()):.4f} e-/ADU (median SE per pixel)"
    )

# %%
# The curve itself, from the stacks: each level's mean and variance above the offset,
# per pixel, against the line the likelihood's φ and read noise draw.
manifest = emccdcal.read_manifest(sim.manifest)
means, variances = [], []
for acquisition in manifest.acquisitions:
    counts = tifffile.imread(acquisition.frames_path).astype(float) - acquisition.offset
    means.append(counts.mean(axis=0).ravel())
    variances.append(counts.var(axis=0, ddof=1).ravel())
phi = float(mle.e_per_adu.median())
sigma = float(np.median(manifest.acquisitions[0].read_noise))
line = np.geomspace(min(map(np.min, means)), max(map(np.max, means)), 50)
fig, ax = plt.subplots(figsize=(5.5, 3.6), constrained_layout=True)
for m, v in zip(means, variances):
    ax.plot(m, v, ".", ms=3, color="C0", alpha=0.5)
ax.plot(line, line / phi + sigma**2, "k-", lw=1, label=f"mean / φ + σ², φ = {phi:.3f}")
ax.set(xscale="log", yscale="log", xlabel="mean − offset (ADU)", ylabel="variance (ADU²)")
ax.legend()
plt.show()

# %%
# Per pixel, the two estimates: each scatters about the truth by its standard error.
fig, ax = plt.subplots(figsize=(5.5, 3.4), constrained_layout=True)
ax.hist(mv.e_per_adu.values.ravel(), bins=15, alpha=0.6, label="mv-adu")
ax.hist(mle.e_per_adu.values.ravel(), bins=15, alpha=0.6, label="is-adu")
ax.axvline(sim.truth["e_per_adu"], color="k", ls="--", lw=1, label="truth")
ax.set(xlabel="e_per_adu (e⁻/ADU)", ylabel="pixels")
ax.legend()
plt.show()
