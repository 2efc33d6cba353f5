"""``emccdcal plan``: the acquisition a target precision needs, predicted from the Fisher
information and checked by recording (simulating) exactly what the plan says."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from emccdcal import cli
from emccdcal.acquire.plan import plan, predict
from emccdcal.acquire.plan_file import plan_text, read_plan
from emccdcal.calibration import calibrate
from emccdcal.errors import InputError
from emccdcal.model.noise import EMModel, excess_noise_factor
from emccdcal.simulate.series import simulate_gain_series

#: The paper's ProEM-like camera (docs/protocol.md).
PROEM = dict(e_per_adu=3.859, read_noise=15.5, offset=587.7, adc_bits=16)
SETPOINTS = [1, 5, 25, 100, 300]


@pytest.mark.slow
def test_a_gain_series_recorded_as_planned_reaches_the_predicted_precision(tmp_path):
    """Simulate what the plan says (its light, frames per set-point and darks, the gains
    it assumed), calibrate, and compare with the prediction per set-point: the reported
    per-pixel SE and the scatter of the estimates over pixels within 15 %, the 95 %
    intervals covering the truth 93-97 % of the time (1024 intervals)."""
    p = plan(method="gs", setpoints=SETPOINTS, target_se=1.0, **PROEM)
    assert p.reached and p.predicted_se <= 1.0
    sim = simulate_gain_series(
        tmp_path / "sim",
        setpoints=[a.setpoint for a in p.acquisitions],
        em_gain=[a.em_gain for a in p.acquisitions],
        photoelectrons=p.photoelectrons,
        frames=[a.frames for a in p.acquisitions],
        dark_frames=p.dark_frames,
        seed=11,
        rows=16,
        cols=16,
        offset_drop=0.0,
        **{k: PROEM[k] for k in ("e_per_adu", "read_noise", "offset")},
    )
    ds = calibrate(sim.manifest, method="gs", checks=False)
    covered = []
    for a in p.acquisitions[1:]:
        g = ds.em_gain.sel(setpoint=a.setpoint).values.ravel()
        se = ds.em_gain_se.sel(setpoint=a.setpoint).values.ravel()
        predicted = a.predicted_se["em_gain"] / 100
        assert np.median(se / g) == pytest.approx(predicted, rel=0.15)
        assert np.std(np.log(g)) == pytest.approx(predicted, rel=0.15)
        covered.append(np.abs(g - a.em_gain) <= 1.96 * se)
    assert 0.93 <= np.mean(covered) <= 0.97


def test_a_plan_through_the_array_api_standard_is_numpys():
    """The plan's expected information from windows computed on array-api-strict arrays
    (a pretend device: nothing outside the standard passes) is NumPy's: the same plan."""
    pytest.importorskip("array_api_strict")
    here = plan(method="gs", setpoints=SETPOINTS, target_se=1.0, **PROEM)
    there = plan(
        method="gs", setpoints=SETPOINTS, target_se=1.0, device="array-api-strict", **PROEM
    )
    assert plan_text(there) == plan_text(here)


def test_the_plan_is_least_cost_and_within_the_papers_frames():
    """A 0.5 % plan for the paper's camera asks for no stack beyond the paper's 5000
    frames; every targeted SE meets the target; a tighter target costs more frames, about
    as 1/target²; fewer frames than planned miss it."""
    p = plan(method="gs", setpoints=SETPOINTS, target_se=0.5, **PROEM)
    assert p.reached and max(a.frames for a in p.acquisitions) <= 5000
    assert p.dark_frames <= 5000
    assert all(a.predicted_se["em_gain"] <= 0.5 for a in p.acquisitions[1:])
    tight = plan(method="gs", setpoints=SETPOINTS, target_se=0.25, **PROEM)
    assert 3.0 < tight.total_frames / p.total_frames < 5.0
    # the same stacks with a fifth fewer light frames each: above the target
    fewer = predict(
        "gs",
        [a.setpoint for a in p.acquisitions],
        [a.em_gain for a in p.acquisitions],
        [a.photoelectrons for a in p.acquisitions],
        [int(0.8 * a.frames) for a in p.acquisitions],
        p.dark_frames,
        p.camera,
        0.5,
    )
    assert not fewer.reached and fewer.predicted_se > p.predicted_se


