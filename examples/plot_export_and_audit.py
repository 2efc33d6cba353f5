"""
Export to Picasso, and audit what a tool reads
==============================================

A localization tool wants its own camera numbers: Picasso a sensitivity in e⁻/ADU, an
EM gain, a baseline in ADU and a quantum efficiency. :func:`emccdcal.export_calibration`
(``emccdcal export``) writes them from a calibration, in the tool's own file and
convention; :func:`emccdcal.audit` (``emccdcal audit``) reads a tool's file back and says, number by number, whether it agrees with the calibration, and by
how much a wrong number would bias the photons the tool reports.
"""

# %%
# A calibration of a simulated camera: φ from a 1× intensity series, the gains from a
# gain series.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import yaml

import emccdcal

scratch = tempfile.TemporaryDirectory(prefix="emccdcal-gallery-")  # removed at the end
work = Path(scratch.name)
camera = dict(rows=8, cols=8, e_per_adu=3.859)
adu = emccdcal.simulate_intensity_series(work / "adu", frames=800, seed=21, **camera)
gs = emccdcal.simulate_gain_series(
    work / "gs", frames=1000, setpoints=[1, 10, 100], seed=22, **camera
)
phi = emccdcal.calibrate(adu.manifest, method="is-adu")
gains = emccdcal.calibrate(gs.manifest, method="gs", e_per_adu=phi)
pair = [phi, gains]  # a calibration of two results: φ from one, the gains from the other

# %%
# Export the numbers Picasso reads at the 100× set-point.
(config,) = emccdcal.export_calibration(
    pair, "picasso", work / "picasso", setpoint=100, pixel_size_nm=107
)
print(config.read_text())

# %%
# The audit of that file: every number agrees.
for audit in emccdcal.audit(config, pair, setpoint=100):
    print("\n".join(audit.lines()))
    assert audit.ok

# %%
# A hand-typed file, with the camera's nominal numbers (gain 100, where the true gain at
# that set-point is lower, and a round baseline), is flagged, with the bias it causes in
# the photons the tool reports.
typed = yaml.safe_load(config.read_text())
entry = typed["Cameras"]["EMCCD (emccdcal)"]
entry.update(DefaultGain=100, Sensitivity=3.859, Baseline=500)
(work / "typed.yaml").write_text(yaml.safe_dump(typed))
(audit,) = emccdcal.audit(work / "typed.yaml", pair, setpoint=100)
print("\n".join(audit.lines()))
assert not audit.ok  # the audit's "off"

# %%
# Pixel by pixel: the photons each file makes of a pixel's counts, against the
# calibration's own φ/g there (Picasso reads one Sensitivity / Gain for the sensor).
phi_map = phi.e_per_adu.values
gain = gains.em_gain.sel(setpoint=100).values
exported = yaml.safe_load(config.read_text())["Cameras"]["EMCCD (emccdcal)"]
fig, ax = plt.subplots(figsize=(5.5, 3.4), constrained_layout=True)
for label, e in (("exported", exported), ("hand-typed", entry)):
    bias = (e["Sensitivity"] / e["DefaultGain"]) / (phi_map / gain) - 1
    ax.hist(100 * bias.ravel(), bins=20, alpha=0.7, label=label)
ax.set(xlabel="photon bias per pixel (%)", ylabel="pixels")
ax.legend()
plt.show()
