"""Tests of emccdcal.quality: stationarity, saturation, pixel defects, reports and the CLI."""

from __future__ import annotations

import argparse
import json
import re
import warnings

import numpy as np
import pytest
import tifffile
from conftest import write_real_manifest

from emccdcal import cli, errors
from emccdcal.cli.check import add_parser
from emccdcal.data.manifest import read_manifest
from emccdcal.data.quality import (
    DEFAULT_DRIFT_THRESHOLD,
    MIN_FRAMES,
    check_manifest,
    drift_test,
    format_report,
    linear_drift,
    pixel_defects,
    saturation,
    stationarity,
)
from emccdcal.simulate.series import simulate_gain_series

N = 5000


def read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", errors.ReadNoiseGrowthWarning)
        return read_manifest(path)


# --------------------------------------------------------------------------------------
# docs/validation.md case 12 (statsmodels 0.15.0; numpy.random.default_rng(0), n = 5000)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def case12():
    rng = np.random.default_rng(0)
    t = np.arange(N) / (N - 1)
    trend = 100.0 * (1.0 + 0.01 * t)  # 1 % linear drift over the series
    white = 100.0 + rng.normal(0.0, 1.0, N)  # drawn first
    walk = np.cumsum(rng.normal(0.0, 1.0, N))
    drift1 = trend + rng.normal(0.0, 1.0, N)
    drift10 = trend + rng.normal(0.0, 10.0, N)
    return {
        "white": stationarity(white),
        "walk": stationarity(walk),
        "drift1": stationarity(drift1),
        "drift10": stationarity(drift10),
    }


def test_case12_white_noise(case12):
    r = case12["white"]
    assert r["adf_pvalue"] < 1e-10
    assert r["kpss_pvalue"] == pytest.approx(0.071, abs=0.0005)
    assert r["kpss_p_bound"] is None
    assert abs(r["drift_pct"]) < 3 * r["drift_pct_se"]
    assert r["stationary"] is True


def test_case12_random_walk(case12):
    r = case12["walk"]
    assert r["adf_pvalue"] == pytest.approx(0.87, abs=0.005)
    assert r["kpss_pvalue"] == 0.01 and r["kpss_p_bound"] == "lower"
    assert not r["adf_rejects_unit_root"] and r["kpss_rejects_stationarity"]
    assert r["stationary"] is False


def test_case12_linear_drift_sd1(case12):
    r = case12["drift1"]
    # ADF('c') rejects the unit root although the series drifts: KPSS catches it
    assert r["adf_pvalue"] == pytest.approx(7e-7, rel=0.1)
    assert r["adf_rejects_unit_root"]
    assert r["kpss_pvalue"] == 0.01 and r["kpss_p_bound"] == "lower"
    # +1 ADU over a mean level of 100.5 ADU: 0.995 %; SE = sd·√(12/n)/level = 0.049 %
    assert r["drift_pct"] == pytest.approx(100 / 100.5, abs=3 * r["drift_pct_se"])
    assert r["drift_pct_se"] == pytest.approx(0.049, abs=0.001)
    assert r["stationary"] is False


def test_case12_linear_drift_sd10(case12):
    r = case12["drift10"]
    assert r["adf_pvalue"] < 1e-10
    assert r["kpss_pvalue"] == pytest.approx(0.029, abs=0.0005)
    assert r["kpss_p_bound"] is None
    assert r["drift_pct"] == pytest.approx(100 / 100.5, abs=3 * r["drift_pct_se"])
    assert r["stationary"] is False


def test_kpss_upper_clip_reported():
    # an anti-persistent (alternating) series: KPSS statistic tiny, p clipped at 0.1
    rng = np.random.default_rng(3)
    x = 50 + (-1.0) ** np.arange(500) + rng.normal(0, 0.1, 500)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the interpolation warning must not escape
        r = stationarity(x)
    assert r["kpss_pvalue"] == 0.1 and r["kpss_p_bound"] == "upper"
    assert r["stationary"] is True


def test_drift_threshold_decides_verdict():
    # a clean 3 % drift with little noise: KPSS rejects anyway, and the drift is flagged
    rng = np.random.default_rng(1)
    x = 200.0 * (1 + 0.03 * np.linspace(-0.5, 0.5, 1000)) + rng.normal(0, 0.5, 1000)
    r = stationarity(x)
    assert r["drift_pct"] == pytest.approx(3.0, abs=0.02)
    assert r["drift_exceeds"] and not r["stationary"]
    assert not stationarity(x, drift_threshold=5.0)["drift_exceeds"]


