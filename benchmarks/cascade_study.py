"""Known-truth study of the EM register model: gains of exact-cascade data under the
gamma and the cascade likelihood.

Two cameras, simulated with an exact Bernoulli-cascade register (32 × 32 = 1024 pixels,
2000 frames, true offset and read-noise maps in the manifests):

* ``paper``: the paper's ProEM (536 stages, φ 3.859 e⁻/ADU, σ 15.5 ADU, E 370 e⁻,
  set-points 1/5/25/100/300 with the paper's gains);
* ``e2v-604``: a CCD201-like register (604 stages, φ 5.2 e⁻/ADU, σ 15.4 ADU, E 150 e⁻,
  set-points 1/5/20/100/400, true gains 0.95 × set-point).

Each is calibrated by ``gs``, ``gs-no1x`` (φ given: the truth) and ``is-gain`` (an
intensity series of six levels at set-point 20 or 25) under both models. Per set-point:
the pixel mean of g against the truth (in SEM and per cent) and the coverage of the
per-pixel 95 % intervals. A JSON of the numbers goes to the path given (default
``cascade_study.json`` in the working directory); the table to stdout
(docs/cascade.md).

Run: ``.venv/bin/python benchmarks/cascade_study.py [OUT.json]``
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from emccdcal import calibrate
from known_truth import COLS, FRAMES, ROWS, coverage, truth_manifest
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

CAMERAS = {
    "paper": dict(
        stages=536,
        e_per_adu=3.859,
        read_noise=15.5,
        offset=587.7,
        photoelectrons=370.0,
        setpoints=(1, 5, 25, 100, 300),
        em_gain=(1, 4.78, 22.95, 90.06, 261.6),
        is_setpoint=25,
        is_gain=22.95,
        is_levels=(50, 100, 200, 400, 800, 1600),
    ),
    "e2v-604": dict(
        stages=604,
        e_per_adu=5.2,
        read_noise=15.4,
        offset=500.0,
        photoelectrons=150.0,
        setpoints=(1, 5, 20, 100, 400),
        em_gain=(1, 4.75, 19.0, 95.0, 380.0),
        is_setpoint=20,
        is_gain=19.0,
        is_levels=(30, 60, 120, 240, 480, 960),
    ),
}


def simulate(base, cam):
    common = dict(
        rows=ROWS,
        cols=COLS,
        frames=FRAMES,
        dark_frames=10,
        e_per_adu=cam["e_per_adu"],
        read_noise=cam["read_noise"],
        offset=cam["offset"],
        multiplication="cascade",
        stages=cam["stages"],
    )
    gs = simulate_gain_series(
        base / "gs",
        setpoints=cam["setpoints"],
        em_gain=cam["em_gain"],
        photoelectrons=cam["photoelectrons"],
        seed=61,
        **common,
    )
    isg = simulate_intensity_series(
        base / "isg",
        levels=cam["is_levels"],
        setpoint=cam["is_setpoint"],
        em_gain=cam["is_gain"],
        seed=62,
        **common,
    )
    return truth_manifest(gs, cam["read_noise"]), truth_manifest(isg, cam["read_noise"])


def judge(est, se, truth):
    est, se = np.ravel(est), np.ravel(se)
    ok = np.isfinite(est) & np.isfinite(se)
    mean = est[ok].mean()
    sem = est[ok].std(ddof=1) / np.sqrt(ok.sum())
    return {
        "truth": truth,
        "mean": float(mean),
        "sem": float(sem),
        "bias_sem": float((mean - truth) / sem),
        "bias_percent": float(100 * (mean - truth) / truth),
        "coverage": coverage(est[ok], se[ok], truth),
        "pixels": int(ok.sum()),
    }


def main(out_json):
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, cam in CAMERAS.items():
            t0 = time.perf_counter()
            gs_manifest, is_manifest = simulate(Path(tmp) / name, cam)
            print(f"# {name}: simulated in {time.perf_counter() - t0:.0f} s", flush=True)
            for method in ("gs", "gs-no1x", "is-gain"):
                for model in ("gamma", "cascade"):
                    manifest = is_manifest if method == "is-gain" else gs_manifest
                    extra = {"e_per_adu": cam["e_per_adu"]} if method != "gs" else {}
                    t0 = time.perf_counter()
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always")
                        ds = calibrate(
                            manifest,
                            method,
                            checks=False,
                            **extra,
                            **(
                                {"em_model": "cascade", "stages": cam["stages"]}
                                if model == "cascade"
                                else {}
                            ),
                        )
                    seconds = time.perf_counter() - t0
                    misfit = [
                        str(w.message).split(";")[0] for w in caught if "misfit" in str(w.message)
                    ]
                    gof = ds.gof_pvalue.values.reshape(ds.gof_pvalue.shape[0], -1)
                    if method == "is-gain":
                        # one gain shared by the levels: judge it once
                        g = ds.em_gain.values.reshape(ds.em_gain.shape[0], -1)[0]
                        se = ds.em_gain_se.values.reshape(ds.em_gain.shape[0], -1)[0]
                        targets = [
                            (
                                cam["is_setpoint"],
                                g,
                                se,
                                cam["is_gain"],
                                float(np.nanmean(gof < 0.01)),
                            )
                        ]
                    else:
                        sps = list(ds.setpoint.values)
                        g = ds.em_gain.values.reshape(len(sps), -1)
                        se = ds.em_gain_se.values.reshape(len(sps), -1)
                        truth = dict(zip(cam["setpoints"], cam["em_gain"]))
                        targets = [
                            (sp, g[i], se[i], truth[int(sp)], float(np.nanmean(gof[i] < 0.01)))
                            for i, sp in enumerate(sps)
                            if sp != 1
                        ]
                    for sp, est, err, truth, flagged in targets:
                        r = dict(
                            camera=name,
                            method=method,
                            em_model=model,
                            setpoint=float(sp),
                            seconds=seconds,
                            gof_flagged=flagged,
                            misfit_warnings=misfit,
                            **judge(est, err, truth),
                        )
                        rows.append(r)
                        print(
                            f"{name:8} {method:8} {model:8} {sp:>5g}x  g {r['mean']:9.4f} "
                            f"(truth {truth:g})  {r['bias_percent']:+7.3f} %  "
                            f"{r['bias_sem']:+6.1f} SEM  coverage {100 * r['coverage']:5.1f} %"
                            f"  gof p<0.01 {100 * flagged:4.1f} %  {seconds:5.1f} s",
                            flush=True,
                        )
    Path(out_json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "cascade_study.json")
