"""The simulator: moments against the model, effects, files, reproducibility, CLI, demo."""

from __future__ import annotations

import doctest
import io
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import tifffile

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

from emccdcal import cli
from emccdcal.data.manifest import read_manifest
from emccdcal.demo import run_demo
from emccdcal.model.cascade import excess_noise_factor
from emccdcal.simulate.beads import bead_scene, simulate_beads
from emccdcal.simulate.camera import (
    expected_moments,
    offset_at_setpoint,
    simulate_frames,
)
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

PHI = 3.859
SIGMA = 15.5


def _check_moments(counts, mean, var):
    """Sample mean and variance of ``counts`` within 4.5 standard errors of (mean, var)."""
    x = counts.astype(np.float64).ravel()
    n = x.size
    dev = x - x.mean()
    m2, m4 = np.mean(dev**2), np.mean(dev**4)
    se_mean = math.sqrt(m2 / n)
    se_var = math.sqrt((m4 - m2**2) / n)
    assert abs(x.mean() - mean) < 4.5 * se_mean, (x.mean(), mean, se_mean)
    assert abs(x.var(ddof=1) - var) < 4.5 * se_var, (x.var(ddof=1), var, se_var)


# --------------------------------------------------------------------------------------
# Moments of simulated counts against the model
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "g, multiplication, f2",
    [
        (1.0, "gamma", 1.0),  # 1×: Poisson–normal, no multiplication
        (25.0, "gamma", 2.0),
        (4.78, "cascade", float(excess_noise_factor(4.78, 536))),
        (90.06, "cascade", float(excess_noise_factor(90.06, 536))),
    ],
)
def test_frame_moments_match_model(g, multiplication, f2):
    E, S0 = 370.0, 583.9
    counts = simulate_frames(
        E, g, PHI, S0, SIGMA, frames=1500, rows=16, cols=16, multiplication=multiplication, seed=7
    )
    assert counts.shape == (1500, 16, 16) and counts.dtype == np.uint16
    mean = S0 + g * E / PHI
    var = SIGMA**2 + 1 / 12 + f2 * E * (g / PHI) ** 2
    _check_moments(counts, mean, var)
    m, v = expected_moments(E, g, PHI, S0, SIGMA, frames=1500, multiplication=multiplication)
    assert m == pytest.approx(mean, rel=1e-12) and v == pytest.approx(var, rel=1e-12)


@pytest.mark.parametrize(
    "E, g, phi, S0, sigma",
    [
        (370.0, 1.0, PHI, 587.7, SIGMA),
        (370.0, 4.78, PHI, 583.9, SIGMA),
        (60.0, 9.1, 12.0, 990.0, 40.0),
        (2.0, 261.6, PHI, 566.2, SIGMA),
    ],
)
def test_gamma_counts_follow_noise_model_pmf(E, g, phi, S0, sigma):
    """Chi-square of the simulated histogram against emccdcal.noise.pmf (≤ 60 equiprobable bins).

    The model's read noise is the SD of the rounded read-out, sqrt(σ² + 1/12).
    """
    from scipy import stats

    from emccdcal.model import noise

    c = (
        simulate_frames(
            E, g, phi, S0, sigma, frames=1000, rows=16, cols=16, seed=21, multiplication="gamma"
        )
        .ravel()
        .astype(int)
    )
    ks = np.arange(c.min() - 50, c.max() + 51)
    cdf = np.cumsum(noise.pmf(ks, E, g, phi, S0, math.sqrt(sigma**2 + 1 / 12), em_model="gamma"))
    # bin i holds ks[edges[i-1]] < k <= ks[edges[i]] (narrow pmfs give fewer than 60 bins)
    edges = np.unique(np.searchsorted(cdf, np.linspace(0, 1, 61)[1:-1]))
    observed = np.bincount(np.searchsorted(ks[edges], c, side="left"), minlength=edges.size + 1)
    expected = np.diff(np.concatenate(([0.0], cdf[edges], [cdf[-1]]))) * c.size / cdf[-1]
    assert stats.chisquare(observed, expected).pvalue > 1e-3


def test_cascade_and_gamma_differ_at_low_gain():
    """At 5× the cascade's variance is ~10% below the gamma model's: detectable."""
    kw = dict(frames=2000, rows=16, cols=16, seed=3)
    v_gamma = simulate_frames(370.0, 5.0, PHI, 580.0, SIGMA, multiplication="gamma", **kw).var()
    v_casc = simulate_frames(370.0, 5.0, PHI, 580.0, SIGMA, multiplication="cascade", **kw).var()
    signal_ratio = (v_casc - SIGMA**2) / (v_gamma - SIGMA**2)
    assert signal_ratio == pytest.approx(float(excess_noise_factor(5.0, 536)) / 2, abs=0.03)


