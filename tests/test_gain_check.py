"""``emccdcal gain-check``: the EM gain from dark frames alone (fit.darkgain), against
its calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from emccdcal import cli
from emccdcal.errors import InputError
from emccdcal.export import database
from emccdcal.fit.darkgain import check_gain
from emccdcal.simulate.camera import simulate_frames

PHI, OFFSET, SIGMA = 3.859, 500.0, 15.5


def _darks(g, *, seed, frames=2000, size=16, cic=0.01, multiplication="cascade"):
    return simulate_frames(
        0.0,
        g,
        PHI,
        OFFSET,
        SIGMA,
        frames=frames,
        rows=size,
        cols=size,
        cic=cic,
        multiplication=multiplication,
        seed=seed,
    )


@pytest.mark.parametrize("g, model", [(300.0, "cascade"), (100.0, "cascade"), (300.0, "gamma")])
# (where the check is valid, against gain, charge and read noise: docs/gain-check.md)
def test_the_gain_of_simulated_darks_within_its_standard_error(g, model):
    """Known truth: the exact register's darks (and gamma darks under the gamma model),
    the gain within 3 SE; the SE what the events allow (about 1/√events at high gain)."""
    darks = _darks(g, seed=11, multiplication=model)
    check = check_gain(
        [darks], PHI, setpoint=g, em_model=model, stages=536 if model == "cascade" else None
    )
    assert abs(check.em_gain - g) < 3 * check.em_gain_se
    assert check.pixels == 256 and check.frames == 2000
    assert check.events == pytest.approx(256 * 2000 * 0.01, rel=0.15)
    assert check.event_rate == pytest.approx(0.01, rel=0.15)
    if g == 300:
        assert 0.8 < check.relative_se * np.sqrt(check.events) < 1.6
    # the frames a target needs scale with the SE squared
    assert check.frames_for(check.relative_se / 2) == pytest.approx(4 * 2000, rel=0.01)


@pytest.mark.parametrize(
    "device, library", [("array-api-strict", "array_api_strict"), ("jax", "jax")]
)
def test_the_gain_check_through_the_array_api_standard_is_numpys(device, library):
    """The shared register's tables evaluated on array-api-strict arrays (a pretend
    device: nothing outside the standard passes, the blocks' threads included), or
    through JAX (a real library whose arrays are immutable), give the gain NumPy's
    evaluation gives."""
    pytest.importorskip(library)
    darks = _darks(300.0, seed=5, frames=500, size=8)
    here = check_gain([darks], PHI, bias_correction=False)
    there = check_gain([darks], PHI, bias_correction=False, device=device)
    assert there.em_gain == pytest.approx(here.em_gain, rel=1e-10)
    assert there.em_gain_se == pytest.approx(here.em_gain_se, rel=1e-10)
    assert (here.device, there.as_dict()["device"]) == ("cpu", device)


def test_a_region_and_several_stacks_and_too_few_events():
    """Two stacks of one set-point pool their frames; a region uses only its pixels; darks
    without multiplied events (1×, no charge) are refused with the reason."""
    a, b = _darks(300.0, seed=1, frames=1000), _darks(300.0, seed=2, frames=1000)
    both = check_gain([a, b], PHI)
    assert both.frames == 2000 and abs(both.em_gain - 300) < 3 * both.em_gain_se
    part = check_gain([a, b], PHI, region=(slice(0, 8), slice(4, 12)))
    assert part.pixels == 64 and part.em_gain_se > 1.5 * both.em_gain_se
    cut = check_gain([a[:, 0:8, 4:12], b[:, 0:8, 4:12]], PHI)
    assert (cut.em_gain, cut.em_gain_se) == (part.em_gain, part.em_gain_se)
    with pytest.raises(InputError, match="too low for a check from dark frames"):
        check_gain([_darks(300.0, seed=3, frames=200, cic=0.0)], PHI)


def test_a_gain_the_darks_do_not_determine_is_refused_with_what_would(monkeypatch):
    """Events of 13 ADU under a read noise of 26 ADU (50x, 100 e- rms): a gain of ± 19 %
    here; with the refusal threshold below that, one line saying so and what would
    determine it, never a number whose ± reads as "agrees" with any calibration."""
    from emccdcal.fit import darkgain

    darks = simulate_frames(
        0.0, 50.0, PHI, OFFSET, 25.9, frames=1000, rows=32, cols=32, cic=0.01, seed=1
    )
    check = check_gain([darks], PHI)
    assert 0.1 < check.relative_se < darkgain.MAX_RELATIVE_SE
    monkeypatch.setattr(darkgain, "MAX_RELATIVE_SE", 0.1)
    with pytest.raises(InputError, match="do not determine the EM gain") as info:
        check_gain([darks], PHI)
    message = str(info.value)
    assert "\n" not in message and "1024 px × 1000 frames" in message
    assert f"needs about {check.frames_for(0.02)} frames" in message


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A simulated gain series (charge in its darks) calibrated by gs: (folder, result)."""
    out = tmp_path_factory.mktemp("gaincheck")
    series = out / "series"
    assert (
        cli.main(
            [
                "simulate",
                "gain-series",
                "-o",
                str(series),
                "--rows",
                "16",
                "--cols",
                "16",
                "--frames",
                "400",
                "--dark-frames",
                "3000",
                "--cic",
                "0.02",
                "--setpoints",
                "1,100,300",
                "--em-gain",
                "1,95,310",
                "--seed",
                "4",
                "-q",
            ]
        )
        == 0
    )
    result = out / "cal"
    assert (
        cli.main(
            ["calibrate", str(series / "manifest.toml"), "-o", str(result), "--no-checks", "-q"]
        )
        == 0
    )
    return series, next(result.glob("*.nc"))


