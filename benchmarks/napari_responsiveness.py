"""Does the napari viewer keep drawing while the Calibrate widget runs a 64 × 64 sensor?

On an X display (Xvfb via ``xvfb-run``, Mesa's software OpenGL), opens a napari viewer, simulates
a 64 × 64 px gain series (1 / 5 / 25 / 100 / 300×, ``--frames`` frames each) and runs the
plugin's Calibrate widget on it, while a 20 ms Qt timer records when the event loop
runs. Prints the run's length, the ticks and the longest gap between them (the viewer
redraws, takes input, only when the loop runs). docs/benchmarks.md holds the figures;
tests/test_napari.py checks the same on the 32 × 32 sample data.

Needs the ``napari-test`` extra and Xvfb (Debian package ``xvfb``, which brings
``xvfb-run``). Run:
``xvfb-run -a -s "-screen 0 1400x1000x24" .venv/bin/python
benchmarks/napari_responsiveness.py [--frames 1000]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    if not os.environ.get("DISPLAY"):
        sys.exit(
            "napari_responsiveness: no X display; run it under xvfb-run "
            "(see the module's docstring)"
        )
    os.environ["QT_QPA_PLATFORM"] = "xcb"
    import napari
    from qtpy.QtCore import QTimer
    from qtpy.QtWidgets import QApplication

    from emccdcal.napari._widgets import CalibrateWidget
    from emccdcal.simulate.series import simulate_gain_series

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_gain_series(
            Path(tmp) / "gs",
            rows=args.size,
            cols=args.size,
            frames=args.frames,
            dark_frames=args.frames,
            seed=7,
            progress=False,
        )
        viewer = napari.Viewer(show=True)
        widget = CalibrateWidget(viewer)
        viewer.window.add_dock_widget(widget, name="Calibrate")
        widget.source.value = sim.manifest
        added = []  # (seconds into the run, seconds) of each layer the widget adds

        class Timed:  # the viewer, its add_image timed
            def __getattr__(self, name):
                return getattr(viewer, name)

            def add_image(self, *a, **k):
                start = time.perf_counter()
                layer = viewer.add_image(*a, **k)
                added.append((start - t0, time.perf_counter() - start))
                return layer

        widget.viewer = Timed()
        widget.out.value = Path(tmp) / "out"
        app = QApplication.instance()
        ticks = []
        timer = QTimer()
        timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
        timer.start(20)
        t0 = time.perf_counter()
        widget.run()
        adding = None  # when the worker was done and the result's layers began
        while widget.status.value.endswith("…"):
            app.processEvents()
            if adding is None and widget.status.value.startswith("adding"):
                adding = time.perf_counter() - t0
            time.sleep(0.005)
        elapsed = time.perf_counter() - t0
        timer.stop()
        gaps = np.diff(ticks)
        print(
            f"{args.size} x {args.size} px, 5 set-points x {args.frames} frames: "
            f"{widget.status.value[:60]}"
        )
        print(
            f"run {elapsed:.1f} s; {len(ticks)} ticks of a 20 ms timer "
            f"({len(ticks) / (elapsed / 0.02):.0%} of those due); gaps: median "
            f"{1000 * np.median(gaps):.0f} ms, 99th percentile "
            f"{1000 * np.percentile(gaps, 99):.0f} ms, longest {1000 * gaps.max():.0f} ms"
        )
        worst = int(np.argmax(gaps))
        print(
            f"the longest gap began {ticks[worst] - t0:.1f} s into the run; the worker "
            f"was done and the layers began at {adding:.1f} s"
        )
        first = added[0][0] if added else elapsed
        during = gaps[np.asarray(ticks[1:]) - t0 <= first]
        print(
            f"while the worker ran ({first:.1f} s): longest gap {1000 * during.max():.0f} "
            f"ms, 99th percentile {1000 * np.percentile(during, 99):.0f} ms"
        )
        print(
            "layers added (s into the run, s each): "
            + ", ".join(f"{a:.1f}/{b:.2f}" for a, b in added)
        )
        viewer.close()


if __name__ == "__main__":
    main()