def test_cascade_methods_agree():
    kw = dict(frames=400, rows=8, cols=8, multiplication="cascade")
    a = simulate_frames(50.0, 25.0, PHI, 500.0, SIGMA, cascade_method="stages", seed=1, **kw)
    b = simulate_frames(50.0, 25.0, PHI, 500.0, SIGMA, cascade_method="pmf", seed=2, **kw)
    mean = 500.0 + 25.0 * 50.0 / PHI
    var = SIGMA**2 + 1 / 12 + float(excess_noise_factor(25.0, 536)) * 50.0 * (25.0 / PHI) ** 2
    _check_moments(a, mean, var)
    _check_moments(b, mean, var)


def test_rounding_adds_one_twelfth():
    """Counts are rounded continuous values: dark variance σ² + 1/12 (σ = 1 ADU)."""
    dark = simulate_frames(0.0, 1.0, PHI, 100.3, 1.0, frames=2000, rows=16, cols=16, seed=11)
    _check_moments(dark, 100.3, 1.0 + 1 / 12)
    assert dark.var() > 1.04  # σ² alone is excluded


def test_maps_broadcast_per_pixel():
    E = np.zeros((4, 6))
    E[:, 3:] = 1000.0
    off = np.full((4, 6), 200.0)
    off[0] = 300.0
    counts = simulate_frames(E, 1.0, 4.0, off, 2.0, frames=3000, seed=2)
    assert counts.shape == (3000, 4, 6)
    means = counts.mean(axis=0)
    np.testing.assert_allclose(means, off + E / 4.0, atol=0.5)


# --------------------------------------------------------------------------------------
# Effects: CIC, drift, saturation
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("multiplication", ["gamma", "cascade"])
def test_cic_in_signal_and_darks(multiplication):
    c, g, S0, E = 0.5, 50.0, 570.0, 20.0
    f2 = 2.0 if multiplication == "gamma" else float(excess_noise_factor(g, 536))
    kw = dict(frames=1500, rows=16, cols=16, cic=c, multiplication=multiplication)
    dark = simulate_frames(0.0, g, PHI, S0, SIGMA, seed=5, **kw)
    _check_moments(dark, S0 + g * c / PHI, SIGMA**2 + 1 / 12 + f2 * c * (g / PHI) ** 2)
    signal = simulate_frames(E, g, PHI, S0, SIGMA, seed=6, **kw)
    _check_moments(
        signal, S0 + g * (E + c) / PHI, SIGMA**2 + 1 / 12 + f2 * (E + c) * (g / PHI) ** 2
    )
    # CIC is multiplied: at 1× the same charge shifts the dark mean by c/φ only.
    dark1 = simulate_frames(0.0, 1.0, PHI, S0, SIGMA, seed=5, **kw)
    _check_moments(dark1, S0 + c / PHI, SIGMA**2 + 1 / 12 + c / PHI**2)


def test_illumination_drift():
    E, S0, d, T = 370.0, 587.7, 0.2, 2000
    counts = simulate_frames(E, 1.0, PHI, S0, SIGMA, frames=T, rows=16, cols=16, drift=d, seed=8)
    frame_means = counts.reshape(T, -1).mean(axis=1)
    t = np.arange(T)
    slope, intercept = np.polyfit(t, frame_means, 1)
    change = slope * (T - 1)  # fitted change from first to last frame, ADU
    expected_change = d * E / PHI
    resid_sd = np.std(frame_means - (intercept + slope * t))
    se_change = resid_sd * math.sqrt(12.0 / T)
    assert abs(change - expected_change) < 5 * se_change
    assert abs(change - expected_change) / expected_change < 0.02
    # The mean over the acquisition stays at E; the drift adds its own spread.
    var_t = (d * E) ** 2 * (T + 1) / (12 * (T - 1)) / PHI**2
    _check_moments(counts, S0 + E / PHI, SIGMA**2 + 1 / 12 + E / PHI**2 + var_t)
    m, v = expected_moments(E, 1.0, PHI, S0, SIGMA, frames=T, drift=d)
    assert v == pytest.approx(SIGMA**2 + 1 / 12 + E / PHI**2 + var_t, rel=1e-12)


def test_adc_saturation_is_a_clip():
    """Same seed, fewer bits: exactly the 16-bit counts clipped at 2**bits − 1."""
    kw = dict(frames=500, rows=8, cols=8, seed=9)
    full = simulate_frames(64.0, 25.0, PHI, 600.0, SIGMA, adc_bits=16, **kw)
    ten = simulate_frames(64.0, 25.0, PHI, 600.0, SIGMA, adc_bits=10, **kw)
    assert ten.max() == 1023
    assert 0.1 < np.mean(ten == 1023) < 0.9
    np.testing.assert_array_equal(ten, np.minimum(full, 1023))


