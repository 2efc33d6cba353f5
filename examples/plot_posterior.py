"""
The posterior of one pixel
==========================

A pixel's standard errors come from the curvature of its likelihood at the optimum. Where
that is in doubt (few frames, a skewed likelihood), :func:`emccdcal.sample_posterior`
samples the pixel's whole posterior with emcee (priors flat in the log of each parameter),
and gives its medians and credible intervals beside the fit's.
"""

# %%
# A small intensity series at 1×, and the posterior of one pixel under ``is-adu``.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
sim = emccdcal.simulate_intensity_series(
    work / "is",
    levels=(2000, 8000, 32000),
    rows=3,
    cols=3,
    frames=300,
    seed=51,
    progress=False,
)
fit = emccdcal.calibrate(sim.manifest, method="is-adu", progress=False)
post = emccdcal.sample_posterior(sim.manifest, "is-adu", [(1, 1)], seed=52, progress=False)
phi = post.samples.sel(parameter="e_per_adu").values[0, : int(post.n_draws[0])]
print(
    f"fit: {float(fit.e_per_adu[1, 1]):.4f} ± {float(fit.e_per_adu_se[1, 1]):.4f}; "
    f"posterior median {float(post['median'].sel(parameter='e_per_adu')[0]):.4f}, "
    f"SD {phi.std():.4f} e-/ADU"
)

# %%
# φ's posterior against the normal the fit's standard error draws, and φ against the
# light of the brightest level: the two move together (the counts fix their ratio).
import numpy as np  # noqa: E402

grid = np.linspace(phi.min(), phi.max(), 200)
mu, se = float(fit.e_per_adu[1, 1]), float(fit.e_per_adu_se[1, 1])
names = post.parameter.values.tolist()
light = post.samples.values[0, : int(post.n_draws[0]), names.index(names[-1])]
fig, axes = plt.subplots(1, 2, figsize=(8, 3.4), constrained_layout=True)
axes[0].hist(phi, bins=40, density=True, alpha=0.6, label="posterior")
axes[0].plot(
    grid,
    np.exp(-0.5 * ((grid - mu) / se) ** 2) / (se * np.sqrt(2 * np.pi)),
    "k-",
    lw=1,
    label="fit ± SE",
)
axes[0].set(xlabel="e_per_adu (e⁻/ADU)", ylabel="density")
axes[0].legend()
axes[1].plot(phi, light, ",", alpha=0.4)
axes[1].set(xlabel="e_per_adu (e⁻/ADU)", ylabel=f"{names[-1]}")
plt.show()
