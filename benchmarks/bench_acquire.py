"""``emccdcal acquire``'s overhead: frames written per second against the rate the core
delivers them, with Micro-Manager's DemoCamera at its fastest; and its memory over a
long acquisition.

The core's rate: a sequence of the same frames popped from the core's buffer and
dropped, timed from the sequence's start to the last frame. acquire's: the same frames
recorded by ``acquire`` (a two-set-point plan of darks and lights, light check off), timed
from the call to its return (the session made, each stack's settings read and its file
written to the last frame). Runs alternate (this machine is shared); medians are compared as a ratio.
Memory: the peak resident memory of a fresh process recording a short and a four times
longer plan at 128 x 128 px (the session's frames are on disk, never all in memory).

Usage: python benchmarks/bench_acquire.py [--frames N] [--repeats R]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIG = """\
Device,Camera,DemoCamera,DCam
Device,Shutter,DemoCamera,DShutter
Property,Core,Initialize,1
Property,Camera,PixelType,16bit
Property,Camera,FastImage,1
Property,Camera,Exposure,0
Property,Core,Camera,Camera
Property,Core,Shutter,Shutter
"""


def _plan(folder: Path, frames: int) -> Path:
    from emccdcal.acquire.plan import predict
    from emccdcal.acquire.plan_file import plan_text

    p = predict(
        "gs",
        [1, 2],
        [1, 2],
        [100.0, 100.0],
        [frames, frames],
        frames,
        dict(
            e_per_adu=1.0, read_noise=2.5, offset=100.0, adc_bits=16, em_model="gamma", stages=None
        ),
        float("nan"),
    )
    path = folder / f"plan-{frames}.toml"
    path.write_text(plan_text(p))
    return path


def core_rate(config: Path, frames: int, roi=None) -> float:
    from emccdcal.acquire.record import config_core

    core = config_core(config)
    if roi is not None:
        core.setROI(*roi)
    try:
        start, got = time.perf_counter(), 0  # the camera's start counted, as in acquire's
        core.startSequenceAcquisition(frames, 0.0, True)
        while got < frames:
            if core.getRemainingImageCount() > 0:
                core.popNextImage()
                got += 1
            elif not core.isSequenceRunning() and core.getRemainingImageCount() == 0:
                break
            else:
                time.sleep(0.0002)
        return got / (time.perf_counter() - start)
    finally:
        core.stopSequenceAcquisition()
        core.unloadAllDevices()


def acquire_rate(config: Path, plan: Path, out: Path, frames: int, roi=None) -> float:
    from emccdcal.acquire import record

    core = record.config_core(config)
    try:
        start = time.perf_counter()
        record.acquire(
            plan,
            out,
            core=core,
            gain_prop="Gain",
            light_tolerance=None,
            roi=roi,
            progress=False,
        )
        return 4 * frames / (time.perf_counter() - start)
    finally:
        core.unloadAllDevices()


def _peak_rss(plan: Path, out: Path, config: Path) -> float:
    code = (
        "import resource, sys; from emccdcal.acquire import record; "
        f"core = record.config_core({str(config)!r}); "
        f"record.acquire({str(plan)!r}, {str(out)!r}, core=core, gain_prop='Gain', "
        "light_tolerance=None, roi=(192, 192, 128, 128), progress=False); "
        "core.unloadAllDevices(); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000, help="frames per stack")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        config = tmp / "demo.cfg"
        config.write_text(CONFIG)
        plan = _plan(tmp, args.frames)
        for roi in (None, (192, 192, 128, 128)):
            cores, ours = [], []
            for r in range(args.repeats):
                cores.append(core_rate(config, 4 * args.frames, roi))
                out = tmp / f"session-{r}"
                ours.append(acquire_rate(config, plan, out, args.frames, roi))
                shutil.rmtree(out)
            rows.append(
                {
                    "frame": "512 x 512" if roi is None else "128 x 128 (--roi)",
                    "core_fps": [round(c) for c in cores],
                    "acquire_fps": [round(c) for c in ours],
                    "ratio_of_medians": round(
                        statistics.median(ours) / statistics.median(cores), 3
                    ),
                }
            )
        long_plan = _plan(tmp, 4 * args.frames)
        rss = {
            n: _peak_rss(p, tmp / f"rss-{n}", config)
            for n, p in ((args.frames, plan), (4 * args.frames, long_plan))
        }
    print(
        json.dumps(
            {
                "camera": "DemoCamera, uint16, FastImage, exposure 0 ms",
                "frames_per_run": 4 * args.frames,
                "rates": rows,
                "peak_rss_mib_by_frames_per_stack": {str(k): round(v, 1) for k, v in rss.items()},
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