def test_clip_at_zero():
    counts = simulate_frames(0.0, 1.0, PHI, 0.0, SIGMA, frames=1000, rows=8, cols=8, seed=10)
    assert counts.min() == 0
    # P(round(N(0, σ)) ≤ 0) = Φ(0.5/σ)
    p0 = 0.5 * (1 + math.erf(0.5 / SIGMA / math.sqrt(2)))
    assert np.mean(counts == 0) == pytest.approx(p0, abs=4 * math.sqrt(p0 * (1 - p0) / counts.size))


def test_reproducible_frames():
    kw = dict(frames=50, rows=4, cols=4, multiplication="cascade")
    a = simulate_frames(370.0, 22.95, seed=42, **kw)
    b = simulate_frames(370.0, 22.95, seed=np.random.default_rng(42), **kw)
    c = simulate_frames(370.0, 22.95, seed=43, **kw)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(frames=-5), "frames"),
        (dict(frames=2.5), "frames"),
        (dict(multiplication="poisson"), "multiplication"),
        (dict(em_gain=0.5), "em_gain"),
        (dict(e_per_adu=0.0), "e_per_adu"),
        (dict(read_noise=0.0), "read_noise"),
        (dict(offset=-1.0), "offset"),
        (dict(cic=-0.1), "cic"),
        (dict(drift=2.5), "drift"),
        (dict(adc_bits=17), "adc_bits"),
        (dict(stages=0), "stages"),
        (dict(photoelectrons=np.ones((3, 3)), rows=4, cols=4), "photoelectrons"),
        (dict(photoelectrons=np.nan), "photoelectrons"),
        (dict(cascade_method="fast"), "cascade_method"),
    ],
)
def test_simulate_frames_bad_input(kwargs, name):
    args = dict(photoelectrons=10.0, frames=3, rows=2, cols=2) | kwargs
    with pytest.raises(ValueError, match=name):
        simulate_frames(**args)


# --------------------------------------------------------------------------------------
# Files: gain series, intensity series
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gain_series(tmp_path_factory):
    out = tmp_path_factory.mktemp("gs")
    return simulate_gain_series(
        out, rows=6, cols=5, frames=400, dark_frames=300, seed=123, cic=0.02
    )


def _manifest(path):
    with open(path, "rb") as fh:
        return tomllib.load(fh)


def test_gain_series_files(gain_series):
    res = gain_series
    doc = _manifest(res.manifest)
    assert doc["e_per_adu"] == pytest.approx(3.859)
    assert doc["adc_bits"] == 16
    acqs = doc["acquisition"]
    assert [a["em_gain_setpoint"] for a in acqs] == [1, 5, 25, 100, 300]
    truth = json.loads(res.truth_path.read_text())
    assert truth == res.truth
    assert truth["seed"] == 123 and truth["kind"] == "gain-series"
    assert truth["units"]["e_per_adu"] == "e-/ADU" and truth["units"]["offset"] == "ADU"
    assert [a["em_gain"] for a in truth["acquisitions"]] == [1.0, 4.78, 22.95, 90.06, 261.6]
    pattern = tifffile.imread(res.outdir / truth["offset_pattern"]["file"])
    assert pattern.shape == (6, 5) and pattern.dtype == np.float32
    for a, t in zip(acqs, truth["acquisitions"]):
        assert set(a) >= {"frames", "em_gain_setpoint", "offset", "read_noise"}
        assert "level" not in a
        stack = tifffile.imread(res.manifest.parent / a["frames"])
        assert stack.shape == (400, 6, 5) and stack.dtype == np.uint16
        dark = tifffile.imread(res.outdir / t["dark"])
        assert dark.shape == (300, 6, 5) and dark.dtype == np.uint16
        off = tifffile.imread(res.manifest.parent / a["offset"])
        sd = tifffile.imread(res.manifest.parent / a["read_noise"])
        assert off.dtype == np.float32 and sd.dtype == np.float32 and off.shape == (6, 5)
        np.testing.assert_allclose(off, dark.mean(axis=0), rtol=1e-6)
        np.testing.assert_allclose(sd, dark.std(axis=0, ddof=1), rtol=1e-5)
        # dark maps: offset level + pattern, SD ≈ sqrt(σ² + 1/12) (+ CIC, tiny here)
        s = t["em_gain_setpoint"]
        assert t["offset"] == pytest.approx(offset_at_setpoint(s, 587.7, 8.68))
        exp_dark_sd = math.sqrt(t["expected"]["dark_variance"])
        assert abs(
            np.mean(off - pattern) - t["expected"]["dark_mean"]
        ) < 4 * exp_dark_sd / math.sqrt(dark.size)
        assert np.mean(sd**2) == pytest.approx(
            exp_dark_sd**2, rel=4 * math.sqrt(2 / dark.size) * 1.3
        )
        # signal mean against truth
        m = stack.astype(float).mean() - pattern.mean()
        assert abs(m - t["expected"]["mean"]) < 4.5 * math.sqrt(
            t["expected"]["variance"] / stack.size
        )
    assert set(res.files) >= {res.manifest, res.truth_path}
    assert all(p.exists() for p in res.files)
    assert not [p for p in res.outdir.rglob(".*")]  # no temporary files left behind