def test_drift_t_test_is_statsmodels_ols():
    import statsmodels.api as sm

    rng = np.random.default_rng(5)
    x = 50 + 0.0002 * np.arange(3000) + rng.normal(0, 2, 3000)
    d = linear_drift(x)
    fit = sm.OLS(x, sm.add_constant(np.arange(3000.0))).fit()
    assert d["slope"] == pytest.approx(fit.params[1], rel=1e-10)
    assert d["slope_se"] == pytest.approx(fit.bse[1], rel=1e-10)
    assert d["pvalue"] == pytest.approx(fit.pvalues[1], rel=1e-8)


def test_drift_test_needs_significance_and_size():
    rng = np.random.default_rng(2)
    t = np.linspace(-0.5, 0.5, N)
    noise = rng.normal(0, 20, N)
    noise -= t * (t @ noise) / (t @ t)  # its own trend removed: the estimate is exact
    noisy = 100 * (1 + 0.005 * t) + noise  # 0.5 %, with a standard error of ~1 %
    r = drift_test(noisy)
    assert r["drift_pct"] == pytest.approx(0.5, rel=1e-3)  # of a level of 100 ± 0.3
    assert r["drift_pct_se"] == pytest.approx(20 * np.sqrt(12 / N), rel=0.05)
    assert r["pvalue"] > 0.5 and not r["drifts"]
    tiny = 100 * (1 + 0.0005 * t) + rng.normal(0, 0.01, N)  # 0.05 %: certain but small
    r = drift_test(tiny)
    assert r["pvalue"] < 1e-10 and abs(r["drift_pct"]) < DEFAULT_DRIFT_THRESHOLD
    assert not r["drifts"] and drift_test(tiny, threshold=0.01)["drifts"]
    clear = 100 * (1 - 0.005 * t) + rng.normal(0, 1, N)
    r = drift_test(clear)
    assert r["drifts"] and r["drift_pct"] == pytest.approx(-0.5, abs=4 * r["drift_pct_se"])
    with pytest.raises(ValueError, match="too few frames for the drift test"):
        drift_test(clear[: MIN_FRAMES - 1])
    with pytest.raises(ValueError, match="alpha"):
        drift_test(clear, alpha=0)


def test_linear_drift_exact_and_offset():
    x = 600.0 + np.linspace(0.0, 2.0, 101)  # +2 ADU over the series
    d = linear_drift(x)
    assert d["slope"] == pytest.approx(0.02, rel=1e-12)
    assert d["drift_pct"] == pytest.approx(100 * 2 / 601, rel=1e-12)
    # with the offset of 591 ADU subtracted the level is 10 ADU: 20 %
    d = linear_drift(x, offset=591.0)
    assert d["level"] == pytest.approx(10.0)
    assert d["drift_pct"] == pytest.approx(20.0, rel=1e-12)
    # no positive level (a dark): drift in % is undefined, not a division by ~0
    d = linear_drift(x, offset=700.0)
    assert d["drift_pct"] is None and d["drift_pct_se"] is None


@pytest.mark.parametrize(
    "series, msg",
    [
        (np.arange(MIN_FRAMES - 1, dtype=float), "too few frames for the stationarity tests"),
        (np.r_[np.arange(60.0), np.nan], "NaN"),
        (np.full(100, 7.0), "constant"),
    ],
)
def test_stationarity_bad_input(series, msg):
    with pytest.raises(ValueError, match=msg):
        stationarity(series)


def test_stationarity_bad_options():
    x = np.random.default_rng(0).normal(size=100)
    with pytest.raises(ValueError, match="regression"):
        stationarity(x, regression="n")
    with pytest.raises(ValueError, match="alpha"):
        stationarity(x, alpha=1.5)


# --------------------------------------------------------------------------------------
# Saturation and pixel defects on arrays
# --------------------------------------------------------------------------------------
def test_saturation_counts():
    s = np.zeros((6, 2, 3), dtype=np.uint16)
    s[1, 0, 0] = 100
    s[1, 1, 2] = 101  # above adc_max still counts
    s[4, 0, 0] = 100
    r = saturation(s, adc_max=100)
    assert r["n_values"] == 3 and r["n_frames"] == 2 and r["n_pixels"] == 2
    assert r["pixels"] == [[0, 0], [1, 2]]
    assert r["fraction"] == pytest.approx(3 / 36)
    assert saturation(s, adc_max=102)["n_values"] == 0