def test_the_light_stays_clear_of_the_adc_and_darks_matter():
    """The chosen light leaves the brightest stack's mean + 6 SD below 90 % of the ADC;
    with a 12-bit ADC it must be dimmer; the plan's darks are not the fewest allowed
    (the offset map's error enters every estimate)."""
    p = plan(method="gs", setpoints=SETPOINTS, target_se=0.5, **PROEM)
    g, phi, E = 300.0, PROEM["e_per_adu"], p.photoelectrons
    f2 = excess_noise_factor(g, em_model=EMModel("cascade", 536))
    sd = np.sqrt(f2 * E * (g / phi) ** 2 + PROEM["read_noise"] ** 2)
    assert PROEM["offset"] + E * g / phi + 6 * sd <= 0.9 * 65535
    small = plan(
        method="gs", setpoints=SETPOINTS, target_se=0.5, **(PROEM | {"adc_bits": 14, "offset": 100})
    )
    assert small.photoelectrons < E / 3
    # a register well of 80 000 e- (data sheet) caps the multiplied charge at 300x
    capped = plan(method="gs", setpoints=SETPOINTS, target_se=0.5, register_well=8e4, **PROEM)
    assert capped.photoelectrons * 300 <= 0.9 * 8e4
    adu = plan(method="is-adu", target_se=1.0, pixel_well=1e5, **PROEM)
    assert max(a.photoelectrons for a in adu.acquisitions) <= 0.9 * 1e5
    few_darks = predict(
        "gs",
        SETPOINTS,
        [a.em_gain for a in p.acquisitions],
        [E] * 5,
        [a.frames for a in p.acquisitions],
        50,
        p.camera,
        0.5,
    )
    assert few_darks.predicted_se > 1.2 * p.predicted_se


def test_intensity_series_plans_target_their_own_estimate():
    adu = plan(method="is-adu", target_se=2.0, **PROEM)
    assert adu.method == "is-adu" and adu.reached
    assert {a.setpoint for a in adu.acquisitions} == {1.0}
    assert all("e_per_adu" in a.predicted_se for a in adu.acquisitions)
    gain = plan(method="is-gain", setpoint=100, target_se=1.0, **PROEM)
    assert gain.reached and {a.setpoint for a in gain.acquisitions} == {100.0}