@pytest.mark.filterwarnings("ignore::UserWarning")  # io flags the CIC in the darks
def test_gain_series_readable_by_io(gain_series):
    m = read_manifest(gain_series.manifest)
    assert m.shape == (6, 5)
    assert tuple(m.setpoints) == (1.0, 5.0, 25.0, 100.0, 300.0)


def test_gain_series_options(tmp_path):
    res = simulate_gain_series(
        tmp_path,
        setpoints=[1, 50],
        em_gain=None,
        rows=3,
        cols=3,
        frames=20,
        dark_frames=2000,
        offset=500.0,
        offset_drop=0.0,
        offset_spread=0.0,
        seed=1,
    )
    t = res.truth
    assert [a["em_gain"] for a in t["acquisitions"]] == [1.0, 50.0]  # default: the set-point
    assert [a["offset"] for a in t["acquisitions"]] == [500.0, 500.0]
    dark_means = [tifffile.imread(tmp_path / a["offset_map"]).mean() for a in t["acquisitions"]]
    np.testing.assert_allclose(dark_means, 500.0, atol=4 * SIGMA / math.sqrt(9 * 2000))
    res2 = simulate_gain_series(
        tmp_path / "b",
        setpoints=[5, 25],
        em_gain=[4.0, 20.0],
        offsets=[590, 580],
        rows=2,
        cols=2,
        frames=5,
        seed=1,
    )
    assert [a["em_gain"] for a in res2.truth["acquisitions"]] == [4.0, 20.0]
    assert [a["offset"] for a in res2.truth["acquisitions"]] == [590.0, 580.0]


def test_gain_series_illumination_per_setpoint(tmp_path):
    """One E per set-point: recorded in truth.json, and seen in the frames' means."""
    res = simulate_gain_series(
        tmp_path,
        setpoints=[1, 10],
        em_gain=[1.0, 10.0],
        photoelectrons=[200.0, 400.0],
        rows=4,
        cols=4,
        frames=400,
        offset=500.0,
        offset_drop=0.0,
        offset_spread=0.0,
        seed=3,
    )
    acqs = res.truth["acquisitions"]
    assert [a["photoelectrons"] for a in acqs] == [200.0, 400.0]
    phi = res.truth["e_per_adu"]
    for a in acqs:
        signal = tifffile.imread(tmp_path / a["frames"]).mean() - 500.0  # ADU
        expected = a["photoelectrons"] * a["em_gain"] / phi
        assert signal == pytest.approx(expected, rel=0.02), a["label"]
    with pytest.raises(ValueError, match="photoelectrons has 3 value"):
        simulate_gain_series(
            tmp_path / "b",
            setpoints=[1, 10],
            photoelectrons=[1.0, 2.0, 3.0],
            rows=2,
            cols=2,
            frames=2,
            seed=1,
        )


def test_gain_series_reproducible(tmp_path):
    kw = dict(
        rows=4, cols=3, frames=30, dark_frames=10, multiplication="cascade", cic=0.1, drift=0.05
    )
    a = simulate_gain_series(tmp_path / "a", seed=5, **kw)
    b = simulate_gain_series(tmp_path / "b", seed=5, **kw)
    c = simulate_gain_series(tmp_path / "c", seed=6, **kw)
    names = sorted(p.relative_to(a.outdir) for p in a.files)
    assert names == sorted(p.relative_to(b.outdir) for p in b.files)
    for rel in names:
        assert (a.outdir / rel).read_bytes() == (b.outdir / rel).read_bytes(), rel
    stacks = [rel for rel in names if rel.name.endswith("-gain.tif")]
    assert len(stacks) == 5
    assert all((a.outdir / rel).read_bytes() != (c.outdir / rel).read_bytes() for rel in stacks)


def test_unseeded_run_records_its_seed(tmp_path):
    a = simulate_gain_series(tmp_path / "a", setpoints=[1, 5], rows=2, cols=2, frames=10)
    b = simulate_gain_series(
        tmp_path / "b", setpoints=[1, 5], rows=2, cols=2, frames=10, seed=a.truth["seed"]
    )
    assert (a.outdir / "gain-GS/5x-gain.tif").read_bytes() == (
        b.outdir / "gain-GS/5x-gain.tif"
    ).read_bytes()