def _stack(seed=0, shape=(8, 8), frames=400):
    rng = np.random.default_rng(seed)
    offset = 580 + rng.normal(0, 3, shape)  # fixed offset pattern: not a defect
    signal = 100 * (1 + rng.normal(0, 0.01, shape))  # 1 % response non-uniformity
    stack = np.rint(offset + signal + rng.normal(0, 15.5, (frames, *shape)))
    return stack.astype(np.uint16), offset


def test_clean_stack_has_no_defects():
    stack, offset = _stack()
    r = pixel_defects(stack, offset)
    assert r["tested"]
    assert r["n_hot"] == r["n_dead"] == r["n_stuck"] == 0
    assert r["median_mean"] == pytest.approx(100, abs=2)


def test_injected_hot_dead_stuck_pixels_found():
    stack, offset = _stack()
    stack[:, 2, 3] += 60  # hot: +60 ADU
    stack[:, 5, 5] -= 60  # dead: -60 ADU
    stack[:, 0, 7] = 680  # stuck at a normal level: neither hot nor dead
    r = pixel_defects(stack, offset)
    assert (r["n_hot"], r["hot"]) == (1, [[2, 3]])
    assert (r["n_dead"], r["dead"]) == (1, [[5, 5]])
    assert (r["n_stuck"], r["stuck"]) == (1, [[0, 7]])
    # without the offset map the offset pattern alone (SD 3 ADU) hides nothing this large
    assert pixel_defects(stack)["hot"] == [[2, 3]]
    # a higher threshold lets the hot pixel through
    assert pixel_defects(stack, offset, k=1e6)["n_hot"] == 0


def test_too_few_pixels_only_stuck_checked():
    stack = np.random.default_rng(0).integers(500, 600, (100, 1, 2)).astype(np.uint16)
    stack[:, 0, 1] = 550
    r = pixel_defects(stack)
    assert not r["tested"] and r["robust_sd"] is None
    assert r["stuck"] == [[0, 1]]


# --------------------------------------------------------------------------------------
# Acquisitions and manifests (simulated)
# --------------------------------------------------------------------------------------
def _sim(tmp_path, name, **kw):
    opts = dict(rows=4, cols=4, frames=2000, seed=11, setpoints=(1, 25))
    opts.update(kw)
    return simulate_gain_series(tmp_path / name, **opts).manifest


def test_drifting_series_flagged_and_steady_not(tmp_path):
    steady = check_manifest(read(_sim(tmp_path, "steady", drift=0.0)))
    drifting = check_manifest(read(_sim(tmp_path, "drift", drift=0.05)))
    assert set(steady["acquisitions"]) == {"1x", "25x"}
    assert steady["drift_alpha"] == 0.01
    for a in steady["acquisitions"].values():
        d = a["drift"]
        assert not d["drifts"], a["name"]
        assert d["alpha"] == pytest.approx(0.01 / 2)  # Bonferroni over the two acquisitions
        assert a["stationarity"] is None  # the unit-root tests only on request
    assert steady["warnings"] == []
    for a in drifting["acquisitions"].values():
        d = a["drift"]
        assert d["drifts"], a["name"]
        # the photoelectron rate drifts by 5 %: so does the offset-subtracted frame mean
        assert d["drift_pct"] == pytest.approx(5.0, abs=4 * d["drift_pct_se"])
    joined = "\n".join(drifting["warnings"])
    assert "1x (set-point 1): the frame mean drifts by +" in joined
    assert "25x (set-point 25): the frame mean drifts by +" in joined
    # what the drift does to the estimate, at the acquisition's own level: the true E is
    # 370 e⁻, read roughly from the counts' moments (at 1× the excess variance is a tenth
    # of the read noise's): g +E·d²/24 ≈ +3.9 %, φ at 1× −E·d²/12 ≈ −7.7 %
    found = re.findall(
        r"(EM gain g|φ \(e⁻/ADU\)) is biased by about ([-+][\d.]+) % at this "
        r"acquisition's ([\d.]+) e⁻ per pixel and frame",
        joined,
    )
    assert sorted(w for w, _, _ in found) == ["EM gain g", "φ (e⁻/ADU)"]
    for what, bias, level in found:
        assert float(level) == pytest.approx(370, rel=0.3)
        d = drifting["acquisitions"]["25x" if what == "EM gain g" else "1x"]["drift"]
        expect = (
            100 * float(level) * (d["drift_pct"] / 100) ** 2 / (24 if what == "EM gain g" else -12)
        )
        assert float(bias) == pytest.approx(expect, rel=0.03)
    assert "1000 e⁻" not in joined and "d²" not in joined  # no one else's numbers
    with_tests = check_manifest(read(_sim(tmp_path, "drift", drift=0.05)), unit_root_tests=True)
    assert all(
        a["stationarity"]["kpss_rejects_stationarity"] for a in with_tests["acquisitions"].values()
    )
    assert with_tests["warnings"] == drifting["warnings"]  # reported, never findings
    assert "KPSS p" in format_report(with_tests) and "KPSS p" not in format_report(drifting)