@pytest.mark.slow
def test_darks_of_a_calibrated_series_agree_and_a_fallen_gain_is_flagged(
    calibrated, tmp_path, capsys
):
    """The darks of the simulated series give the gain its gs calibration found (within
    the combined SE, exit 0); darks of the camera after its gain fell 5 % are flagged
    (exit 1, "below its calibration")."""
    series, result = calibrated
    dark = series / "gain-GS" / "300x-gain_no-signal.tif"
    code = cli.main(
        ["gain-check", str(dark), "--setpoint", "300", "--calibration", str(result), "--json", "-q"]
    )
    record = json.loads(capsys.readouterr().out)
    assert code == 0, record
    assert {
        "em_gain",
        "em_gain_se",
        "setpoint",
        "events",
        "event_rate",
        "e_per_adu",
        "em_model",
    } <= set(record)
    assert abs(record["calibration"]["z"]) < 3 and record["setpoint"] == 300
    fallen = tmp_path / "fallen.tif"
    tifffile.imwrite(fallen, _darks(0.95 * 310, seed=9, frames=3000, cic=0.02))
    code = cli.main(
        ["gain-check", str(fallen), "--setpoint", "300", "--calibration", str(result), "-q"]
    )
    printed = capsys.readouterr().out
    assert code == 1 and "below its calibration" in printed and "recalibrate" in printed

    # The drift watch: the calibration in the database, the checks recorded beside it
    # (phi and the gain compared with from the database's calibration of the camera).
    db = tmp_path / "cal.sqlite"
    database.add(result, db=db, camera="SIM-1", date="2026-01-10")
    common = ["--setpoint", "300", "--camera", "SIM-1", "--db", str(db), "--record"]
    out = tmp_path / "check"
    assert (
        cli.main(["gain-check", str(dark), *common, "--date", "2026-02-01", "-o", str(out), "-q"])
        == 0
    )
    record = json.loads((out / "gain-check.json").read_text())
    assert record["calibration"]["changed"] is False and (out / "gain-check.png").is_file()
    assert cli.main(["gain-check", str(fallen), *common, "--date", "2026-03-01", "-q"]) == 1
    checks = database.checks(db=db, camera="SIM-1")
    assert [c.date[:10] for c in checks] == ["2026-02-01", "2026-03-01"]
    capsys.readouterr()
    assert (
        cli.main(
            ["db", "--db", str(db), "compare", "--camera", "SIM-1", "-o", str(tmp_path / "history")]
        )
        == 1
    )
    captured = capsys.readouterr()
    assert "gain check of 2026-03-01" in captured.err and "below its calibration" in captured.err
    assert (
        "2026-02-01" in captured.out and (tmp_path / "history" / "gain-history-SIM-1.png").is_file()
    )

    # The HTML report of the calibration shows the camera's history from the database.
    from emccdcal.report.html import build_report

    page = build_report([result], db=db, camera="SIM-1")
    history = page[page.index('<section id="history">') : page.index('<section id="provenance">')]
    assert "calibration (this result)" in history and history.count("gain check") >= 2
    assert "gain check of 2026-03-01" in history and 'id="figures-history-1"' in history
    assert "data:image/png;base64," in history