def test_intensity_series_files(tmp_path):
    res = simulate_intensity_series(tmp_path, rows=4, cols=4, frames=300, seed=3)
    doc = _manifest(res.manifest)
    assert "e_per_adu" not in doc  # at 1× the series is what measures it
    acqs = doc["acquisition"]
    assert [a["level"] for a in acqs] == ["L1", "L2", "L3", "L4", "L5", "L6"]
    assert {a["offset"] for a in acqs} == {"intensity-IS/1x-gain_no-signal_S0.tif"}
    assert all(a["em_gain_setpoint"] == 1 for a in acqs)
    truth = res.truth
    levels = [a["photoelectrons"] for a in truth["acquisitions"]]
    assert levels == [2000.0, 4000.0, 8000.0, 16000.0, 32000.0, 64000.0]
    for a, t in zip(acqs, truth["acquisitions"]):
        stack = tifffile.imread(tmp_path / a["frames"])
        assert stack.shape == (300, 4, 4)
        m = stack.astype(float).mean()
        assert abs(m - t["expected"]["mean"]) < 0.5 + 4.5 * math.sqrt(
            t["expected"]["variance"] / stack.size
        )
    res2 = simulate_intensity_series(
        tmp_path / "g",
        levels=[10, 20],
        labels=["lo", "hi"],
        setpoint=100,
        rows=2,
        cols=2,
        frames=5,
        seed=1,
    )
    doc2 = _manifest(res2.manifest)
    assert doc2["e_per_adu"] == pytest.approx(3.859)
    assert [a["level"] for a in doc2["acquisition"]] == ["lo", "hi"]
    assert res2.truth["acquisitions"][0]["em_gain"] == 90.06
    assert res2.truth["acquisitions"][0]["offset"] == pytest.approx(587.7 - 8.68 * 2)


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda d: simulate_gain_series(d, em_gain=[1, 2]), "em_gain has 2"),
        (lambda d: simulate_gain_series(d, setpoints=[1, 1]), "setpoints"),
        (lambda d: simulate_gain_series(d, setpoints=[0.5]), "setpoints"),
        (lambda d: simulate_gain_series(d, offsets=[1.0]), "offsets"),
        (lambda d: simulate_gain_series(d, frames=0), "frames"),
        (lambda d: simulate_gain_series(d, dark_frames=1), "dark_frames"),
        (lambda d: simulate_gain_series(d, offset=10, offset_drop=20), "offset"),
        (lambda d: simulate_gain_series(d, seed=-1), "seed"),
        (lambda d: simulate_intensity_series(d, labels=["a"]), "labels"),
        (lambda d: simulate_intensity_series(d, levels=[1, 2], labels=["a/b", "c"]), "labels"),
        (lambda d: simulate_intensity_series(d, em_gain=[1, 2]), "em_gain"),
        (lambda d: simulate_intensity_series(d, setpoint=0), "setpoint"),
    ],
)
def test_series_bad_options(tmp_path, call, name):
    with pytest.raises(ValueError, match=name):
        call(tmp_path / "out")
    assert not (tmp_path / "out").exists()  # checked before anything is written


# --------------------------------------------------------------------------------------
# Command line and demo
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "gain-series", "-o", "OUT", "--frames", "-5"],
        ["simulate", "gain-series", "-o", "OUT", "--multiplication", "poisson"],
        ["simulate", "gain-series", "-o", "OUT", "--em-gain", "1,2"],
        ["simulate", "gain-series", "-o", "OUT", "--setpoints", "1,abc"],
        ["simulate", "gain-series", "-o", "OUT", "--drift", "3"],
        ["simulate", "gain-series", "-o", "OUT", "--adc-bits", "17"],
        ["simulate", "gain-series", "-o", "OUT", "--read-noise", "nan"],
        ["simulate", "intensity-series", "OUT", "--labels", "a,b"],
        ["simulate", "intensity-series", "OUT", "--setpoint", "0.5"],
        ["simulate", "gain-series"],
        ["simulate"],
        ["demo", "--frames", "x"],
    ],
)
def test_cli_bad_options(tmp_path, capsys, argv):
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse errors exit from inside parse_args
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "error" in err[-1]
    assert len([line for line in err if "error" in line]) == 1
    assert not (tmp_path / "out").exists()