def test_plan_toml_round_trips_and_an_edit_is_predicted_again(tmp_path, capsys):
    out = tmp_path / "session"
    assert (
        cli.main(
            [
                "plan",
                "--e-per-adu",
                "3.859",
                "--read-noise",
                "15.5",
                "--offset",
                "587.7",
                "--target-se",
                "1",
                "--frame-rate",
                "50",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "target 1 % reached" in printed and "min at 50 Hz" in printed
    text = (out / "plan.toml").read_text()
    again = read_plan(out / "plan.toml")
    assert plan_text(again) == text  # the file says what it predicts
    # a person halves the 5x stack: the check predicts more error there, and says so
    edited = tmp_path / "edited.toml"
    frames_5x = again.acquisitions[1].frames
    edited.write_text(
        text.replace(
            f"em_gain_setpoint = 5.0\nframes = {frames_5x}\n",
            f"em_gain_setpoint = 5.0\nframes = {frames_5x // 2}\n",
        )
    )
    worse = read_plan(edited)
    assert (
        worse.acquisitions[1].predicted_se["em_gain"]
        > 1.05 * again.acquisitions[1].predicted_se["em_gain"]
    )  # E's shared error stays
    assert cli.main(["plan", "--check", str(edited)]) == 0
    assert "target 1 % NOT reached: record more frames" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("\nframes = ", "\nframes = -", 1))
    with pytest.raises(InputError, match=r"bad\.toml': frames must be an integer >= 2"):
        read_plan(bad)


def test_an_unreachable_target_says_so_and_exits_1(capsys):
    code = cli.main(
        [
            "plan",
            "--e-per-adu",
            "3.859",
            "--read-noise",
            "15.5",
            "--offset",
            "587.7",
            "--target-se",
            "0.1",
            "--max-frames",
            "2000",
        ]
    )
    assert code == 1
    out = capsys.readouterr().out
    assert "NOT reached within 2000 frames per stack" in out
    assert cli.main(["plan", "--read-noise", "15.5", "--offset", "587.7"]) == 2
    err = capsys.readouterr().err
    assert "plan needs --e-per-adu" in err and len(err.strip().splitlines()) == 1


def test_an_earlier_result_describes_the_camera(tmp_path, capsys):
    from test_export import OFFSET, PHI, SIGMA, true_result

    from emccdcal.acquire.plan import camera_of

    result = true_result(tmp_path / "res")
    assert camera_of(result) == pytest.approx(
        {"e_per_adu": PHI, "offset": OFFSET, "read_noise": SIGMA}
    )
    assert (
        cli.main(
            [
                "plan",
                "--e-per-adu",
                str(result),
                "--target-se",
                "1",
                "-q",
                "-o",
                str(tmp_path / "p.toml"),
            ]
        )
        == 0
    )
    assert read_plan(tmp_path / "p.toml").camera["e_per_adu"] == pytest.approx(PHI)


@pytest.mark.slow
def test_a_plan_of_2000_set_points_is_refused_in_bounded_memory(tmp_path):
    """Its information matrices asked for 60 GiB: one line naming the plan, under 2 GB."""
    from conftest import run_measured

    head, *acquisitions = _plan_doc(tmp_path).split("[[acquisition]]")
    one = acquisitions[-1]
    text = head + "".join(
        "[[acquisition]]"
        + re.sub(r"em_gain_setpoint = [\d.]+", f"em_gain_setpoint = {2.0 + i / 2}", one)
        for i in range(2000)
    )
    path = tmp_path / "many.toml"
    path.write_text(text)
    done, peak = run_measured(["plan", "--check", path, "-q"], timeout=300)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert f"'{path}': a series of 2000 acquisitions: at most 64" in done.stderr
    assert peak < 2 * 2**30, peak


def _plan_doc(tmp_path):
    assert (
        cli.main(
            [
                "plan",
                "--e-per-adu",
                "3.9",
                "--read-noise",
                "15.5",
                "--offset",
                "590",
                "-o",
                str(tmp_path / "p"),
                "-q",
            ]
        )
        == 0
    )
    return (tmp_path / "p/plan.toml").read_text()


@pytest.mark.parametrize(
    "edit, says",
    [
        (
            lambda t: re.sub(r"\[camera\][^\[]*", 'camera = "abc"\n\n', t),
            "[camera] must be a table",
        ),
        (lambda t: re.sub(r"\[camera\][^\[]*", "camera = 5\n\n", t), "[camera] must be a table"),
        (
            lambda t: (
                t.split("[camera]")[0]
                + "acquisition = [1, 2]\n[camera]"
                + t.split("[camera]")[1].split("[[acquisition]]")[0]
            ),
            "each [[acquisition]] must be a table",
        ),
        (lambda t: t.replace("stages = 536", "stages = [1, 2]"), "stages must be an integer"),
        (
            lambda t: re.sub(r"^photoelectrons = \S+", "photoelectrons = 1e-300", t, flags=re.M),
            "determine no estimate",
        ),
    ],
    ids=["camera-text", "camera-number", "acquisition-numbers", "stages-list", "no-light"],
)
def test_a_malformed_plan_is_one_line_naming_it(tmp_path, capsys, edit, says):
    path = tmp_path / "bad.toml"
    path.write_text(edit(_plan_doc(tmp_path)))
    capsys.readouterr()
    assert cli.main(["plan", "--check", str(path), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"'{path}': " in err and says in err, err


def test_stop_at_target_without_a_1x_acquisition_is_refused_before_recording(tmp_path, capsys):
    text = _plan_doc(tmp_path)
    head, *acquisitions = text.split("[[acquisition]]")
    path = tmp_path / "no1x.toml"
    path.write_text(head + "".join("[[acquisition]]" + a for a in acquisitions[1:]))
    capsys.readouterr()
    code = cli.main(
        ["acquire", str(path), "-o", str(tmp_path / "s"), "--simulated", "--stop-at-target", "-q"]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "lacks" in err and "1x" in err, err
    assert not (tmp_path / "s").exists()


def test_a_number_of_thousands_of_digits_is_one_line_without_pythons_advice(tmp_path, capsys):
    path = tmp_path / "big.toml"
    path.write_text(_plan_doc(tmp_path).replace("dark_frames = 900", "dark_frames = " + "9" * 5000))
    capsys.readouterr()
    assert cli.main(["plan", "--check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "thousands of digits" in err and "sys." not in err, err


#: A Hamamatsu ORCA-Quest-like qCMOS: 0.27 e⁻ of read noise resolves photon numbers.
QCMOS = dict(e_per_adu=0.107, read_noise=2.5, offset=200.0, pixel_well=7000, camera_kind="qcmos")


@pytest.mark.parametrize("target", [1.0, 0.1])
def test_where_photon_numbers_show_the_plan_is_a_ladder_of_dim_levels(target):
    """φ's information is then the comb's, which only a fit climbing from dim levels
    delivers: the plan's levels are 0.5 e⁻ and each three times the last, four or more,
    each with the frames and the darks that make the prediction hold (a plan of the
    brightest light alone, 50 frames at 5831 e⁻, predicted 0.001 %: its ripples are
    1/5831 apart and no fit could tell which one is true)."""
    from emccdcal.acquire.plan import LADDER_DARKS, LADDER_FRAMES, LADDER_RUNGS

    p = plan(method="is-adu", target_se=target, **QCMOS)
    light = np.array([a.photoelectrons for a in p.acquisitions])
    assert p.reached and p.predicted_se <= target
    assert light.size >= LADDER_RUNGS and p.dark_frames >= LADDER_DARKS
    np.testing.assert_allclose(light, 0.5 * 3.0 ** np.arange(light.size))
    assert all(a.frames >= LADDER_FRAMES for a in p.acquisitions)
    # an sCMOS's photon numbers do not show: its plan is of bright levels, as before
    bright = plan(method="is-adu", target_se=target, e_per_adu=0.46, read_noise=3.0,
                  offset=100.0, pixel_well=30000)  # fmt: skip
    assert min(a.photoelectrons for a in bright.acquisitions) > 500


@pytest.mark.slow
def test_a_qcmos_recorded_as_planned_reaches_the_predicted_precision(tmp_path):
    """The ladder simulated as planned (its levels and frames, its darks; 10 × 10 px, a
    log-normal spread of read noise about 0.27 e⁻) and calibrated: the median SE of φ
    within 20 % of the prediction (0.251 % for 0.241 % predicted on seeds 4–7), and the
    95 % intervals covering 0.9 or more of the pixels (0.948)."""
    import tifffile

    from emccdcal.simulate.cmos import simulate_cmos_series

    p = plan(method="is-adu", target_se=1.0, **QCMOS)
    sim = simulate_cmos_series(
        tmp_path / "sim", kind="qcmos", rows=10, cols=10,
        levels=[a.photoelectrons for a in p.acquisitions],
        frames=max(a.frames for a in p.acquisitions), dark_frames=p.dark_frames,
        seed=3, progress=False,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 50 darks: the read noise's own error is said
        ds = calibrate(sim.manifest, progress=False)
    truth = tifffile.imread(sim.outdir / "truth-e_per_adu.tif")
    se = ds.e_per_adu_se.values / ds.e_per_adu.values
    assert np.median(100 * se) == pytest.approx(p.predicted_se, rel=0.2)
    z = (ds.e_per_adu.values - truth) / ds.e_per_adu_se.values
    assert np.mean(np.abs(z) < 1.96) >= 0.9
