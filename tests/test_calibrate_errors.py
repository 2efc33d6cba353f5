"""Bad input to the main job: clear one-line errors, flagged pixels, never a crash."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import tifffile

from emccdcal import _xp, calibrate, cli
from emccdcal.errors import MethodError, OptionError
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    base = tmp_path_factory.mktemp("errors")
    gs = simulate_gain_series(base / "gs", rows=6, cols=6, frames=1000, seed=3)
    adu = simulate_intensity_series(
        base / "adu", rows=6, cols=6, frames=1000, seed=4, levels=(2000, 8000)
    )
    return gs, adu


def _edit(manifest, tmp_path, old, new, name="edited.toml"):
    text = manifest.read_text()
    assert old in text
    path = manifest.parent / name
    path.write_text(text.replace(old, new))
    return path


def test_gain_series_needs_two_setpoints(series, tmp_path):
    gs, _ = series
    text = gs.manifest.read_text()
    one = text.split("[[acquisition]]")
    path = gs.manifest.parent / "one.toml"
    path.write_text(one[0] + "[[acquisition]]" + one[1])  # the 1x acquisition only
    with pytest.raises(MethodError, match="at least two set-points"):
        calibrate(path, "gs")


def test_gs_without_1x_suggests_gs_no1x(series):
    gs, _ = series
    text = gs.manifest.read_text()
    parts = text.split("[[acquisition]]")
    path = gs.manifest.parent / "no1x.toml"
    path.write_text(parts[0] + "".join("[[acquisition]]" + p for p in parts[2:]))
    with pytest.raises(MethodError, match="gs-no1x"):
        calibrate(path, "gs")
    assert calibrate(path, "gs-no1x").em_gain.shape[0] == 4


def test_is_adu_refuses_em_data(series):
    gs, _ = series
    with pytest.raises(MethodError, match="1x .*only.*5x"):
        calibrate(gs.manifest, "is-adu")


@pytest.mark.parametrize("method", ["gs", "gs-no1x", "gs-hierarchical", "is-gain", "mv-gain"])
def test_gain_methods_need_e_per_adu(series, tmp_path, method):
    gs, _ = series
    path = _edit(gs.manifest, tmp_path, "e_per_adu = 3.859", "", name="nophi.toml")
    with pytest.raises(MethodError, match="e_per_adu"):
        calibrate(path, method)


def test_unknown_method(series):
    gs, _ = series
    with pytest.raises(MethodError, match="unknown method 'gs2'"):
        calibrate(gs.manifest, "gs2")


@pytest.mark.parametrize(
    "method,options,message",
    [
        ("gs", {"mu_sd": 4.0}, "gs takes no options"),
        (
            "gs-hierarchical",
            {"mu_sdev": 4.0},
            "unknown gs-hierarchical option.*'mu_sdev'.*known: mu_sd",
        ),
        (
            "gs-hierarchical",
            {"sigma_sd": -1.0},
            "sigma_sd must be a positive number of photoelectrons",
        ),
        ("gs-hierarchical", {"mu_sd": "wide"}, "mu_sd must be a positive number"),
        ("gs-hierarchical", {"centre": "pixel"}, "unknown hierarchical centre 'pixel'"),
    ],
)
def test_bad_method_options(series, method, options, message):
    gs, _ = series
    with pytest.raises(MethodError, match=message):
        calibrate(gs.manifest, method, options=options)


@pytest.mark.slow
def test_cli_hyperprior_options_are_used_and_recorded(series, tmp_path):
    import json

    from emccdcal import result

    gs, _ = series
    out = tmp_path / "hier"
    argv = [
        "calibrate",
        str(gs.manifest),
        "-m",
        "gs-hierarchical",
        "-o",
        str(out),
        "--quiet",
        "--no-checks",
        "--mu-sd",
        "5",
        "--sigma-sd",
        "2.5",
        "--prior-centre",
        "setpoint",
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert cli.main(argv) == 0
    ds = result.load(out)
    assert json.loads(ds.attrs["options"]) == {"mu_sd": 5.0, "sigma_sd": 2.5, "centre": "setpoint"}
    # a tighter σ_E prior pools harder: the set-points' E spread less about μ than by default
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default = calibrate(gs.manifest, "gs-hierarchical", checks=False)
    assert float(ds.hyper_sd_photoelectrons.median()) < float(
        default.hyper_sd_photoelectrons.median()
    )
    assert cli.main(argv[:-6] + ["-m", "gs", "--mu-sd", "5"]) == 2  # gs takes no hyperprior


def test_cli_errors_are_one_line_exit_2(series, tmp_path, capsys):
    gs, _ = series
    code = cli.main(["calibrate", str(tmp_path / "missing.toml"), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "missing.toml" in err
    code = cli.main(
        ["calibrate", str(gs.manifest), "--method", "is-adu", "-o", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "is-adu" in err
    assert cli.main(["calibrate", str(gs.manifest), "--method", "nonsense", "-o", "x"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_saturated_frames_are_excluded_counted_and_warned(tmp_path):
    # A 15-bit ADC saturates part of the 300x data (mean ≈ 29 000 ADU, SD ≈ 2 100 ADU).
    gs = simulate_gain_series(
        tmp_path / "sat", rows=4, cols=4, frames=2000, seed=5, adc_bits=15, setpoints=(1, 25, 300)
    )
    with pytest.warns(UserWarning, match="ADC maximum"):
        ds = calibrate(gs.manifest, "gs")
    n_sat = ds.n_saturated.sel(setpoint=300).values
    assert n_sat.sum() > 0 and ds.n_saturated.sel(setpoint=1).values.sum() == 0
    assert bool(ds.converged.all())


def test_a_pixel_that_cannot_converge_is_flagged(series, tmp_path):
    gs, _ = series
    # Make pixel (2, 3) of the 25x stack constant at its offset: no signal, no noise.
    src = gs.outdir / "gain-GS" / "25x-gain.tif"
    data = tifffile.imread(src)
    data[:, 2, 3] = int(round(float(np.median(data[:, 0, 0])) / 10))
    bad = tmp_path / "25x-bad.tif"
    tifffile.imwrite(bad, data, photometric="minisblack")
    path = _edit(
        gs.manifest,
        tmp_path,
        'frames = "gain-GS/25x-gain.tif"',
        f'frames = "{bad}"',
        name="bad.toml",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = calibrate(path, "gs")
    assert not bool(ds.converged.values[2, 3])
    others = np.ones(ds.converged.shape, bool)
    others[2, 3] = False
    assert bool(ds.converged.values[others].all())


def test_a_scheduler_that_is_no_address_is_one_line(series):
    """A word where a Dask scheduler's address belongs is one clear error, not a
    traceback from inside the client."""
    pytest.importorskip("distributed")
    gs, _ = series
    with pytest.raises(
        OptionError,
        match=r"scheduler 'synchronous': no Dask scheduler "
        r"reached .*tcp://HOST:PORT",
    ):
        calibrate(gs.manifest, "gs", scheduler="synchronous")
    with pytest.raises(OptionError, match=r"scheduler 'tcp://127.0.0.1:9': no Dask"):
        calibrate(gs.manifest, "gs", scheduler="tcp://127.0.0.1:9")  # nobody listens
    # and nothing is left behind: no half-made client as the process's default, which
    # later Dask-aware writes (xarray's NetCDF locks) would try to reach
    import dask
    from distributed import default_client

    with pytest.raises(ValueError, match="No clients found"):
        default_client()
    assert dask.config.get("scheduler", None) is None


def test_a_device_that_is_not_there_is_one_line(series):
    """An unknown device, or a GPU that neither CuPy nor PyTorch finds, is one clear error
    before anything is read."""
    gs, _ = series
    with pytest.raises(OptionError, match="device 'tpu': expected one of cpu, cuda"):
        calibrate(gs.manifest, "gs", device="tpu")
    try:
        _xp.resolve("cuda")
    except OptionError as exc:
        with pytest.raises(OptionError, match="device 'cuda': no GPU found"):
            calibrate(gs.manifest, "gs", device="cuda")
        assert "\n" not in str(exc)


def test_blocks_on_a_gpu_fill_a_share_of_its_free_memory():
    """On a GPU the default block grows with the card's free memory (a quarter of it,
    at most 8192 pixels, tiles holding whole blocks); the CPU's defaults and a caller's
    own block size stand."""
    from emccdcal.calibration import DEFAULT_BLOCK
    from emccdcal.calibration.api import _blocks_for

    assert DEFAULT_BLOCK == 128
    assert _blocks_for(None, 128, 1024) == (128, 1024)  # the CPU
    assert _blocks_for(80 * 2**30, 128, 1024) == (1280, 1280)  # 20 GiB / 16 MiB
    assert _blocks_for(2**40, 128, 1024) == (8192, 8192)  # capped
    assert _blocks_for(2**30, 128, 1024) == (128, 1024)  # a small card
    assert _blocks_for(80 * 2**30, 64, 1024) == (64, 1024)  # the caller's choice


def test_every_verb_with_a_device_refuses_one_that_is_not_there(series):
    """Every verb that offers ``--device`` (found from the parsers) refuses an unknown
    device with one line before any work, through the same check; and a GPU neither CuPy
    nor PyTorch finds the same way."""
    from emccdcal.acquire.plan import plan
    from emccdcal.fit.darkgain import check_gain
    from emccdcal import sample_posterior

    gs, _ = series
    calls = {
        "calibrate": lambda device: calibrate(gs.manifest, "gs", device=device),
        "posterior": lambda device: sample_posterior(gs.manifest, "gs", [(0, 0)], device=device),
        "plan": lambda device: plan(e_per_adu=3.859, read_noise=15.5, offset=500.0, device=device),
        "gain-check": lambda device: check_gain([np.zeros((10, 2, 2))], 3.859, device=device),
    }
    offering = set()
    for verb in cli.VERBS:
        sub = cli.build_parser(verb)._subparsers._group_actions[0].choices[verb]
        if any("--device" in a.option_strings for a in sub._actions):
            offering.add(verb)
    assert offering == set(calls)
    try:
        _xp.resolve("cuda")
        absent = ["tpu"]
    except OptionError:
        absent = ["tpu", "cuda"]
    for verb, call in calls.items():
        for device in absent:
            with pytest.raises(OptionError, match=f"device '{device}'") as err:
                call(device)
            assert "\n" not in str(err.value), verb


# --- a result that misfits is never a success ---------------------------------------------


def _small_series(tmp_path, frames=1000, **kw):
    """A 4 x 4 px gain series at 1x, 100x and 300x (the re-audit's size)."""
    return simulate_gain_series(
        tmp_path / "gs",
        rows=4,
        cols=4,
        frames=frames,
        seed=3,
        setpoints=(1, 100, 300),
        progress=False,
        **kw,
    )


def _dark_manifest(sim) -> str:
    """The simulated series' manifest with its dark stacks instead of their maps."""
    import re

    text = sim.manifest.read_text()
    text = re.sub(r"^(offset|read_noise|dark_frames) = .*\n", "", text, flags=re.M)
    return re.sub(r'^# dark = ("[^"]+").*$', r"dark = \1", text, flags=re.M)


@pytest.mark.slow
@pytest.mark.parametrize("cic", [0.0, 0.05], ids=["no-cic", "cic"])
def test_a_byte_swapped_dark_is_refused_naming_its_acquisition(tmp_path, capsys, cic):
    """A 300x dark stack read with the wrong byte order (its counts spread over the whole
    16-bit range): refused in one line naming the file and the acquisition, before any
    fit of it (such a dark's noise-model fit ran for minutes, gigabytes deep)."""
    sim = _small_series(tmp_path, cic=cic)
    dark = sim.manifest.parent / "gain-GS/300x-gain_no-signal.tif"
    tifffile.imwrite(dark, tifffile.imread(dark).byteswap())
    manifest = sim.manifest.parent / "dark.toml"
    manifest.write_text(_dark_manifest(sim))
    import unittest.mock

    from emccdcal.data import dark as dark_module

    real_fit = dark_module.fit_dark

    def fit_dark(stack, **kw):  # decided by what ran: the sound 100x dark is fitted only
        assert np.median(stack) < 5000, "the byte-swapped dark was fitted"
        return real_fit(stack, **kw)

    with unittest.mock.patch.object(dark_module, "fit_dark", fit_dark):
        code = cli.main(["calibrate", str(manifest), "-m", "gs", "-o", str(tmp_path / "o"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "acquisition 3" in err and "300x-gain_no-signal.tif" in err and "byte-swapped" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_an_acquisition_the_model_misfits_at_most_pixels_ends_with_exit_1(tmp_path, capsys):
    """The gamma register on an exact register's low gains, 5000 frames: the 2x
    acquisition misfits at most pixels. The command writes the result but ends with exit
    1, naming the acquisition and what to check; the exact register's fit stands."""
    sim = simulate_gain_series(
        tmp_path / "gs",
        rows=4,
        cols=4,
        frames=5000,
        seed=4,
        setpoints=(1, 2, 5, 100),
        progress=False,
    )
    base = ["calibrate", str(sim.manifest), "-m", "gs", "-q", "-o"]
    code = cli.main([*base, str(tmp_path / "gamma"), "--em-model", "gamma"])
    err = capsys.readouterr().err.splitlines()
    assert code == 1
    assert err[-1].startswith("emccdcal calibrate: the calibration is doubtful: set-point 2x:")
    assert "check that acquisition's dark or maps" in err[-1]
    assert not any("stand" in line for line in err)
    from emccdcal import load_result

    assert load_result(tmp_path / "gamma").attrs["verdict"].startswith("doubtful: set-point 2x")
    assert cli.main([*base, str(tmp_path / "cascade")]) == 0
    assert load_result(tmp_path / "cascade").attrs["verdict"] == "stands"


@pytest.mark.slow
def test_a_run_where_no_pixel_converged_leaves_nothing_to_resume(tmp_path, capsys):
    """Maps of the 300x acquisition that no data fit (a misread dark's offset, above
    every count, and read noise): every pixel fails. Nothing is kept as an 'interrupted
    run', the output folder the run made is gone, and the rerun says the same thing
    again. (Maps that are merely wrong, an offset of 13852 ADU under counts of ~25700,
    give a maximum the fit reaches and the goodness of fit rejects: a doubtful run.)"""
    sim = _small_series(tmp_path)
    folder = sim.manifest.parent / "gain-GS"
    tifffile.imwrite(folder / "300x-gain_no-signal_S0.tif", np.full((4, 4), 60000.0, np.float32))
    tifffile.imwrite(folder / "300x-gain_no-signal_sigma.tif", np.full((4, 4), 3968.0, np.float32))
    mine = tmp_path / "mine"
    mine.mkdir()  # a folder of the user's: kept
    for out in (tmp_path / "out", tmp_path / "out", mine):
        argv = ["calibrate", str(sim.manifest), "-m", "gs", "-o", str(out), "-q"]
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert "0 of 16 pixels converged" in err and "interrupted" not in err
    assert not (tmp_path / "out").exists() and mine.is_dir() and not list(mine.iterdir())


@pytest.mark.slow
def test_a_saturated_set_point_is_named_as_saturated(tmp_path, capsys):
    sim = _small_series(tmp_path, frames=300)
    frames = sim.manifest.parent / "gain-GS/300x-gain.tif"
    tifffile.imwrite(frames, np.full_like(tifffile.imread(frames), 65535))
    argv = ["calibrate", str(sim.manifest), "-m", "gs", "-o", str(tmp_path / "o"), "-q"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "saturated) in set-point 300x (16 of 16 pixels)" in err and err.count("\n") == 1