# --------------------------------------------------------------------------------------
# The tables of a shared register against the exact model
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "model, g, rate, cic, per_pixel",
    [
        ("cascade", 300.0, 0.01, 0.0, False),
        ("gamma", 300.0, 0.01, 0.0, False),
        ("cascade", 50.0, 0.02, 0.005, False),
        ("cascade", 1000.0, 0.01, 0.0, False),
        ("cascade", 200.0, 0.3, 0.0, True),
    ],
)
def test_shared_register_tables_match_the_exact_model(model, g, rate, cic, per_pixel):
    """Pixels of their own offsets and read noises (14-17 ADU) sharing one register: ln p
    within 1e-5 of the window engine's wherever p is above 1e-10 of its peak (1e-6 above
    1e-6), and the gain's and the offset's scores within 1e-4 of its differences."""
    from emccdcal.model import noise
    from emccdcal.model.shared_register import SharedRegister

    rng = np.random.default_rng(0)
    P = 6
    sigma, S0 = rng.uniform(14, 17, P), rng.uniform(400, 600, P)
    E = rng.uniform(0.5 * rate, 1.5 * rate, P) if per_pixel else None
    register = noise.as_em_model(model).register
    shared = ("ln_gain",) + (("register_cic",) if cic else ()) + (() if per_pixel else ("ln_rate",))
    table = SharedRegister(
        register,
        g,
        PHI,
        sigma,
        rate=E.max() if per_pixel else rate,
        register_cic=cic,
        per_pixel_rate=per_pixel,
        shared=shared,
    )
    theta = g / PHI  # one electron's mean output, ADU
    values = (
        np.floor(S0)[:, None]
        + np.r_[np.arange(-100, 100, 7), np.arange(100, 25 * theta, theta / 3)]
    ).astype(np.int64)
    with np.errstate(divide="ignore"):  # 0 below round-off, far outside what is compared
        ours = np.log(table.pmf(values, S0, sigma, E))
    rate_ = E[:, None] if per_pixel else rate

    def exact(g_=g, S0_=S0):
        return noise.logpmf(
            values, rate_, g_, PHI, S0_[:, None], sigma[:, None], em_model=model, register_cic=cic
        )

    ref = exact()
    peak = ref.max(axis=1, keepdims=True)
    inside, core = ref > peak + np.log(1e-10), ref > peak + np.log(1e-6)
    assert np.abs(ours - ref)[inside].max() < 1e-5
    assert np.abs(ours - ref)[core].max() < 1e-6
    _, grad, _, floored = table.evaluate(values, inside.astype(float), S0, sigma, E)
    assert not floored.any()
    names = table.coordinates()
    for column, fd in (
        ("ln_gain", (exact(g_=g * np.exp(1e-5)) - exact(g_=g * np.exp(-1e-5))) / 2e-5),
        ("offset", (exact(S0_=S0 + 1e-4) - exact(S0_=S0 - 1e-4)) / 2e-4),
    ):
        want = (fd * inside).sum(axis=1)
        got = grad[:, names.index(column)]
        assert np.max(np.abs(got - want)) < 1e-4 * np.max(np.abs(want)), column


def test_register_cic_is_simulated_and_fitted():
    """Charge made inside the register (entering at a random stage): the simulator makes
    it, and gain-check fits it; a check that assumes none reads the gain low."""
    darks = simulate_frames(
        0.0,
        300.0,
        PHI,
        OFFSET,
        SIGMA,
        frames=1000,
        rows=40,
        cols=40,
        cic=0.01,
        register_cic=0.01,
        seed=2,
    )
    check = check_gain([darks], PHI, fit_register_cic=True)
    assert abs(check.em_gain - 300) < 3 * check.em_gain_se
    assert abs(check.register_cic - 0.01) < 3 * check.register_cic_se
    assert check.as_dict()["register_cic_se"] == check.register_cic_se
    ignored = check_gain([darks], PHI)
    assert 300 - ignored.em_gain > 3 * ignored.em_gain_se
    with pytest.raises(
        InputError,
        match=r"not a parameter of the gamma register model: "
        r"use one that has it \(cascade\)",
    ):
        check_gain([darks], PHI, em_model="gamma", fit_register_cic=True)