def test_saturated_frames_counted(tmp_path):
    # 450 e⁻ at 300x: a mean of 31 000 ADU, a fifth of the values above 15 bits
    m = read(
        _sim(tmp_path, "sat", setpoints=(1, 300), adc_bits=15, frames=200, photoelectrons=450.0)
    )
    assert m.adc_max == 2**15 - 1
    rep = check_manifest(m)
    by_sp = {a.em_gain_setpoint: a for a in m.acquisitions}
    for sp, key in ((1.0, "1x"), (300.0, "300x")):
        stack = np.asarray(by_sp[sp].frames())
        sat = rep["acquisitions"][key]["saturation"]
        hit = stack >= m.adc_max
        assert sat["n_values"] == int(hit.sum())
        assert sat["n_frames"] == int(hit.any(axis=(1, 2)).sum())
        assert sat["n_pixels"] == int(hit.any(axis=0).sum())
    assert rep["acquisitions"]["1x"]["saturation"]["n_values"] == 0
    assert rep["acquisitions"]["300x"]["saturation"]["n_values"] > 0
    sat_warnings = [w for w in rep["warnings"] if "saturated pixel-frames" in w]
    assert len(sat_warnings) == 1 and sat_warnings[0].startswith("300x (set-point 300)")
    frac = rep["acquisitions"]["300x"]["saturation"]["fraction"]
    assert f"{frac:.2%} of its pixel-frames" in sat_warnings[0]
    assert "read low" in sat_warnings[0] and "lower the light" in sat_warnings[0]
    assert "Every other pixel's result stands" in sat_warnings[0]


def test_too_few_frames_skip_only_the_drift_test(tmp_path):
    m = read(_sim(tmp_path, "few", frames=40, adc_bits=12))
    rep = check_manifest(m)
    for a in rep["acquisitions"].values():
        assert a["drift"] is None and a["saturation"]["adc_max"] == 4095
        assert a["pixels"]["tested"]
    few = [w for w in rep["warnings"] if "too few for the drift test" in w]
    assert len(few) == 2 and few[0].startswith("1x (set-point 1): 40 frames")
    assert "n/a" in format_report(rep)


def test_read_noise_growth_reported(tmp_path):
    # clock-induced charge multiplied at 300x makes the darks' sigma grow
    m = read(_sim(tmp_path, "cic", setpoints=(1, 300), cic=0.05, frames=300))
    rep = check_manifest(m)
    assert len(rep["read_noise_growth"]) == 1
    assert rep["read_noise_growth"][0].startswith("read noise at EM gain set-point 300")
    assert rep["warnings"][-1] == rep["read_noise_growth"][0]


def test_report_json_and_table(tmp_path):
    rep = check_manifest(read(_sim(tmp_path, "j", drift=0.05)))
    back = json.loads(json.dumps(rep, allow_nan=False))
    assert back == rep
    text = format_report(rep)
    lines = text.splitlines()
    assert "drift % ± SE" in lines[2]
    rows = [ln for ln in lines if ln.startswith(("1x ", "25x "))]
    assert len(rows) == 2 and all(" NO " in ln for ln in rows)  # the verdict column
    assert f"{len(rep['warnings'])} finding(s):" in text
    for w in rep["warnings"]:
        assert f"- {w}" in lines


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------
def _parser():
    p = argparse.ArgumentParser(prog="emccdcal")
    add_parser(p.add_subparsers(dest="verb"))
    return p