def test_cli_gain_series(tmp_path, capsys):
    out = tmp_path / "gs"
    argv = [
        "simulate",
        "gain-series",
        "-o",
        str(out),
        "--rows",
        "3",
        "--cols",
        "4",
        "--frames",
        "20",
    ]
    argv += [
        "--setpoints",
        "1,5,25",
        "--em-gain",
        "1,4.5,20",
        "--multiplication",
        "cascade",
        "--seed",
        "7",
        "--quiet",
    ]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert str(out / "manifest.toml") in captured.out and captured.err == ""
    truth = json.loads((out / "truth.json").read_text())
    assert [a["em_gain"] for a in truth["acquisitions"]] == [1.0, 4.5, 20.0]
    assert truth["multiplication"] == "cascade" and truth["stages"] == 536
    assert tifffile.imread(out / "gain-GS/25x-gain.tif").shape == (20, 3, 4)


def test_a_progress_bar_on_a_terminal_none_in_a_pipe_nor_with_quiet(tmp_path):
    """The installed command shows its bar where stderr is a terminal (a pseudo-terminal
    here), and none where stderr is a pipe or a log file, nor with ``-q``."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    from conftest import console_script

    def run(out, *, terminal, quiet=False):
        argv = [console_script(), "simulate", "intensity-series", "-o", str(tmp_path / out)]
        argv += ["--rows", "2", "--cols", "2", "--frames", "3000", "--levels", "100,200"]
        argv += ["--setpoint", "25", "--seed", "1"] + (["-q"] if quiet else [])
        if not terminal:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, done.stderr
            return done.stderr
        parent, child = pty.openpty()
        # a terminal 80 columns wide (a new one has none, and tqdm draws into its width)
        fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=child)
        os.close(child)
        seen = b""
        while True:
            try:
                chunk = os.read(parent, 4096)
            except OSError:  # the child closed the terminal
                break
            if not chunk:
                break
            seen += chunk
        os.close(parent)
        assert proc.wait(timeout=300) == 0
        return seen.decode(errors="replace")

    assert "simulate intensity-series" in run("tty", terminal=True)  # tqdm's bar
    assert "simulate intensity-series" not in run("pipe", terminal=False)
    assert "simulate intensity-series" not in run("quiet", terminal=True, quiet=True)
    assert len(_manifest(tmp_path / "pipe" / "manifest.toml")["acquisition"]) == 2


def test_console_entry_point(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "simulate",
            "gain-series",
            "-o",
            str(tmp_path),
            "--frames",
            "0",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "frames" in proc.stderr


@pytest.mark.slow
def test_demo_calibrates_and_recovers_truth(tmp_path):
    text = io.StringIO()
    res = run_demo(tmp_path, rows=4, cols=4, frames=3000, out=text)
    out = text.getvalue()
    assert "is-adu" in out and "em_gain at 300x" in out
    adu, gs = res["adu"], res["gs"]
    assert bool(adu.converged.all()) and bool(gs.converged.all())
    # truth of the demo: φ = 3.859, E = 370, gains 4.78 / 22.95 / 90.06 / 261.6
    phi = adu.e_per_adu.values
    assert abs(np.median(phi) - 3.859) < np.median(adu.e_per_adu_se.values)
    truth = {5: 4.78, 25: 22.95, 100: 90.06, 300: 261.6}
    for sp, g in truth.items():
        est = gs.em_gain.sel(setpoint=sp).values
        se = gs.em_gain_se.sel(setpoint=sp).values  # φ's error included (chained)
        assert abs(np.mean(est) - g) < 2 * np.mean(se)  # 8 SE of the 16-pixel mean
    # step 2 took φ with its standard error from step 1's result, and says so
    np.testing.assert_allclose(gs.e_per_adu_se.values, adu.e_per_adu_se.values)
    assert gs.attrs["e_per_adu_source"] == f"result {tmp_path / 'result-is-adu'}"
    assert "not propagated" not in out and "include that of e_per_adu from step 1" in out
    assert (tmp_path / "result-gs" / "calibration.nc").exists()


@pytest.mark.slow
def test_demo_cli(tmp_path, capsys):
    assert (
        cli.main(
            [
                "demo",
                "-o",
                str(tmp_path / "d"),
                "--rows",
                "2",
                "--cols",
                "2",
                "--frames",
                "500",
                "--quiet",
                "--no-report",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "em_gain at 300x" in out and "e_per_adu" in out
    assert (tmp_path / "d" / "gain-series" / "manifest.toml").exists()
    assert cli.main(["demo", "-o", str(tmp_path / "e"), "--frames", "0"]) == 2


def test_docstring_examples():
    from emccdcal.simulate import beads, camera

    attempted = 0
    for module in (camera, beads):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert result.failed == 0
        attempted += result.attempted
    assert attempted > 5


# --------------------------------------------------------------------------------------
# Beads
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bead_movies(tmp_path_factory):
    out = tmp_path_factory.mktemp("beads")
    return simulate_beads(
        out,
        beads=3,
        photoelectrons=[4000, 5000, 6000],
        rows=40,
        cols=36,
        frames=150,
        dark_frames=200,
        setpoints=[1, 25],
        seed=9,
    )


def test_bead_scene_is_the_psf_model():
    from emccdcal.model import psf

    E = bead_scene([[10.2, 12.7], [25.0, 20.4]], [5000.0, 3000.0], 1.3, 10.0, 36, 30)
    assert E.shape == (36, 30)
    assert E.sum() == pytest.approx(8000.0 + 10.0 * 36 * 30, rel=1e-9)
    one = psf.spot_image([12.7, 10.2, 1.3, 5000.0, 0.0], np.arange(36), np.arange(30))
    np.testing.assert_allclose(E[:18], (one + 10.0)[:18], rtol=1e-6)


def test_bead_files_truth_and_true_calibration(bead_movies):
    from emccdcal import result
    from emccdcal.data.manifest import read_manifest

    res = bead_movies
    t = res.truth
    assert t["kind"] == "beads" and t["seed"] == 9 and t["width"] == 1.3
    assert t["background"] == 10.0 and t["calibration"] == "truth_calibration.nc"
    assert [b["photoelectrons"] for b in t["beads"]] == [4000.0, 5000.0, 6000.0]
    pos = np.array([[b["row"], b["col"]] for b in t["beads"]])
    # placement: inside the margins and apart
    assert np.all(pos >= 6) and np.all(pos[:, 0] <= 40 - 7) and np.all(pos[:, 1] <= 36 - 7)
    d = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    assert d[np.triu_indices(3, 1)].min() >= 12
    assert [a["em_gain"] for a in t["acquisitions"]] == [1.0, 22.95]
    m = read_manifest(res.manifest)
    assert m.shape == (40, 36) and m.setpoints == (1.0, 25.0) and m.e_per_adu == 3.859
    cal = result.load(res.outdir / "truth_calibration.nc")
    assert cal.attrs["method"] == "truth"
    assert cal.attrs["manifest_sha256"] == m.content_hash
    np.testing.assert_array_equal(cal["em_gain"].sel(setpoint=25).values, 22.95)
    np.testing.assert_array_equal(cal["e_per_adu"].values, 3.859)
    scene = bead_scene(pos, [4000, 5000, 6000], 1.3, 10.0, 40, 36)
    np.testing.assert_allclose(cal["photoelectrons"].values, scene)
    pattern = tifffile.imread(res.outdir / "truth-offset-pattern.tif")
    np.testing.assert_allclose(cal["offset"].sel(setpoint=1).values, 587.7 + pattern)
    # the 25× stack: offset-subtracted mean, in photoelectrons, is the scene
    stack = tifffile.imread(res.outdir / "beads/25x-beads.tif").astype(float)
    assert stack.shape == (150, 40, 36)
    off = cal["offset"].sel(setpoint=25).values
    e = (stack.mean(axis=0) - off) * 3.859 / 22.95
    sd = np.sqrt(2 * scene / 150 + (15.5 * 3.859 / 22.95) ** 2 / 150)
    z = (e - scene) / sd
    assert abs(z.mean()) < 4 / np.sqrt(z.size) and 0.8 < z.std() < 1.2
    assert not [p for p in res.outdir.rglob(".*")]


def test_beads_reproducible_and_options(tmp_path):
    kw = dict(
        beads=2,
        rows=30,
        cols=30,
        frames=5,
        dark_frames=4,
        setpoints=[1, 5],
        multiplication="cascade",
    )
    a = simulate_beads(tmp_path / "a", seed=3, **kw)
    b = simulate_beads(tmp_path / "b", seed=3, **kw)
    for rel in ("beads/5x-beads.tif", "beads/1x-beads_no-signal.tif", "truth.json"):
        assert (a.outdir / rel).read_bytes() == (b.outdir / rel).read_bytes()
    assert a.truth["multiplication"] == "cascade" and a.truth["stages"] == 536
    with pytest.raises(ValueError, match="cannot place 30 beads"):
        simulate_beads(tmp_path / "c", beads=30, rows=30, cols=30, frames=2)
    with pytest.raises(ValueError, match="photoelectrons has 2 values but there are 3 beads"):
        simulate_beads(tmp_path / "c", beads=3, photoelectrons=[1, 2], frames=2)
    with pytest.raises(ValueError, match="outside the 30×30 sensor"):
        simulate_beads(tmp_path / "c", positions=[[5, 31]], rows=30, cols=30, frames=2)
    with pytest.raises(ValueError, match="width must be > 0"):
        simulate_beads(tmp_path / "c", width=0, frames=2)
    assert not (tmp_path / "c").exists()


def test_cli_beads(tmp_path, capsys):
    out = tmp_path / "b"
    argv = [
        "simulate",
        "beads",
        "-o",
        str(out),
        "--beads",
        "2",
        "--rows",
        "30",
        "--cols",
        "30",
        "--frames",
        "4",
        "--dark-frames",
        "3",
        "--setpoints",
        "1,100",
        "--width",
        "1.5",
        "--background",
        "5",
        "--photoelectrons",
        "3000",
        "--seed",
        "2",
        "--quiet",
    ]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "truth_calibration.nc" in captured.out and captured.err == ""
    truth = json.loads((out / "truth.json").read_text())
    assert truth["width"] == 1.5 and truth["background"] == 5.0 and len(truth["beads"]) == 2
    assert tifffile.imread(out / "beads/100x-beads.tif").shape == (4, 30, 30)
    assert tifffile.imread(out / "beads/100x-beads_no-signal.tif").shape == (3, 30, 30)
    assert cli.main(["simulate", "beads", "-o", str(tmp_path / "x"), "--beads", "-1"]) == 2


def test_cli_beads_that_blink_have_a_halo_and_a_repeated_setpoint(tmp_path):
    out = tmp_path / "b"
    argv = [
        "simulate",
        "beads",
        "-o",
        str(out),
        "--beads",
        "2",
        "--rows",
        "30",
        "--cols",
        "30",
        "--frames",
        "200",
        "--dark-frames",
        "3",
        "--setpoints",
        "1,100",
        "--seed",
        "2",
        "--blinking",
        "0.3",
        "--blink-frames",
        "4",
        "--halo",
        "0.2",
        "--repeat",
        "1",
        "--quiet",
    ]
    assert cli.main(argv) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["halo"] == 0.2 and truth["halo_width"] == pytest.approx(3 * 1.3)
    assert [a["name"] for a in truth["acquisitions"]] == ["1x", "100x", "1x-repeat"]
    assert "1x-repeat" in (out / "manifest.toml").read_text()
    # each bead off about 30 % of the 600 frames of the series, in runs
    off = [b["frames_off"] for b in truth["beads"]]
    assert all(100 < k < 260 for k in off)
    # an off bead's pixels receive the background only: its brightest pixel's counts at
    # 100x fall into two groups
    stack = tifffile.imread(out / "beads/100x-beads.tif").astype(float)
    r, c = (round(v) for v in (truth["beads"][0]["row"], truth["beads"][0]["col"]))
    peak = stack[:, r, c] - np.median(stack[:, 0, 0])
    assert 0.1 < np.mean(peak < 0.3 * np.median(peak[peak > np.median(peak)])) < 0.6
    with pytest.raises(ValueError, match="repeat = 5 is not one of the set-points"):
        simulate_beads(tmp_path / "c", setpoints=[1, 100], repeat=5, frames=2)


def test_one_camera_object_serves_every_simulator(tmp_path):
    from emccdcal.errors import OptionError
    from emccdcal.simulate.camera import Camera

    cam = Camera(rows=3, cols=4, frames=20, e_per_adu=5.2, read_noise=15.4)
    a = simulate_gain_series(tmp_path / "a", camera=cam, setpoints=(1, 5), seed=1)
    b = simulate_gain_series(
        tmp_path / "b",
        setpoints=(1, 5),
        seed=1,
        rows=3,
        cols=4,
        frames=20,
        e_per_adu=5.2,
        read_noise=15.4,
    )
    assert a.truth["options"] == b.truth["options"]
    assert (a.outdir / "gain-GS/5x-gain.tif").read_bytes() == (
        b.outdir / "gain-GS/5x-gain.tif"
    ).read_bytes()
    c = simulate_intensity_series(tmp_path / "c", camera=cam, cic=0.5, levels=(100,), seed=2)
    assert c.truth["cic"] == 0.5 and c.truth["e_per_adu"] == 5.2  # one field replaced
    with pytest.raises(OptionError, match="did you mean 'rows'"):
        simulate_gain_series(tmp_path / "d", rowz=3)
    with pytest.raises(OptionError, match="read_noise must be > 0"):
        Camera(read_noise=0)


def test_a_tight_sensor_still_takes_the_beads_that_fit():
    """4 beads 12 px apart and 6 px from the edges fit a 32 × 32 sensor (at its corners'
    grid), whatever the random draws; 5 do not, and that is said."""
    import itertools

    from emccdcal.errors import OptionError
    from emccdcal.simulate.beads import _place_beads

    for seed in range(20):
        at = _place_beads(4, 32, 32, 6.0, 12.0, np.random.default_rng(seed))
        assert at.shape == (4, 2) and at.min() >= 6 and at.max() <= 25
        assert min(np.hypot(*(a - b)) for a, b in itertools.combinations(at, 2)) >= 12
    with pytest.raises(OptionError, match="cannot place 5 beads at least 12 px apart"):
        _place_beads(5, 32, 32, 6.0, 12.0, np.random.default_rng(0))
