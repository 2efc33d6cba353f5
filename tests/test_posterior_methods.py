"""Posterior sampling for every likelihood method, on small simulated series, and the
successful CLI path (the real-data criteria are in ``test_posterior.py``)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import emccdcal

from emccdcal import calibrate, cli
from emccdcal.fit import posterior
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

pytestmark = pytest.mark.slow  # about 35 s: every likelihood method sampled to convergence

PIXEL = (0, 1)
#: The register model of the sampler-against-engine tests: either model tests the sampler,
#: and the gamma model's evaluations cost less; the CLI test runs the default, the cascade.
MODEL = "gamma"
#: Effective samples asked of the chains.
MIN_ESS = 400


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    base = tmp_path_factory.mktemp("series")
    # 60 e- (not the paper's 370): the likelihood's cost is the FFT windows that cover the
    # counts, and what is tested, the sampler against the engine, does not depend on it
    gs = simulate_gain_series(
        base / "gs",
        rows=2,
        cols=2,
        frames=1000,
        setpoints=(1, 25, 300),
        photoelectrons=60.0,
        seed=21,
        progress=False,
    )
    isg = simulate_intensity_series(
        base / "isg",
        rows=2,
        cols=2,
        frames=1000,
        setpoint=25,
        em_gain=22.95,
        levels=(50, 200, 800),
        seed=22,
        progress=False,
    )
    return {"gs": gs.manifest, "isg": isg.manifest}


def _engine(manifest, method):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(
            manifest,
            method,
            checks=False,
            map_errors=False,  # as the posterior
            em_model=MODEL,
        )


@pytest.mark.parametrize(
    "method, source", [("is-gain", "isg"), ("gs-no1x", "gs"), ("gs-hierarchical", "gs")]
)
def test_posterior_agrees_with_the_engine(series, method, source):
    """Median within a quarter of a posterior SD of the estimate, SD within 20 % of the SE
    (the hierarchical MAP within half an SD, and not by SD: its SE is a sandwich, not a
    posterior SD)."""
    manifest = series[source]
    # an effective sample of 400 puts the median within 0.06 posterior SD and the SD
    # within 4 % (Monte Carlo errors), far inside what is asserted
    ds = emccdcal.sample_posterior(
        manifest, method, [PIXEL], seed=1, em_model=MODEL, n_steps=500, min_ess=MIN_ESS
    )
    engine = _engine(manifest, method)
    assert ds.attrs["em_model"] == engine.attrs["em_model"] == MODEL
    assert np.all(ds.ess.values >= MIN_ESS)
    names = [str(p) for p in ds.parameter.values]
    gains = [n for n in names if n.startswith("em_gain")]
    assert gains
    for name in gains:
        q = ds.sel(parameter=name).isel(pixel=0)
        # "em_gain[300x]", or plain "em_gain" where the method has one set-point
        setpoint = (
            float(name.split("[")[1].rstrip("x]"))
            if "[" in name
            else float(engine.setpoint.values[-1])
        )
        est = float(engine.em_gain.sel(setpoint=setpoint).values[PIXEL])
        se = float(engine.em_gain_se.sel(setpoint=setpoint).values[PIXEL])
        assert float(q.mle) == pytest.approx(est, rel=1e-5)
        if method == "gs-hierarchical":  # a MAP: the mode of a skewed posterior, not its median
            assert abs(float(q["median"]) - est) < 0.5 * float(q.sd), name
        else:
            assert abs(float(q["median"]) - est) < 0.25 * float(q.sd), name
            assert abs(float(q.sd) / se - 1) < 0.2, name


def test_cli_writes_the_posterior(tmp_path, capsys):
    # a small series (the cost of a step is the FFT windows that cover its counts) under
    # the exact register (the default model, whose choice calibrate's tests and
    # choose_em_model's examples show), 64 stages long to keep its sampling short
    gs = simulate_gain_series(
        tmp_path / "gs",
        rows=2,
        cols=2,
        frames=300,
        setpoints=(1, 5, 25),
        photoelectrons=50.0,
        seed=23,
        progress=False,
    )
    out = tmp_path / "post"
    code = cli.main(
        [
            "posterior",
            str(gs.manifest),
            "--method",
            "gs",
            "--pixel",
            "1,0",
            "--stages",
            "64",
            "-o",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    summary = json.loads((out / posterior.SUMMARY_FILE).read_text())
    assert summary["method"] == "gs"
    assert summary["em_model"] == "cascade" and summary["register_stages"] == 64
    assert summary["register_stages_source"] == "given"
    (px,) = summary["pixels"]
    assert (px["row"], px["col"]) == (1, 0)
    assert set(px["parameters"]) == {"photoelectrons", "em_gain[5x]", "em_gain[25x]"}
    assert px["parameters"]["em_gain[25x]"]["ess"] >= posterior.DEFAULT_MIN_ESS
    assert (out / posterior.POSTERIOR_FILE).is_file() and (out / "posterior_1_0.png").is_file()
