"""Bead validation: the consistency metric, calibration groups, validate, bad input."""

from __future__ import annotations

import json
import math
import re
import warnings

import numpy as np
import pytest
import xarray as xr

from emccdcal import cli, result
from emccdcal.beads import validation
from emccdcal.simulate.beads import simulate_beads

PHI = 3.859
SHAPE = (32, 40)
SETPOINTS = [1.0, 25.0]
GAINS = [1.0, 22.95]
POSITIONS = [[9.3, 10.6], [21.7, 28.2], [10.4, 30.8]]
#: A short cascade register for the tests of bead effects (blinking, bleaching, halos,
#: repeats): they check the validation, not the register, and the register's cost grows
#: with its stages (the truth calibration records them, so the fits use the same).
SHORT = 64


def _result(
    path,
    *,
    method,
    setpoints,
    gains,
    phi=PHI,
    shape=SHAPE,
    origin=(0, 0),
    converged=True,
    stages=None,
):
    """A result of these numbers (with a cascade of ``stages``, else no register named)."""
    from emccdcal.model.noise import EMModel

    R, C = shape
    ds = result.make_dataset(
        method=method,
        setpoints=setpoints,
        e_per_adu=phi,
        e_per_adu_se=0.0,
        em_gain=np.broadcast_to(np.array(gains, float)[:, None, None], (len(setpoints), R, C)),
        em_gain_se=0.0,
        photoelectrons=np.zeros(shape),
        photoelectrons_se=0.0,
        converged=converged,
        manifest_hash="0" * 64,
        origin=origin,
        attrs=EMModel("cascade", stages).attrs if stages else None,
    )
    result.save(ds, path)
    return path / result.CALIBRATION_FILE


