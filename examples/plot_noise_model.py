"""
The noise model against a histogram, at 5× and 300×
===================================================

The probability of a pixel's counts given its light, the EM gain, φ, the offset and the
read noise (``emccdcal.noise.pmf``), under the exact register (a Bernoulli cascade of N
stages, the default) and the paper's gamma approximation, against the counts of a
simulated camera whose register is a real cascade.
"""

# %%
import matplotlib.pyplot as plt
import numpy as np

import emccdcal

light, gain, phi, offset, sigma = 30.0, 5.0, 3.859, 587.7, 15.5  # e-, -, e-/ADU, ADU, ADU


def counts_at(em_gain, seed):
    """20000 frames of one pixel of this camera at a true gain, as a flat array."""
    return emccdcal.simulate_frames(
        light,
        em_gain=em_gain,
        e_per_adu=phi,
        offset=offset,
        read_noise=sigma,
        frames=20000,
        rows=1,
        cols=1,
        seed=seed,
    ).ravel()


counts = counts_at(gain, seed=4)
print(f"{counts.size} frames, counts {counts.min()}–{counts.max()} ADU")

# %%
# The model's probabilities of every count seen, under both register models.
s = np.arange(counts.min(), counts.max() + 1)
exact = emccdcal.noise.pmf(
    s, photoelectrons=light, em_gain=gain, e_per_adu=phi, offset=offset, read_noise=sigma
)
gamma = emccdcal.noise.pmf(
    s,
    photoelectrons=light,
    em_gain=gain,
    e_per_adu=phi,
    offset=offset,
    read_noise=sigma,
    em_model="gamma",
)
observed = np.bincount(counts - s[0], minlength=s.size) / counts.size
for name, p in (("cascade", exact), ("gamma", gamma)):
    ll = float(np.sum(np.log(p[counts - s[0]])))
    print(f"{name:>8}: log-likelihood of the frames {ll:.1f} nats")

# %%
# Histogram and model on a log scale: the read-noise peak of the frames with no
# photoelectron, and the multiplied tail of the others.
fig, ax = plt.subplots(figsize=(6, 3.6), constrained_layout=True)
width = 4  # ADU per bin, for the eye
edges = np.arange(s[0], s[-1] + width, width)
ax.hist(counts, bins=edges, density=True, color="0.8", label="simulated counts")
for name, p, style in (("cascade", exact, "-"), ("gamma", gamma, "--")):
    ax.plot(s, p, style, lw=1.2, label=f"pmf, {name} register")
ax.set(yscale="log", ylim=(1e-7, None), xlabel="counts (ADU)", ylabel="probability per ADU")
ax.legend()
plt.show()

# %%
# The same light at the 300× set-point (a true gain of about 262): the multiplied tail
# now spans thousands of ADU, and both models follow it; the exact register differs
# from the gamma approximation at low gains, where each stage's chance matters.
high = 262.0
counts_high = counts_at(high, seed=5)
s_high = np.arange(counts_high.min(), counts_high.max() + 1)
fig, ax = plt.subplots(figsize=(6, 3.6), constrained_layout=True)
ax.hist(
    counts_high,
    bins=np.arange(s_high[0], s_high[-1] + 40, 40),
    density=True,
    color="0.8",
    label="simulated counts, 300x",
)
for name, style in (("cascade", "-"), ("gamma", "--")):
    p = emccdcal.noise.pmf(
        s_high,
        photoelectrons=light,
        em_gain=high,
        e_per_adu=phi,
        offset=offset,
        read_noise=sigma,
        em_model=name,
    )
    ax.plot(s_high, p, style, lw=1.2, label=f"pmf, {name} register")
ax.set(yscale="log", ylim=(1e-8, None), xlabel="counts (ADU)", ylabel="probability per ADU")
ax.legend()
plt.show()
