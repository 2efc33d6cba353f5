"""
A qCMOS camera: photoelectrons resolved, per-pixel maps
=======================================================

A photon-number-resolving qCMOS camera (~0.27 e⁻ read noise) shows each pixel's counts as
a comb, one peak per photoelectron 1/φ ADU apart. The calibration of a camera without an
EM register fits every pixel's φ, offset and read noise by the exact likelihood (the
ADC's rounding in it), from a Huang-protocol folder: a dark and a few light levels
(docs: "sCMOS and qCMOS cameras").
"""

# %%
# A simulated ORCA-Quest-like camera: 8 × 8 pixels, a dark and four levels of 0.5 to 10
# photoelectrons per pixel per frame. The manifest names the camera kind, so
# ``calibrate`` needs no method.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import tifffile

import emccdcal
from emccdcal.model import noise
from emccdcal.simulate.cmos import CMOSCamera, simulate_cmos_series

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
camera = CMOSCamera(kind="qcmos", rows=8, cols=8, frames=1500, dark_frames=3000)
sim = simulate_cmos_series(work / "qcmos", camera=camera, seed=60, progress=False)
ds = emccdcal.calibrate(sim.manifest, progress=False)
truth = tifffile.imread(sim.outdir / "truth-e_per_adu.tif")
z = (ds.e_per_adu.values - truth) / ds.e_per_adu_se.values
print(
    f"{ds.attrs['camera_kind']}, {ds.attrs['method']}: φ median "
    f"{float(ds.e_per_adu.median()):.4f} e-/ADU, per-pixel SE "
    f"{float((ds.e_per_adu_se / ds.e_per_adu).median()) * 100:.2f} %, "
    f"RMS z against the truth {np.sqrt(np.mean(z**2)):.2f}"
)

# %%
# One pixel's counts at the brightest level against the fitted model: the comb of
# photoelectron peaks, each as wide as the read noise.
r, c = 3, 4
counts = tifffile.imread(sim.outdir / "int4.tif")[:, r, c].astype(int)
k = np.arange(counts.min(), counts.max() + 1)
observed = np.bincount(counts - k[0], minlength=k.size) / counts.size
E = float(ds.photoelectrons.isel(level=3)[r, c])
model = noise.pmf(
    k, E, 1.0, float(ds.e_per_adu[r, c]), float(ds.offset.isel(level=3)[r, c]),
    float(ds.read_noise.isel(level=3)[r, c]), em_model="gamma",
)  # fmt: skip
fig, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
ax.bar(k, observed, width=1.0, color="0.75", label="counts (1500 frames)")
ax.plot(k, model, "k-", lw=1, label=f"fit: φ = {float(ds.e_per_adu[r, c]):.4f} e⁻/ADU")
ax.set(xlabel="count (ADU)", ylabel="fraction of frames", title=f"pixel ({r}, {c}), E = {E:.1f} e⁻")
ax.legend()
plt.show()

# %%
# The per-pixel maps a localization tool reads: φ, the offset and the read noise (the
# analog σ before the ADC's rounding), each with its standard error in the result.
maps = [
    (ds.e_per_adu.values, "φ (e⁻/ADU)"),
    (ds.offset.isel(level=0).values, "offset (ADU)"),
    (ds.read_noise.isel(level=0).values * ds.e_per_adu.values, "read noise (e⁻)"),
]
fig, axes = plt.subplots(1, 3, figsize=(9, 3), constrained_layout=True)
for ax, (image, title) in zip(axes, maps):
    shown = ax.imshow(image, cmap="viridis")
    ax.set(title=title, xticks=[], yticks=[])
    fig.colorbar(shown, ax=ax, shrink=0.8)
plt.show()