@pytest.fixture(scope="module")
def beads_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("beads")
    sim = simulate_beads(
        d / "sim",
        positions=POSITIONS,
        rows=SHAPE[0],
        cols=SHAPE[1],
        frames=80,
        dark_frames=300,
        setpoints=SETPOINTS,
        seed=42,
        stages=SHORT,
    )
    cal = {
        "truth": d / "sim" / "truth_calibration.nc",
        "wrong": _result(
            d / "wrong", method="gs", setpoints=SETPOINTS, gains=[1.0, 1.1 * GAINS[1]], stages=SHORT
        ),
        "adu": _result(d / "adu", method="is-adu", setpoints=[1.0], gains=[1.0]),
        "g25": _result(
            d / "g25", method="is-gain", setpoints=[25.0], gains=[GAINS[1]], stages=SHORT
        ),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = validation.validate(
            sim.manifest,
            [str(cal["truth"]), str(cal["wrong"]), f"{cal['adu']},{cal['g25']}"],
            out=d / "val",
        )
    return sim, cal, doc, d / "val"


# --------------------------------------------------------------------------------------
# The metric (docs/validation.md case 14)
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("scale", [1.0, 5000.0])
def test_metric_case_14(scale):
    means = {
        1: 1.00 * scale,
        5: 1.10 * scale,
        25: 0.99 * scale,
        100: 1.01 * scale,
        300: 1.00 * scale,
    }
    incl, excl = validation.consistency(means)
    assert incl == pytest.approx(0.040497, abs=5e-7)
    assert excl == pytest.approx(0.043875, abs=5e-7)
    incl1, excl1 = validation.consistency(means, ddof=1)
    assert incl1 == pytest.approx(0.045277, abs=5e-7)
    assert excl1 == pytest.approx(0.050662, abs=5e-7)
    # scaled to the 1× mean: a bead 10 % brighter at 1× changes the numbers
    shifted = {**means, 1: 1.10 * scale}
    assert validation.consistency(shifted)[1] == pytest.approx(0.043875 / 1.10, abs=5e-7)


def test_metric_edge_cases():
    with pytest.raises(ValueError, match="set-point 1 is needed"):
        validation.consistency({5: 1.0, 25: 1.0})
    incl, excl = validation.consistency({1: 100.0, 5: 110.0}, ddof=1)
    assert incl == pytest.approx(np.std([1.0, 1.1], ddof=1)) and math.isnan(excl)
    assert math.isnan(validation.consistency({1: 100.0, 5: np.nan})[0])


# --------------------------------------------------------------------------------------
# validate: the files
# --------------------------------------------------------------------------------------
def test_validation_json_schema_and_ranking(beads_data):
    sim, cal, doc, out = beads_data
    on_disk = json.loads((out / validation.VALIDATION_FILE).read_text())
    assert on_disk["calibrations"] == doc["calibrations"]
    assert doc["ddof"] == 0
    assert [c["file"] for c in doc["calibrations"]] == [
        str(cal["truth"]),
        str(cal["wrong"]),
        f"{cal['adu']},{cal['g25']}",
    ]
    assert [c["method"] for c in doc["calibrations"]] == ["truth", "gs", "is-adu+is-gain"]
    for c in doc["calibrations"]:
        assert {"file", "method", "beads", "sigma_means_incl_1x", "sigma_means_excl_1x"} <= set(c)
        assert len(c["beads"]) == 3
        for b in c["beads"]:
            assert {
                "row",
                "col",
                "mean_intensity",
                "mean_intensity_se",
                "sigma_means_incl_1x",
                "sigma_means_excl_1x",
            } <= set(b)
            assert list(b["mean_intensity"]) == ["1", "25"] == list(b["mean_intensity_se"])
            assert isinstance(b["row"], int) and isinstance(b["col"], int)
            # the offset maps (300 dark frames) add an error that frames do not average;
            # an ADU of offset is φ e- at 1x, φ/g at 25x (about 0.4 % of the bead at 1x)
            off = b["mean_intensity_se_offset"]
            assert 0 < off["25"] < off["1"] < b["mean_intensity_se"]["1"]
            # so does the error of the bead's shared position, width and background
            shared = b["mean_intensity_se_shared"]
            assert all(0 < shared[k] < b["mean_intensity_se"][k] for k in ("1", "25"))
            assert off["1"] / b["mean_intensity"]["1"] == pytest.approx(0.005, rel=0.5)
    # beads at the truth's positions
    found = sorted((b["row"], b["col"]) for b in doc["calibrations"][0]["beads"])
    assert found == sorted(tuple(round(v) for v in p) for p in POSITIONS)
    truth, wrong, group = doc["calibrations"]
    assert truth["converged_fraction"] == {"1": 1.0, "25": 1.0}
    # the wrong gain at 25× makes the 25× intensities 1/1.1 of the truth's
    for bt, bw in zip(truth["beads"], wrong["beads"]):
        # the same φ at 1×: the same intensities but for the shared width, which the
        # other set-points' gains move a little
        assert bw["mean_intensity"]["1"] == pytest.approx(bt["mean_intensity"]["1"], rel=1e-3)
        assert bw["mean_intensity"]["25"] / bt["mean_intensity"]["25"] == pytest.approx(
            1 / 1.1, rel=0.01
        )
        assert bt["mean_intensity"]["25"] == pytest.approx(5000.0, rel=0.02)
    assert doc["ranking"][-1] == str(cal["wrong"])
    assert wrong["sigma_means_incl_1x"] > 0.03 > truth["sigma_means_incl_1x"]
    # the group (φ from is-adu, 25× gain from is-gain) is the truth again
    assert group["beads"] == truth["beads"]
    # per-bead metric recomputed from the means (ddof 0 headline, ddof 1 beside it)
    b = wrong["beads"][0]
    m = {float(k): v for k, v in b["mean_intensity"].items()}
    assert b["sigma_means_incl_1x"] == pytest.approx(validation.consistency(m)[0])
    assert b["sigma_means_incl_1x_ddof1"] == pytest.approx(validation.consistency(m, ddof=1)[0])
    assert wrong["sigma_means_incl_1x"] == pytest.approx(
        np.mean([x["sigma_means_incl_1x"] for x in wrong["beads"]])
    )


def test_intensities_file(beads_data):
    _, cal, doc, out = beads_data
    with xr.open_dataset(out / validation.INTENSITIES_FILE, engine="h5netcdf") as ds:
        ds = ds.load()
    assert ds["intensity"].dims == ("calibration", "bead", "setpoint", "frame")
    assert ds.sizes == {"calibration": 3, "bead": 3, "setpoint": 2, "frame": 80}
    assert ds["intensity"].attrs["units"] == "e-" and ds["intensity_se"].attrs["units"] == "e-"
    assert ds["converged"].dtype == bool and ds["converged"].mean() > 0.95
    assert list(ds["calibration"].values) == [c["file"] for c in doc["calibrations"]]
    assert list(ds["method"].values) == ["truth", "gs", "is-adu+is-gain"]
    assert ds["setpoint"].values.tolist() == SETPOINTS
    rows = [b["row"] for b in doc["calibrations"][0]["beads"]]
    assert ds["bead_row"].values.tolist() == rows
    # validation.json's means are the means of these over converged frames
    I = ds["intensity"].where(ds["converged"])
    mean = I.isel(calibration=1, bead=0, setpoint=1).mean().item()
    assert mean == pytest.approx(doc["calibrations"][1]["beads"][0]["mean_intensity"]["25"])


# --------------------------------------------------------------------------------------
# Calibrations and bad input
# --------------------------------------------------------------------------------------
def test_load_calibration_groups(tmp_path):
    adu = _result(tmp_path / "adu", method="is-adu", setpoints=[1.0], gains=[1.0], phi=3.9)
    g5 = _result(tmp_path / "g5", method="is-gain", setpoints=[5.0], gains=[4.78])
    g25 = _result(tmp_path / "g25", method="is-gain", setpoints=[25.0], gains=[22.95])
    with pytest.warns(UserWarning, match="fitted with another e_per_adu"):
        c = result.load_calibration(f"{adu},{g5},{g25}", SHAPE)
    assert c.method == "is-adu+is-gain" and c.setpoints == (1.0, 5.0, 25.0)
    assert np.all(c.e_per_adu == 3.9) and np.all(c.gain(25) == 22.95) and np.all(c.gain(1) == 1)
    with pytest.raises(
        ValueError,
        match=r"set-point 100x is missing .*\(it has "
        r"1x, 5x, 25x\)",
    ):
        c.gain(100)
    other = _result(tmp_path / "g5b", method="is-gain", setpoints=[5.0], gains=[4.7])
    with pytest.raises(ValueError, match="set-point 5x is in both"):
        result.load_calibration([g5, other])
    adu2 = _result(tmp_path / "adu2", method="mv-adu", setpoints=[1.0], gains=[1.0])
    with pytest.raises(ValueError, match="both measured e_per_adu"):
        result.load_calibration([adu, adu2])
    # non-converged pixels are missing values
    mask = np.ones(SHAPE, bool)
    mask[3, 4] = False
    part = _result(
        tmp_path / "part", method="gs", setpoints=[1.0, 5.0], gains=[1.0, 4.78], converged=mask
    )
    c = result.load_calibration(part)
    assert np.isnan(c.gain(5)[3, 4]) and np.isnan(c.e_per_adu[3, 4])


def test_calibration_of_another_sensor_or_region(tmp_path):
    small = _result(
        tmp_path / "small", method="gs", setpoints=[1.0, 25.0], gains=GAINS, shape=(16, 16)
    )
    with pytest.raises(
        ValueError,
        match=r"small/calibration.nc: calibration covers rows 0–15 "
        r"and columns 0–15, but the bead frames are 32×40",
    ):
        result.load_calibration(small, SHAPE, of="the bead frames")
    moved = _result(
        tmp_path / "moved", method="gs", setpoints=[1.0, 25.0], gains=GAINS, origin=(4, 0)
    )
    with pytest.raises(ValueError, match="rows 4–35"):
        result.load_calibration(moved, SHAPE)
    with pytest.raises(FileNotFoundError, match="nope.nc"):
        result.load_calibration(tmp_path / "nope.nc")
    junk = tmp_path / "junk.nc"
    junk.write_text("not netcdf")
    with pytest.raises(ValueError, match="junk.nc: not an emccdcal result file"):
        result.load_calibration(junk)


def _cli(capsys, *argv):
    code = cli.main(["validate", *map(str, argv)])
    return code, capsys.readouterr()


def test_cli_bad_input_is_one_line(beads_data, tmp_path, capsys):
    sim, cal, _, _ = beads_data
    missing = _result(tmp_path / "no25", method="gs", setpoints=[1.0, 5.0], gains=[1.0, 4.78])
    cases = [
        ((missing,), "set-point 25x is missing from this calibration"),
        ((tmp_path / "absent.nc",), "absent.nc: no such file"),
        (
            (
                _result(
                    tmp_path / "small", method="gs", setpoints=SETPOINTS, gains=GAINS, shape=(8, 8)
                ),
            ),
            "but the bead frames are 32×40",
        ),
    ]
    for cals, message in cases:
        code, io_ = _cli(
            capsys, sim.manifest, "--calibration", *cals, "-o", tmp_path / "o", "--quiet"
        )
        assert code == 2
        lines = io_.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("emccdcal validate: error: ")
        assert message in lines[0]
    assert not (tmp_path / "o" / validation.VALIDATION_FILE).exists()


def test_no_beads_and_beads_at_the_edge(tmp_path, capsys):
    empty = simulate_beads(
        tmp_path / "empty",
        beads=0,
        rows=24,
        cols=24,
        frames=20,
        dark_frames=50,
        setpoints=SETPOINTS,
        seed=1,
    )
    truth = tmp_path / "empty" / "truth_calibration.nc"
    code, io_ = _cli(capsys, empty.manifest, "-c", truth, "-o", tmp_path / "o", "-q")
    assert code == 2 and "no beads found" in io_.err and "25x-beads.tif" in io_.err
    # one bead at the edge (skipped with a warning), one inside
    edge = simulate_beads(
        tmp_path / "edge",
        positions=[[2.2, 12.0], [12.4, 11.7]],
        rows=24,
        cols=24,
        frames=20,
        dark_frames=50,
        setpoints=SETPOINTS,
        seed=2,
    )
    truth = tmp_path / "edge" / "truth_calibration.nc"
    with pytest.warns(
        UserWarning,
        match=r"skipped 1 bead\(s\) closer than 4 px to the frame's "
        r"edge at \(row, col\) \(2, 12\)",
    ):
        doc = validation.validate(edge.manifest, [truth])
    assert [(b["row"], b["col"]) for b in doc["calibrations"][0]["beads"]] == [(12, 12)]
    # only a bead at the edge: nothing left to fit
    only = simulate_beads(
        tmp_path / "only",
        positions=[[12.0, 1.6]],
        rows=24,
        cols=24,
        frames=20,
        dark_frames=50,
        setpoints=SETPOINTS,
        seed=3,
    )
    code, io_ = _cli(
        capsys,
        only.manifest,
        "-c",
        tmp_path / "only" / "truth_calibration.nc",
        "-o",
        tmp_path / "o",
        "-q",
    )
    assert code == 2 and "all 1 bead(s) found are at the edge" in io_.err


def test_bead_with_missing_calibration_pixels_is_left_out(beads_data, tmp_path):
    sim, _, _, _ = beads_data
    mask = np.ones(SHAPE, bool)
    mask[22, 28] = False  # inside the box of the bead at (22, 28)
    part = _result(tmp_path / "part", method="gs", setpoints=SETPOINTS, gains=GAINS, converged=mask)
    with pytest.warns(UserWarning, match=r"in the box of 1 bead\(s\) at \(row, col\) \(22, 28\)"):
        doc = validation.validate(sim.manifest, [part])
    c = doc["calibrations"][0]
    left_out = next(b for b in c["beads"] if (b["row"], b["col"]) == (22, 28))
    assert left_out["mean_intensity"]["1"] is None and left_out["sigma_means_incl_1x"] is None
    assert c["beads_used"] == 2 and c["sigma_means_incl_1x"] is not None


@pytest.mark.slow
def test_cli_writes_files_and_figures(beads_data, tmp_path, capsys):
    sim, cal, _, _ = beads_data
    out = tmp_path / "v"
    code, io_ = _cli(capsys, sim.manifest, "--calibration", cal["truth"], cal["wrong"], "-o", out)
    assert code == 0
    assert "rank" in io_.out and "truth" in io_.out  # (no bar: stderr is not a terminal)
    assert (out / "validation.json").is_file() and (out / "intensities.nc").is_file()
    assert (out / "bead_consistency.png").is_file()
    assert sorted(p.name for p in out.glob("bead_intensities_*.png")) == [
        f"bead_intensities_{i}.png" for i in range(3)
    ]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files


def test_docstring_examples():
    import doctest

    attempted = 0
    for part in (validation.metric, validation.run, validation.document):
        res = doctest.testmod(part)
        assert res.failed == 0, part.__name__
        attempted += res.attempted
    assert attempted >= 1


# --------------------------------------------------------------------------------------
# Bleaching: a fade within the series looks like a gain error unless it is undone
# --------------------------------------------------------------------------------------
def test_intensity_trend_finds_a_fade_and_nothing_else():
    rng = np.random.default_rng(3)
    B, S, F, m = 8, 3, 300, 5000.0
    times = np.arange(S)[:, None] * F + np.arange(F)[None, :]
    se = np.full((B, S, F), 0.02 * m)
    for fade, detected in ((0.02, True), (0.0, False)):
        k = -math.log1p(-fade) / (S * F - 1)
        levels = m * np.array([1.0, 0.9, 1.05])[None, :, None]  # set-point levels: not a trend
        N = levels * np.exp(-k * times) + se * rng.standard_normal((B, S, F))
        t = validation.intensity_trend(N, se, times)
        assert t["detected"] is detected
        assert abs(t["rate_per_frame"] - k) < 4 * t["rate_se"]
        assert t["fade_over_series"] == pytest.approx(fade, abs=0.004)


@pytest.mark.slow
def test_bleaching_is_detected_and_corrected_so_the_ranking_holds(tmp_path):
    sim = simulate_beads(
        tmp_path / "sim",
        beads=8,
        frames=300,
        dark_frames=300,
        setpoints=(1, 5, 25),
        bleaching=0.02,
        seed=8,
        stages=SHORT,
    )
    truth = tmp_path / "sim" / "truth_calibration.nc"
    gains = [1.0, 4.78, 0.98 * 22.95]  # 25x gain 2 % low: its beads 2 % bright
    wrong = _result(
        tmp_path / "wrong",
        method="gs",
        setpoints=[1.0, 5.0, 25.0],
        gains=gains,
        shape=(64, 64),
        stages=SHORT,
    )
    fits = validation.fit_validation(sim.manifest, [str(truth), str(wrong)])
    docs = {}
    for action in ("warn", "correct"):  # one fit, compared both ways
        with pytest.warns(UserWarning, match=r"intensity falls within the acquisitions"):
            docs[action] = validation.validation_document(fits, bleaching=action)
    for action, doc in docs.items():
        trend = doc["calibrations"][0]["intensity_trend"]
        assert trend["detected"] and trend["z"] > 4
        assert trend["fade_over_series"] == pytest.approx(0.02, abs=0.006)
        assert trend["corrected"] is (action == "correct")
    # Uncorrected, the fade of the later (25x) frames offsets the wrong gain there;
    # corrected, the true calibration is first and consistent.
    assert docs["warn"]["ranking"][0] == str(wrong)
    assert docs["correct"]["ranking"][0] == str(truth)
    t = docs["correct"]["calibrations"][0]
    rel = np.array([b["mean_intensity"]["25"] / b["mean_intensity"]["1"] for b in t["beads"]])
    # its error: the beads' scatter, and the fade's rate over the 600 frames between them
    err = math.hypot(rel.std(ddof=1) / math.sqrt(rel.size), 600 * t["intensity_trend"]["rate_se"])
    assert abs(rel.mean() - 1) < 3 * err


def test_a_group_takes_the_register_model_of_its_gain_members(tmp_path):
    adu = _result(tmp_path / "adu", method="is-adu", setpoints=[1.0], gains=[1.0], phi=3.9)
    g5 = _result(tmp_path / "g5", method="is-gain", setpoints=[5.0], gains=[4.78])
    g25 = _result(tmp_path / "g25", method="is-gain", setpoints=[25.0], gains=[22.95])
    for f, model in ((adu, "gamma"), (g5, "cascade"), (g25, "cascade")):
        ds = result.load(f)
        ds.attrs.update(
            {"em_model": model} | ({"register_stages": 536} if model == "cascade" else {})
        )
        result.save(ds, f.parent)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = result.load_calibration([adu, g5, g25])  # 1x has no register to disagree
    assert cal.em_model.name == "cascade" and cal.em_model.stages == 536
    ds = result.load(g25)
    ds.attrs["em_model"] = "gamma"
    del ds.attrs["register_stages"]
    result.save(ds, g25.parent)
    with pytest.raises(ValueError, match="fitted with different EM register models"):
        result.load_calibration([adu, g5, g25])


def test_blinking_level_finds_off_frames_and_nothing_else():
    rng = np.random.default_rng(11)
    # 200 bead-set-points without blinking: none detected, the mean untouched
    se = np.full((200, 300), 100.0)
    N = 3000.0 + se * rng.standard_normal(se.shape)
    b = validation.blinking_level(N, se)
    assert not b["detected"].any() and not b["off"].any()
    # 20 % off, in runs: the on level within its error, the off frames found
    on = np.ones((4, 300), bool)
    for k in range(4):
        for start in rng.choice(290, 12, replace=False):
            on[k, start : start + 5] = False
    N = np.where(on, 3000.0, 0.0) + se[:4] * rng.standard_normal((4, 300))
    b = validation.blinking_level(N, se[:4])
    assert b["detected"].all()
    np.testing.assert_array_equal(b["off"], ~on)
    assert np.all(np.abs(b["on_level"] - 3000.0) < 4 * 100.0 / np.sqrt(on.sum(axis=1)))
    np.testing.assert_allclose(b["off_fraction"], (~on).mean(axis=1), atol=0.01)


@pytest.mark.slow
def test_blinking_beads_are_taken_at_their_on_level(tmp_path):
    """Beads off in 10 % of frames, in runs of 5: a different fraction at each set-point,
    which the plain means take for a gain error; the mixture's on level does not."""
    sim = simulate_beads(
        tmp_path / "sim",
        beads=6,
        frames=200,
        dark_frames=300,
        setpoints=(1, 25),
        blinking=0.1,
        seed=8,
        stages=SHORT,
    )
    truth = tmp_path / "sim" / "truth_calibration.nc"
    wrong = _result(
        tmp_path / "wrong",
        method="gs",
        setpoints=[1.0, 25.0],
        gains=[1.0, 0.98 * 22.95],
        shape=(64, 64),
        stages=SHORT,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # each document below warns of the blinking
        fits = validation.fit_validation(sim.manifest, [str(truth), str(wrong)])
    docs = {}
    for action in ("ignore", "model"):  # one fit, compared both ways
        with pytest.warns(UserWarning, match=r"switch off in some frames"):
            docs[action] = validation.validation_document(fits, blinking=action)
    off_true = sum(b["frames_off"] for b in sim.truth["beads"])
    for doc in docs.values():
        found = sum(doc["calibrations"][0]["blinking"]["frames_off"].values())
        assert abs(found - off_true) <= 0.02 * off_true
    ignored = {c["file"]: c for c in docs["ignore"]["calibrations"]}
    modelled = {c["file"]: c for c in docs["model"]["calibrations"]}
    assert ignored[str(truth)]["sigma_means_incl_1x"] > 0.01  # blinking dominates
    assert modelled[str(truth)]["sigma_means_incl_1x"] < 0.005
    assert docs["model"]["ranking"][0] == str(truth)
    # the 2 % gain error, seen through the blinking: 25x/1x = 1/0.98 for every bead
    rel = [
        b["mean_intensity"]["25"] / b["mean_intensity"]["1"] for b in modelled[str(wrong)]["beads"]
    ]
    assert np.mean(rel) == pytest.approx(1 / 0.98, abs=0.006)
    table = validation.format_table(docs["model"])
    assert re.search(r"6 bead\(s\) blinking, \d+ frame\(s\) off \(on level taken\)", table)
    with pytest.raises(ValueError, match="blinking must be"):
        validation.validate(sim.manifest, [str(truth)], blinking="drop")
    with pytest.raises(ValueError, match="blinking must be"):
        validation.validation_document(fits, blinking="drop")


@pytest.mark.slow
def test_residual_psf_pass_on_beads_with_a_halo(tmp_path):
    """Beads whose PSF has a halo: validate says the Gaussian does not describe them, and
    with --psf residual fits a third pass whose model does; the truth stays first."""
    sim = simulate_beads(
        tmp_path / "sim",
        beads=6,
        frames=200,
        dark_frames=300,
        setpoints=(1, 25),
        halo=0.2,
        seed=9,
        stages=SHORT,
    )
    truth = tmp_path / "sim" / "truth_calibration.nc"
    wrong = _result(
        tmp_path / "wrong",
        method="gs",
        setpoints=[1.0, 25.0],
        gains=[1.0, 0.98 * 22.95],
        shape=(64, 64),
        stages=SHORT,
    )
    with pytest.warns(UserWarning, match=r"does not describe .* residual image was added"):
        doc = validation.validate(
            sim.manifest, [str(truth), str(wrong)], psf="residual", out=tmp_path / "val"
        )
    c = doc["calibrations"][0]
    assert c["psf"] == "residual"
    assert c["psf_mismatch"]["gaussian"]["25"]["chi2_per_pixel"] > 2.0
    # held out: built on the even frames, scored on the odd, its own noise counted
    assert doc["psf_held_out"]["scored_on"] == "odd frames"
    held_out = c["psf_mismatch"]["residual"]["25"]
    assert abs(held_out["chi2_per_pixel"] - 1) < 4 * held_out["chi2_per_pixel_se"]
    assert doc["ranking"][0] == str(truth)
    assert (
        json.loads((tmp_path / "val" / "validation.json").read_text())["calibrations"][0]["psf"]
        == "residual"
    )
    with pytest.raises(ValueError, match="psf must be"):
        validation.validate(sim.manifest, [str(truth)], psf="airy")
    with pytest.raises(ValueError, match="psf_split must be"):
        validation.validate(sim.manifest, [str(truth)], psf="residual", psf_split="odd")


@pytest.mark.slow
def test_a_repeated_set_point_joins_the_trend_and_is_checked(tmp_path):
    """1x recorded again at the end of a bleaching series: its frames pool with the
    first 1x acquisition's, the fade is measured across the whole series, and after the
    correction the two 1x acquisitions agree."""
    sim = simulate_beads(
        tmp_path / "sim",
        beads=6,
        frames=200,
        dark_frames=300,
        setpoints=(1, 25),
        repeat=1,
        bleaching=0.03,
        seed=12,
        stages=SHORT,
    )
    names = [a["name"] for a in sim.truth["acquisitions"]]
    assert names == ["1x", "25x", "1x-repeat"]
    truth = tmp_path / "sim" / "truth_calibration.nc"
    with pytest.warns(UserWarning, match="intensity falls"):
        doc = validation.validate(sim.manifest, [str(truth)], out=tmp_path / "val")
    c = doc["calibrations"][0]
    assert c["intensity_trend"]["fade_over_series"] == pytest.approx(0.03, abs=0.006)
    assert c["beads"][0]["frames_used"] == {"1": 400, "25": 200}
    (rep,) = c["repeats"]
    assert rep["setpoint"] == "1" and rep["first"] == "1x"
    (later,) = rep["later"]
    assert later["acquisition"] == "1x-repeat" and abs(later["z"]) < 4
    assert set(c["psf_mismatch"]["gaussian"]) == {"1", "25", "1#2"}
    assert c["sigma_means_incl_1x"] < 0.005
    assert re.search(
        r"intensity trend -\d\.\d\d % over the series \(z \d+\.\d, corrected\)\n"
        r" +1x recorded again: \d\.\d{4} ± \d\.\d{4} of the first",
        validation.format_table(doc),
    )
    ds = xr.open_dataset(tmp_path / "val" / "intensities.nc", engine="h5netcdf")
    acq = ds["acquisition"].sel(setpoint=1.0).values
    assert list(acq[:200]) == ["1x"] * 200 and list(acq[200:]) == ["1x-repeat"] * 200
    ds.close()


def test_repeats_warn_when_the_beads_changed_between_acquisitions():
    class Acq:
        def __init__(self, name, n):
            self.name, self.n_frames = name, n

    a1, a25, a1b = Acq("1x", 100), Acq("25x", 100), Acq("1x-again", 100)
    slot = validation.metric._Slot
    layout = [
        slot(0, 1.0, a1, 0, "1", 0),
        slot(1, 25.0, a25, 0, "25", 100),
        slot(0, 1.0, a1b, 100, "1#2", 200),
    ]
    rng = np.random.default_rng(2)
    I = 5000.0 * (1 + 0.01 * rng.standard_normal((8, 2, 200)))
    off = np.zeros(I.shape, bool)
    rep = validation.document._repeats(type("Cal", (), {"label": "c"}), layout, ["1", "25"], I, off)
    assert abs(rep[0]["later"][0]["z"]) < 4
    I[:, 0, 100:] *= 0.97  # 3 % of the light lost between the acquisitions
    with pytest.warns(
        UserWarning,
        match=r"changed by -3\.\d\d % between acquisitions '1x' "
        r"and '1x-again'",
    ):
        rep = validation.document._repeats(
            type("Cal", (), {"label": "c"}), layout, ["1", "25"], I, off
        )
    assert rep[0]["later"][0]["ratio"] == pytest.approx(0.97, abs=0.002)
