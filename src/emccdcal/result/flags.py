"""The per-pixel flags a result may hold: pixels the dark frames showed not to be one
normal, each a variable of 1 (flagged) and 0, on (row, col).

One table for every place that shows or carries them: the report's notes, napari's
layers, the OME-TIFF export's masks and :class:`emccdcal.result.use.Calibration`.
"""

from __future__ import annotations

from typing import NamedTuple

from ..data.telegraph import FALSE_ALARM
from ..defaults import DEFAULT_K

__all__ = ["PIXEL_FLAGS", "PixelFlag"]


class PixelFlag(NamedTuple):
    """What a flag says (``title``, a sentence's subject), what follows from it
    (``meaning``) and its napari layer's name (``layer``)."""

    title: str
    meaning: str
    layer: str


#: The flags by variable name, in the order they are shown.
PIXEL_FLAGS = {
    "stuck": PixelFlag(
        "Stuck pixels (dark counts that never change: dead, or stuck at one value)",
        "they have no read noise to measure and are left out of the fit (NaN, converged False)",
        "stuck pixels",
    ),
    "telegraph": PixelFlag(
        "Random-telegraph pixels (two or more offset states in the dark frames, tested at a "
        f"{100 * FALSE_ALARM:g} % false-alarm rate)",
        "their offset, read noise and φ are doubtful",
        "telegraph pixels",
    ),
    "hot": PixelFlag(
        f"Hot pixels (a dark current more than {DEFAULT_K:g} robust SDs above the median pixel's)",
        "their dark signal adds to every frame's",
        "hot pixels",
    ),
}
