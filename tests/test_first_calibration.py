"""A first calibration with no expert at hand, on the published ProEM folders copied as
they are (no manifest written by hand): the path of docs/first-calibration.md."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
import tifffile

from emccdcal import cli, result

pytestmark = pytest.mark.real_data


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_from_camera_folders_to_photons_in_picasso(real_data, tmp_path, capsys):
    for name in ("ADU", "gain-GS"):
        shutil.copytree(real_data / name, tmp_path / name)
    adu, gs = tmp_path / "ADU", tmp_path / "gain-GS"
    # 1. scan: each folder becomes a manifest
    assert _run(capsys, "scan", adu)[0] == 0
    assert _run(capsys, "scan", gs)[0] == 0
    # 2. phi from the 1x intensity series
    code, out, _ = _run(
        capsys,
        "calibrate",
        adu / "manifest.toml",
        "--method",
        "is-adu",
        "-o",
        tmp_path / "out-adu",
        "-q",
    )
    assert code == 0
    # 3. the gains with that phi, under the default register model: no misfit warning
    code, out, err = _run(
        capsys,
        "calibrate",
        gs / "manifest.toml",
        "--method",
        "gs",
        "--e-per-adu",
        tmp_path / "out-adu",
        "-o",
        tmp_path / "out-gs",
    )
    assert code == 0
    assert "method gs (cascade register)" in out
    assert "register length: 536 stages (default)" in out
    assert "misfit" not in err
    ds = result.load(tmp_path / "out-gs")
    gain_300 = float(np.median(ds.em_gain.sel(setpoint=300).values))
    assert 255 < gain_300 < 270  # the paper's 261.6 under its gamma model, +0.2 % exact
    # 4. export to Picasso at the movies' set-point
    assert (
        _run(
            capsys,
            "export",
            tmp_path / "out-gs",
            "--to",
            "picasso",
            "--setpoint",
            300,
            "-o",
            tmp_path / "picasso",
            "-q",
        )[0]
        == 0
    )
    config = tmp_path / "picasso" / "picasso-config.yaml"
    # 5. the audit of that export agrees ...
    code, out, _ = _run(
        capsys, "audit", config, "--calibration", tmp_path / "out-gs", "--setpoint", 300
    )
    assert code == 0 and "  OK: photons within 2 %" in out
    # ... and of a config with its Sensitivity 10 % off: exit 1, the field and the bias
    text = config.read_text()
    sens = float(re.search(r'"Sensitivity": ([0-9.]+)', text).group(1))
    off = tmp_path / "config-off.yaml"
    off.write_text(text.replace(f'"Sensitivity": {sens}', f'"Sensitivity": {sens * 1.1:.4f}'))
    code, out, _ = _run(
        capsys, "audit", off, "--calibration", tmp_path / "out-gs", "--setpoint", 300
    )
    assert code == 1
    assert re.search(r"OFF: photons \+10\.0 % \(most of it Sensitivity\)", out)
    # 6. photons of a movie at 300x (the gain series' own stack stands in for one)
    code, out, _ = _run(
        capsys,
        "apply",
        tmp_path / "out-gs",
        gs / "300x-gain.tif",
        "--setpoint",
        300,
        "--qe",
        0.9,
        "-o",
        tmp_path / "photons.tif",
        "-q",
    )
    assert code == 0
    photons = tifffile.imread(tmp_path / "photons.tif")
    raw = tifffile.imread(gs / "300x-gain.tif").astype(float)
    assert photons.shape == raw.shape  # an image series, not RGB
    # (S - S0)·phi/g/QE; the scene's ~371 e- per pixel and frame, /0.9
    assert np.median(photons) == pytest.approx(np.median(ds.photoelectrons.values) / 0.9, rel=0.02)


NOTEBOOK = """
import collections, json, sys, warnings
import emccdcal

calls = []
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for call in (
        lambda: emccdcal.calibrate("ADU/manifest.toml", "is-adu", progress=False),
        lambda: emccdcal.calibrate("gain-GS/manifest.toml", e_per_adu=phi, progress=False),
        lambda: emccdcal.calibrate(
            "gain-GS/manifest.toml", "gs-hierarchical", e_per_adu=phi, progress=False
        ),
    ):
        before = len(caught)
        ds = call()
        if ds.attrs["method"] == "is-adu":
            phi = ds
        calls.append({
            "kinds": [w.category.__name__ for w in caught[before:]],
            "all_ours": all(issubclass(w.category, emccdcal.EmccdcalWarning)
                            for w in caught[before:]),
            "kept": len(ds.attrs["warnings"]),
            "verdict": ds.attrs["verdict"],
        })
warnings.simplefilter("ignore", emccdcal.EmccdcalWarning)
emccdcal.calibrate("gain-GS/manifest.toml", e_per_adu=phi, progress=False)
print(json.dumps(calls))
"""


def test_a_notebook_sees_one_warning_of_each_kind_and_can_silence_them_all(real_data, tmp_path):
    """A fresh interpreter calibrates the real series as a notebook would: each call
    issues at most one warning of each kind (every one in full in the result), all of
    them emccdcal's; one filter on ``EmccdcalWarning`` silences the package."""
    import json
    import subprocess
    import sys

    for name in ("ADU", "gain-GS"):
        shutil.copytree(real_data / name, tmp_path / name)
        assert cli.main(["scan", str(tmp_path / name), "-q"]) == 0
    done = subprocess.run(
        [sys.executable, "-c", NOTEBOOK], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    calls = json.loads(done.stdout.strip().splitlines()[-1])
    for call in calls:
        assert call["all_ours"] and call["verdict"].startswith("stands"), call
        assert len(call["kinds"]) == len(set(call["kinds"])), call  # one per kind
        assert call["kept"] >= len(call["kinds"])
    assert sum(c["kept"] > len(c["kinds"]) for c in calls), calls  # some were merged
    # the last call, silenced by the one filter, printed no warning (the others recorded)
    assert "Warning: " not in done.stderr, done.stderr
