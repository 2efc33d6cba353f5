"""napari's sample data: a simulated EMCCD gain series (what ``emccdcal demo`` uses)."""

from __future__ import annotations

import tempfile
from pathlib import Path

__all__ = ["gain_series"]

#: A small sensor: the calibrate widget runs it in seconds.
SIZE, FRAMES = 32, 1000
#: Clock-induced charge, e-/px/frame: the darks' events, which the gain check reads.
CIC = 0.02


def gain_series(folder=None, *, seed: int = 7) -> list[tuple]:
    """Simulate a gain series (1, 5, 25, 100, 300×, the exact register, clock-induced
    charge in every frame, with darks and a manifest) into ``folder`` (a new temporary folder by default) and open its stacks
    as layers; each layer's metadata names the manifest, which the calibrate widget
    takes."""
    from ..simulate.series import simulate_gain_series
    from ._reader import stack_layer

    folder = (
        Path(folder) if folder is not None else Path(tempfile.mkdtemp(prefix="emccdcal-sample-"))
    )
    sim = simulate_gain_series(
        folder / "gain-series",
        rows=SIZE,
        cols=SIZE,
        frames=FRAMES,
        dark_frames=FRAMES,
        cic=CIC,
        seed=seed,
        progress=False,
    )
    layers = []
    for path in sorted(
        (sim.outdir / "gain-GS").glob("*x-gain.tif"), key=lambda p: float(p.name.split("x-")[0])
    ):
        data, kwargs, kind = stack_layer(path)
        kwargs["metadata"]["emccdcal_manifest"] = str(sim.manifest)
        layers.append((data, kwargs, kind))
    return layers
