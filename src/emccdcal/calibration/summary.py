"""A result in a few lines for a terminal (:func:`format_summary`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .. import result
from .._util import nanmedian
from ..defaults import WITHOUT_EM_REGISTER
from ..model import noise
from .tiles import ESTIMATE_E_PER_ADU

if TYPE_CHECKING:
    pass


def format_summary(ds):
    """A short human-readable table of a calibration (median over converged pixels)."""
    ok = ds.converged.values
    model = noise.EMModel.from_attrs(ds.attrs)
    register = model is not None and ds.attrs.get("camera_kind") not in WITHOUT_EM_REGISTER
    lines = [
        f"method {ds.attrs['method']}"
        + (f" ({model.name} register)" if register else "")
        + f": {int(ok.sum())}/{ok.size} pixels converged, "
        f"{ds.attrs.get('seconds', float('nan')):.1f} s; medians over those"
    ]
    if not ok.any():
        return lines[0].replace("; medians over those", "; no estimate to show")
    multiplied = any(float(sp) != 1.0 for sp in ds.setpoint.values)
    if model is not None and model.register.uses_stages and multiplied:
        source = ds.attrs.get("register_stages_source")
        lines.append(
            f"  register length: {model.stages} stages" + (f" ({source})" if source else "")
        )

    def med(v):
        return nanmedian(np.asarray(v)[..., ok], axis=-1)

    phi, phi_se = med(ds.e_per_adu.values), med(ds.e_per_adu_se.values)
    chained = ds.attrs.get("e_per_adu_result")
    if np.isfinite(phi_se) and phi_se > 0:
        how = (
            ""
            if ds.attrs["method"] in ESTIMATE_E_PER_ADU
            else f"; from {chained}"
            if chained
            else "; given with its SE"
        )
        lines.append(
            f"  e_per_adu  {phi:.4f} ± {phi_se:.4f} e-/ADU (adu_per_e {1 / phi:.4f} ADU/e-{how})"
        )
    else:
        lines.append(
            f"  e_per_adu  {phi:.4f} e-/ADU, fixed (given without an error; "
            f"adu_per_e {1 / phi:.4f} ADU/e-)"
        )
    for i, sp in enumerate(ds.setpoint.values):
        g, se = med(ds.em_gain.values[i]), med(ds.em_gain_se.values[i])
        if float(sp) == 1.0:  # no multiplication: g = 1 by the model, not estimated
            lines.append("  em_gain at 1x: 1, fixed (no multiplication)")
        else:
            lines.append(f"  em_gain at {result.format_setpoint(sp)}x: {g:.4f} ± {se:.4f}")
    pe = ds.photoelectrons
    if pe.ndim == 2:
        lines.append(
            f"  photoelectrons {med(pe.values):.2f} ± {med(ds.photoelectrons_se.values):.2f} e-"
        )
    else:
        dim = pe.dims[0]
        for i, lab in enumerate(pe[dim].values):
            lines.append(
                f"  photoelectrons [{dim} {lab}] {med(pe.values[i]):.2f} ± "
                f"{med(ds.photoelectrons_se.values[i]):.2f} e-"
            )
    if "dark_current" in ds:
        lines.append(
            f"  dark_current {med(ds.dark_current.values):.4g} ± "
            f"{med(ds.dark_current_se.values):.2g} e-/s per pixel"
        )
    lines.append("  (± the per-pixel standard error, median over pixels; docs/results.md)")
    return "\n".join(lines)