def test_cli_human_and_json(tmp_path, capsys):
    manifest = _sim(tmp_path, "cli", drift=0.05)
    args = _parser().parse_args(["check", str(manifest)])
    assert args.func(args) == 0  # findings do not change the exit code
    out = capsys.readouterr().out
    assert out.startswith("Data-quality checks:") and "the frame mean drifts by" in out
    args = _parser().parse_args(["check", str(manifest), "--json"])
    assert args.func(args) == 0
    rep = json.loads(capsys.readouterr().out)
    assert set(rep["acquisitions"]) == {"1x", "25x"}
    assert rep["warnings"]
    args = _parser().parse_args(["check", str(manifest), "--json", "--drift-threshold", "50"])
    args.func(args)
    rep = json.loads(capsys.readouterr().out)
    assert not any(a["drift"]["drifts"] for a in rep["acquisitions"].values())
    # --strict: a finding exits 1, none exits 0
    assert cli.main(["check", str(manifest), "-q", "--strict"]) == 1
    assert cli.main(["check", str(manifest), "-q", "--strict", "--drift-threshold", "50"]) == 0


def test_cli_through_main(tmp_path, capsys, monkeypatch):
    manifest = _sim(tmp_path, "main")
    assert cli.main(["check", str(manifest), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == []
    bad = tmp_path / "bad.toml"
    bad.write_text('[[acquisition]]\nframes = "missing.tif"\nem_gain_setpoint = 1\n')
    assert cli.main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("emccdcal check: error:") and "bad.toml" in err
    assert err.count("\n") == 1


def test_cli_bad_manifest_raises_valueerror(tmp_path):
    args = _parser().parse_args(["check", str(tmp_path / "nope.toml")])
    with pytest.raises(ValueError, match="nope.toml"):
        args.func(args)


# --------------------------------------------------------------------------------------
# Real data (shared ProEM gain series)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def real_report(real_data, tmp_path_factory):
    path = write_real_manifest(tmp_path_factory.mktemp("real"), "gs")
    return check_manifest(read(path), unit_root_tests=True)


@pytest.mark.slow
def test_real_gain_series_findings(real_report):
    rep = real_report
    acqs = rep["acquisitions"]
    assert list(acqs) == [f"{g}x-gain" for g in (1, 5, 25, 100, 300)]
    st = {k: a["stationarity"] for k, a in acqs.items()}
    # ADF rejects a unit root everywhere
    assert all(s["adf_pvalue"] < 1e-4 for s in st.values())
    # KPSS: p <= 0.01 (clipped) at 1x, 5x, 300x; >= 0.1 (clipped) at 25x and 100x
    assert {k: s["kpss_p_bound"] for k, s in st.items()} == {
        "1x-gain": "lower",
        "5x-gain": "lower",
        "25x-gain": "upper",
        "100x-gain": "upper",
        "300x-gain": "lower",
    }
    # linear drift over each acquisition, % of the offset-subtracted level (regression guard)
    expected = {
        "1x-gain": 0.87,
        "5x-gain": 0.51,
        "25x-gain": -0.16,
        "100x-gain": 0.00,
        "300x-gain": -0.68,
    }
    for k, v in expected.items():
        assert st[k]["drift_pct"] == pytest.approx(v, abs=0.01), k
        assert acqs[k]["drift"]["drift_pct"] == pytest.approx(v, abs=0.01), k
    assert [k for k, s in st.items() if s["stationary"]] == ["25x-gain", "100x-gain"]
    # the drift rule (family-wise 1 %): the two drifts of 0.5 % or more that the frame
    # means resolve; 1x (0.87 ± 0.30 %, p = 0.004) misses the 0.2 % level
    flagged = [k for k, a in acqs.items() if a["drift"]["drifts"]]
    assert flagged == ["5x-gain", "300x-gain"]
    # no saturation, no hot, dead or stuck pixel in the 3x3 crop
    for a in acqs.values():
        assert a["saturation"]["n_values"] == 0
        assert a["pixels"]["tested"]
        assert a["pixels"]["n_hot"] == a["pixels"]["n_dead"] == a["pixels"]["n_stuck"] == 0
    # read noise grows at 100x (8 %) and 300x (44 %): clock-induced charge
    growth = rep["read_noise_growth"]
    assert len(growth) == 2
    assert growth[0].startswith("read noise at EM gain set-point 100 (median 16.6 ADU) is 8 %")
    assert growth[1].startswith("read noise at EM gain set-point 300 (median 22.1 ADU) is 44 %")
    assert len(rep["warnings"]) == 2 + 2


def test_summary_of_a_file_by_bands_is_the_summary_of_the_stack(tmp_path, monkeypatch):
    # check reads stacks band by band (bounded memory); the statistics are the same
    from emccdcal.data import quality
    from emccdcal.data.quality import StackSummary

    data = np.random.default_rng(1).integers(500, 4095, (60, 7, 5)).astype(np.uint16)
    data[10, 2, 1] = 4095  # one saturated value (after the skipped frames)
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, data)
    monkeypatch.setattr(quality.stacks, "_CHUNK_ELEMENTS", 55 * 5 * 2)  # bands of two rows
    a = StackSummary.of_file(path, 5, 4095, third=True)
    b = StackSummary.of(data[5:], 4095, third=True)
    for name in ("frame_sums", "frame_saturated", "mean", "sd", "n_saturated", "m3"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12, err_msg=name)
    assert a.saturation()["n_values"] == 1


def test_the_steady_column_gives_its_reason(real_report):
    """+0.87 % at 1x is steady and +0.51 % at 5x is not: each verdict says which side of
    the rule it is on (the family-wise p threshold, or the size threshold)."""
    text = format_report(real_report)
    assert "(each p must be below 0.002: a large drift with a large SE can be steady" in text
    rows = {line.split()[0]: line for line in text.splitlines() if "x-gain " in line}
    assert "+0.87 ± 0.30" in rows["1x-gain"] and "yes: p ≥ 0.002" in rows["1x-gain"]
    assert "+0.51 ± 0.13" in rows["5x-gain"] and " NO " in rows["5x-gain"]
    small = {**real_report["acquisitions"]["5x-gain"]["drift"], "drift_pct": 0.05, "drifts": False}
    from emccdcal.data.quality.series import _steady_cell

    assert _steady_cell(small) == "yes: < 0.1 %"  # significant, but below the size threshold


def test_every_finding_says_whether_the_result_stands_and_what_fixes_it():
    """A finding that makes a result doubtful says whether to trust it and how to fix it
    (a new user once read a drift warning that said neither)."""
    from emccdcal.data.quality.series import _findings

    a = {
        "name": "L6",
        "em_gain_setpoint": 1.0,
        "level": "L6",
        "frames": "a.tif",
        "skip_frames": 2,
        "n_frames": 500,
        "drift": {"drifts": True, "drift_pct": 0.26, "drift_pct_se": 0.01, "pvalue": 1e-9},
        "photoelectrons_estimate": 6.7e4,
        "photoelectrons_source": "fit",
        "estimate_relative_se": 0.011,
        "offset": {"above_data": True, "n_below_offset": 9, "n_pixels": 9},
        "multiplication": {"multiplied": True, "R": 1.5, "R_se": 0.02, "n_pixels": 9},
        "frames_defective": {
            "n_constant": 2,
            "constant": [0, 1],
            "n_repeated": 1,
            "repeated": [200],
        },
        "saturation": {
            "n_values": 5,
            "adc_max": 65535,
            "fraction": 0.01,
            "n_frames": 5,
            "n_pixels": 1,
            "pixels": [[0, 0]],
        },
        "pixels": {
            "n_hot": 1,
            "hot": [[1, 1]],
            "n_dead": 0,
            "dead": [],
            "k": 6.0,
            "robust_sd": 2.0,
            "n_stuck": 1,
            "stuck": [[2, 2]],
        },
    }
    found = _findings(a)
    assert len(found) == 8, found
    for text in found:
        assert "stand" in text, text  # "the result stands", "does not stand" ...
        assert any(
            fix in text for fix in ("calibrate again", "record again", "do not use", "no result")
        ), text
    drift, offset, multiplied, constant, repeated, saturated, hot, stuck = found
    assert "φ pools every level" in drift and "3.4 times its standard error" in drift
    assert "may not stand" in drift and 'level = "L6"' in drift
    assert "nothing fitted from it stands" in offset
    # leading dropped frames are skipped by the manifest, frames in the middle are not
    assert "set skip_frames = 4" in constant
    assert "skip_frames" not in repeated.split("they bias")[1]
    a["estimate_relative_se"] = 0.05  # the same drift within the SE: the result stands
    assert "the result stands" in _findings(a)[0]
    a["em_gain_setpoint"], a["level"] = 300.0, None  # a gain: its own estimate, no pooling
    a["estimate_relative_se"] = 0.001
    assert "the result does not stand as it is" in _findings(a)[0]
    a["drift_absorbed"] = False  # gs: g from the mean against the 1x light
    assert "a drift does not move: the result stands" in _findings(a)[0]
