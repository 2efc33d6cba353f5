"""Posterior sampling (emccdcal.posterior) on the real ProEM ADU series, and its refusals."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

import emccdcal
from conftest import write_real_manifest

from emccdcal._util import parse_pixel
from emccdcal.errors import MethodError, NotConvergedError
from emccdcal.fit import posterior

needs_real = pytest.mark.real_data


@pytest.fixture(scope="module")
def adu_manifest(real_data, tmp_path_factory):
    return write_real_manifest(tmp_path_factory.mktemp("adu"), "adu")


@pytest.fixture(scope="module")
def adu_run(adu_manifest, tmp_path_factory):
    """One converged is-adu posterior of pixel (1, 1), written to disk (about 20 s)."""
    from emccdcal import calibrate

    out = tmp_path_factory.mktemp("post")
    ds = emccdcal.sample_posterior(adu_manifest, "is-adu", [(1, 1)], seed=0, out=out)
    engine = calibrate(adu_manifest, "is-adu")
    return ds, engine, out


# --------------------------------------------------------------------------------------
# The done-when criteria on the real data
# --------------------------------------------------------------------------------------
@pytest.mark.slow
@needs_real
def test_adu_pixel_posterior_matches_engine(adu_run):
    ds, engine, _ = adu_run
    phi = ds.sel(parameter="e_per_adu").isel(pixel=0)
    est = float(engine.e_per_adu.values[1, 1])
    se = float(engine.e_per_adu_se.values[1, 1])
    assert abs(float(phi["median"]) / est - 1) < 0.01
    assert abs(float(phi.sd) / se - 1) < 0.15
    assert float(phi.ess) >= 1000
    # The engine run on the pixel alone is the same fit as on the whole array.
    assert float(phi.mle) == pytest.approx(est, rel=1e-6)
    assert float(phi.mle_se) == pytest.approx(se, rel=1e-4)
    assert ds.units.sel(parameter="e_per_adu").item() == "e-/ADU"


@pytest.mark.slow
@needs_real
def test_adu_pixel_diagnostics_meet_the_criteria(adu_run):
    ds, engine, _ = adu_run
    assert ds.parameter.values.tolist() == ["e_per_adu"] + [
        f"photoelectrons[L{i}]" for i in range(1, 7)
    ]
    assert np.all(ds.ess.values >= 1000)
    kept = ds.n_steps.values[0] - ds.burn.values[0]
    assert kept >= posterior.MIN_LENGTH_TAUS * ds.autocorr_time.values[0].max()
    assert posterior.ACCEPTANCE[0] <= float(ds.acceptance[0]) <= posterior.ACCEPTANCE[1]
    # Every E_i agrees with the engine as well (same model, a flat prior in log space).
    for i in range(6):
        pe = float(ds["median"].values[0, 1 + i])
        assert pe == pytest.approx(float(engine.photoelectrons.values[i, 1, 1]), rel=0.01)
    n = int(ds.n_draws[0])
    draws = ds.samples.values[0, :n]
    assert np.all(np.isfinite(draws)) and np.all(draws > 0)
    q = ds.sel(parameter="e_per_adu").isel(pixel=0)
    assert float(q.q025) < float(q.q16) < float(q["median"]) < float(q.q84) < float(q.q975)


@pytest.mark.slow
@needs_real
def test_outputs_are_written(adu_run):
    import xarray as xr

    ds, _, out = adu_run
    summary = json.loads((out / posterior.SUMMARY_FILE).read_text())
    assert summary["method"] == "is-adu" and summary["prior"] == "log-uniform"
    (px,) = summary["pixels"]
    assert (px["row"], px["col"]) == (1, 1)
    phi = px["parameters"]["e_per_adu"]
    for key in (
        "median",
        "sd",
        "q16",
        "q84",
        "q025",
        "q975",
        "ess",
        "autocorr_time",
        "acceptance",
        "mle",
        "mle_se",
    ):
        assert isinstance(phi[key], float), key
    assert phi["units"] == "e-/ADU"
    with xr.open_dataset(out / posterior.POSTERIOR_FILE, engine="h5netcdf") as back:
        np.testing.assert_array_equal(back.samples.values, ds.samples.values)
        assert back.units.values.tolist()[0] == "e-/ADU"
    from emccdcal.report.corner import write_corner_figures

    (png,) = write_corner_figures(ds, out)
    assert png == out / "posterior_1_1.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob("*.tmp"))  # atomic writes left no temporary files


# --------------------------------------------------------------------------------------
# Refusal of an unconverged chain
# --------------------------------------------------------------------------------------
@needs_real
def test_unconverged_chain_is_refused(adu_manifest):
    with pytest.raises(NotConvergedError) as err:
        emccdcal.sample_posterior(adu_manifest, "is-adu", [(0, 0)], n_steps=40, max_steps=60)
    msg = str(err.value)
    assert "\n" not in msg
    assert "not converged after 60 steps" in msg
    assert "max_steps" in msg and "walkers" in msg


@pytest.mark.slow
@needs_real
def test_refusal_is_reproducible_with_the_seed(adu_manifest):
    def message(seed):
        with pytest.raises(NotConvergedError) as err:
            emccdcal.sample_posterior(
                adu_manifest, "is-adu", [(2, 2)], n_steps=30, max_steps=30, seed=seed
            )
        return str(err.value)

    assert message(3) == message(3)
    assert message(3) != message(4)


@needs_real
def test_the_posterior_through_the_array_api_standard_is_numpys(adu_manifest):
    """Walkers whose likelihood is computed on array-api-strict arrays (a pretend device
    that refuses anything outside the standard) walk NumPy's chain: the same refusal,
    number for number."""
    pytest.importorskip("array_api_strict")

    def message(device):
        with pytest.raises(NotConvergedError) as err:
            emccdcal.sample_posterior(
                adu_manifest, "is-adu", [(2, 2)], n_steps=30, max_steps=30, seed=3, device=device
            )
        return str(err.value)

    assert message("array-api-strict") == message("cpu")


@needs_real
def test_cli_refusal_exit_code(adu_manifest, tmp_path, capsys):
    args = _parse(
        [
            "posterior",
            str(adu_manifest),
            "--method",
            "is-adu",
            "--pixel",
            "0,2",
            "-o",
            str(tmp_path / "o"),
            "--steps",
            "20",
            "--max-steps",
            "20",
            "--quiet",
        ]
    )
    assert args.func(args) == 1
    err = capsys.readouterr().err
    assert err.startswith("emccdcal posterior: refused:") and err.count("\n") == 1
    assert not (tmp_path / "o" / posterior.SUMMARY_FILE).exists()


# --------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------
@needs_real
@pytest.mark.parametrize("pixel", [(3, 0), (0, 3), (-1, 1)])
def test_pixel_outside_the_array(adu_manifest, pixel):
    with pytest.raises(ValueError, match=r"outside the array of shape 3x3"):
        emccdcal.sample_posterior(adu_manifest, "is-adu", [pixel])


@pytest.mark.parametrize("text", ["1;1", "a,b", "1,2,3", "1", "1.5,2", ""])
def test_malformed_pixel(text):
    with pytest.raises(ValueError, match=r"malformed pixel .*ROW,COL"):
        parse_pixel(text)


def test_parse_pixel():
    assert parse_pixel(" 2 , 0") == (2, 0)


@needs_real
@pytest.mark.parametrize(
    "method, kwargs, match",
    [
        ("gs", {"e_per_adu": 3.9}, "one acquisition per set-point"),
        ("is-gain", {}, "needs e_per_adu"),
        ("mv-adu", {}, "likelihood method"),
        ("bogus", {}, "likelihood method"),
    ],
)
def test_method_the_manifest_cannot_support(adu_manifest, method, kwargs, match):
    with pytest.raises(MethodError, match=match):
        emccdcal.sample_posterior(adu_manifest, method, [(1, 1)], **kwargs)


@needs_real
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_walkers": 10}, "n_walkers must be even and at least 14"),
        ({"n_walkers": 33}, "n_walkers must be even"),
        ({"prior": "jeffreys"}, "unknown prior"),
        ({"max_steps": 0}, "max_steps must be an integer"),
        ({"n_steps": 2.5}, "n_steps must be an integer"),
        ({"e_per_adu": -1.0}, "e_per_adu must be positive"),
    ],
)
def test_bad_options(adu_manifest, kwargs, match):
    with pytest.raises(ValueError, match=match):
        emccdcal.sample_posterior(adu_manifest, "is-adu", [(1, 1)], **kwargs)


@needs_real
def test_cli_bad_pixel_is_one_line_and_exit_2(adu_manifest, tmp_path, capsys):
    from emccdcal.cli import main

    for pixel, message in (
        ("1-1", "malformed pixel '1-1'"),
        ("9,9", "outside the array of shape 3x3"),
    ):
        code = main(
            [
                "posterior",
                str(adu_manifest),
                "--method",
                "is-adu",
                "--pixel",
                pixel,
                "-o",
                str(tmp_path),
            ]
        )
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def _parse(argv):
    from emccdcal.cli.posterior import add_parser

    parser = argparse.ArgumentParser(prog="emccdcal")
    add_parser(parser.add_subparsers(dest="verb"))
    return parser.parse_args(argv)