@pytest.mark.slow
def test_the_bias_of_each_pixels_own_parameters_is_removed():
    """150 frames per pixel: estimating every pixel's offset and read noise biases the
    maximum-likelihood gain up (about 2 % here: docs/gain-check.md); the half-sample
    jackknife takes it out, and the gain is within 3 SE of the truth."""
    darks = _darks(300.0, seed=21, frames=150, size=128, cic=0.005)
    check = check_gain([darks], PHI)
    assert check.bias_correction == "half-sample jackknife"
    assert check.em_gain_mle - check.em_gain > check.em_gain_se
    assert abs(check.em_gain - 300) < 3 * check.em_gain_se
    plain = check_gain([darks], PHI, bias_correction=False)
    assert plain.em_gain == check.em_gain_mle and plain.bias_correction == "none"


@pytest.mark.slow
def test_emccd_detect_darks_give_its_gain():
    """Dark frames of NASA's emccd-detect (its own stage-by-stage register of 604 stages,
    CIC before it, read noise 80 e-, phi 4 e-/ADU, its ADC), 16 x 16 px x 2000 frames at
    400x: the gain within 3 SE (the full 32 x 32 x 4000 at several gains:
    benchmarks/gain_check_study.py)."""
    detect = pytest.importorskip("emccd_detect.emccd_detect")
    np.random.seed(7)  # noqa: NPY002  (emccd-detect draws from NumPy's global generator)
    camera = detect.EMCCDDetectBase(
        em_gain=400.0,
        full_well_image=1e5,
        full_well_serial=9e4,
        dark_current=0.0,
        cic=0.005,
        read_noise=80.0,
        bias=2000.0,
        qe=0.9,
        cr_rate=0.0,
        pixel_pitch=13e-6,
        eperdn=4.0,
        nbits=16,
        numel_gain_register=604,
    )
    # independent pixels (no traps, no fixed pattern): frames simulated as one tall frame
    darks = camera.sim_sub_frame(np.zeros((2000 * 16, 16)), 0.0).reshape(2000, 16, 16)
    check = check_gain([darks.astype(np.uint16)], 4.0, stages=604)
    assert abs(check.em_gain - 400) < 3 * check.em_gain_se
    assert check.relative_se < 0.04
    assert check.event_rate == pytest.approx(0.005, rel=0.15)


def test_a_half_lit_movie_without_a_region_is_refused_in_bounded_memory(tmp_path):
    """The user forgot --region: half the movie is lit. One line naming the file and what
    to give, under 2 GB (the tables of the lit pixels' read noises took 5.4 GB and more),
    and with the region the same file checks."""
    from conftest import run_measured

    light = np.zeros((16, 16))
    light[:, 8:] = 200.0
    movie = tmp_path / "movie.tif"
    tifffile.imwrite(
        movie,
        simulate_frames(
            light,
            em_gain=262.0,
            e_per_adu=3.859,
            offset=566.0,
            read_noise=15.5,
            frames=400,
            seed=1,
            cic=0.05,
        ),
    )
    base = ["gain-check", movie, "--e-per-adu", 3.859, "--setpoint", 300, "-q"]
    done, peak = run_measured(base, timeout=300)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert f"'{movie}': 128 of 256 pixels are not dark" in done.stderr
    assert "--region" in done.stderr and peak < 2 * 2**30, peak
    done, peak = run_measured([*base, "--region", "0:16,0:8"], timeout=300)
    assert done.returncode == 0, done.stderr


def test_tables_beyond_their_memory_bound_are_refused_before_they_are_built():
    from emccdcal.model.noise import EMModel
    from emccdcal.model.shared_register import SharedRegister

    sigma = np.concatenate([np.full(50, 15.0), np.linspace(1000, 1600, 128)])
    with pytest.raises(InputError, match=r"read noises span 15 to 1\d+ ADU.*GiB"):
        SharedRegister(
            EMModel("cascade").register,
            262.0,
            3.859,
            sigma,
            rate=0.05,
            register_cic=0.0,
            per_pixel_rate=True,
            shared=("ln_gain",),
        )


def test_a_stack_of_no_frames_is_one_line(tmp_path, capsys):
    path = tmp_path / "darks-300x.npy"
    np.save(path, np.zeros((0, 4, 4), np.uint16))
    assert cli.main(["gain-check", str(path), "--e-per-adu", "3.9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"'{path}': holds no frames" in err, err


def test_darks_that_record_no_set_point_ask_for_one(tmp_path, capsys):
    path = tmp_path / "darks.npy"
    np.save(path, np.zeros((5, 4, 4), np.uint16))
    assert cli.main(["gain-check", str(path), "--e-per-adu", "3.9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "record no EM gain set-point" in err and "None" not in err
