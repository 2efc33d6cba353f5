"""What the user said, checked against what the data show: set-points, copies, 1× labels,
offsets and the ADC range."""

from __future__ import annotations

import re
import shutil
import warnings

import numpy as np
import pytest
from conftest import quiet

from emccdcal import calibrate, cli
from emccdcal.data.manifest import read_manifest
from emccdcal.data.quality import check_manifest
from emccdcal.errors import ManifestError, OptionError
from emccdcal.simulate.camera import simulate_frames
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series


@pytest.fixture(scope="module")
def gain_series(tmp_path_factory):
    d = tmp_path_factory.mktemp("plaus")
    # enough pixel-frames to see a third cumulant: its relative error per pixel is
    # about √(6/frames) / skewness, 0.4 here (E = 370 e⁻), so 0.05 over 64 pixels
    return simulate_gain_series(d / "gs", rows=8, cols=8, frames=3000, seed=7, setpoints=(1, 5, 25))


def _edited(series, name, edit):
    path = series.manifest.with_name(name)
    path.write_text(edit(series.manifest.read_text()))
    return path


def test_swapped_setpoints_are_named(gain_series):
    # the 5x and 25x stacks listed under each other's set-point: the gains fall
    def swap(text):
        text = text.replace('"gain-GS/5x-gain', '"gain-GS/TMP').replace(
            '"gain-GS/25x-gain', '"gain-GS/5x-gain'
        )
        return text.replace('"gain-GS/TMP', '"gain-GS/25x-gain')

    manifest = _edited(gain_series, "swapped.toml", swap)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = calibrate(manifest, "gs")
    falls = [str(w.message) for w in caught if "measured EM gain falls" in str(w.message)]
    assert len(falls) == 1, [str(w.message) for w in caught]
    assert re.search(r"falls from 2\d\.\d+ at set-point 5 to 4\.\d+ at set-point 25", falls[0])
    assert "swapped" in falls[0] and "swapped.toml" in falls[0]
    assert any("measured EM gain falls" in w for w in ds.attrs["warnings"])
    # in the right order: no such warning
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        calibrate(gain_series.manifest, "gs")
    assert not any("falls" in str(w.message) for w in caught)


def test_one_stack_under_two_setpoints_is_refused(gain_series):
    folder = gain_series.manifest.parent / "gain-GS"
    shutil.copy(folder / "25x-gain.tif", folder / "copy.tif")
    manifest = _edited(
        gain_series,
        "copied.toml",
        lambda t: t.replace('"gain-GS/5x-gain.tif"', '"gain-GS/copy.tif"'),
    )
    with pytest.raises(
        ManifestError,
        match=r"acquisition 3 .*hold the same data as "
        r"acquisition 2's .*copy\.tif.*two set-points",
    ):
        quiet(read_manifest, manifest)


def test_em_gain_data_labelled_1x_is_found(gain_series):
    # the 25x stack labelled as 1x: its cumulants say multiplied
    manifest = _edited(
        gain_series,
        "mislabelled.toml",
        lambda t: t.replace('"gain-GS/1x-gain.tif"', '"gain-GS/25x-gain.tif"').replace(
            'frames = "gain-GS/25x-gain.tif"\nem_gain_setpoint = 25',
            'frames = "gain-GS/5x-gain.tif"\nem_gain_setpoint = 25',
        ),
    )
    text = manifest.read_text()
    text = re.sub(
        r'\[\[acquisition\]\]\nname = "5x".*?(?=\[\[acquisition\]\])', "", text, flags=re.S
    )
    manifest.write_text(text)
    report = quiet(check_manifest, quiet(read_manifest, manifest))
    one_x = report["acquisitions"]["1x"]["multiplication"]
    assert one_x["multiplied"] and one_x["R"] == pytest.approx(1.5, abs=0.1)
    assert any(
        "look EM-multiplied" in w and w.startswith("1x (set-point 1)") for w in report["warnings"]
    )
    # true 1x data: R = 1 within its error, no finding
    honest = quiet(check_manifest, quiet(read_manifest, gain_series.manifest))
    r = honest["acquisitions"]["1x"]["multiplication"]
    assert not r["multiplied"] and abs(r["R"] - 1) < 4 * r["R_se"] + 0.1
    assert honest["acquisitions"]["5x"]["multiplication"] is None  # only at set-point 1


def test_cumulant_ratio_is_one_and_one_and_a_half(tmp_path):
    # the ratio does not depend on E, g or φ: 1 without multiplication, 1.5 with it
    from emccdcal.data.quality import StackSummary

    for gain, want in ((1.0, 1.0), (40.0, 1.5)):
        for phi in (1.0, 8.0):
            frames = simulate_frames(
                200.0,
                em_gain=gain,
                e_per_adu=phi,
                offset=500.0,
                read_noise=3.0,
                frames=4000,
                rows=4,
                cols=4,
                seed=3,
            )
            s = StackSummary.of(frames, 65535, third=True)
            r = s.multiplication_ratio(np.full((4, 4), 500.0), np.full((4, 4), 3.0))
            assert r["R"] == pytest.approx(want, abs=5 * r["R_se"] + 0.02), (gain, phi)


def test_offset_above_the_data_is_a_finding(gain_series):
    manifest = _edited(
        gain_series,
        "offset-high.toml",
        lambda t: re.sub(r'offset = "[^"]*"', "offset = 20000.0", t),
    )
    report = quiet(check_manifest, quiet(read_manifest, manifest))
    assert all(a["offset"]["above_data"] for a in report["acquisitions"].values())
    assert any(
        "offset map lies above the mean count of 64 of 64 pixels" in w for w in report["warnings"]
    )
    assert not any(
        a["offset"]["above_data"]
        for a in quiet(check_manifest, quiet(read_manifest, gain_series.manifest))[
            "acquisitions"
        ].values()
    )


def test_offset_beyond_the_adc_range_is_refused(tmp_path, capsys):
    with pytest.raises(
        OptionError,
        match=r"offset 587\.7 ADU is at or above the ADC maximum "
        r"255 ADU of 8 bits",
    ):
        simulate_frames(100.0, offset=587.7, adc_bits=8, frames=10, rows=2, cols=2, seed=1)
    assert (
        cli.main(
            [
                "simulate",
                "gain-series",
                str(tmp_path / "s"),
                "--adc-bits",
                "8",
                "--frames",
                "10",
                "--rows",
                "2",
                "--cols",
                "2",
            ]
        )
        == 2
    )
    assert "at or above the ADC maximum 255" in capsys.readouterr().err


def test_intensity_series_with_gain_is_not_misread_as_1x(tmp_path):
    # an honest 1x intensity series gets no multiplication finding
    adu = simulate_intensity_series(tmp_path / "adu", rows=4, cols=4, frames=1000, seed=2)
    report = quiet(check_manifest, quiet(read_manifest, adu.manifest))
    assert not any(a["multiplication"]["multiplied"] for a in report["acquisitions"].values())


def test_offset_of_zero_is_found_by_the_photon_transfer(tmp_path):
    # 1x levels: the excess variance reaches zero where the offset truly is
    adu = simulate_intensity_series(tmp_path / "adu", rows=8, cols=8, frames=2000, seed=2)
    honest = quiet(check_manifest, quiet(read_manifest, adu.manifest))
    t = honest["offset_from_transfer"]
    assert t["n_levels"] == 6 and not t["off"] and abs(t["shift"]) < 5 * t["shift_se"]
    zero = adu.manifest.with_name("zero.toml")
    zero.write_text(re.sub(r'offset = "[^"]*"', "offset = 0.0", adu.manifest.read_text()))
    report = quiet(check_manifest, quiet(read_manifest, zero))
    t = report["offset_from_transfer"]
    truth = float(np.mean(quiet(read_manifest, adu.manifest).acquisitions[0].offset))
    assert t["off"] and t["shift"] == pytest.approx(truth, abs=5 * t["shift_se"])
    assert any(
        w.startswith("set-point 1: the photon transfer of its 6 levels")
        and "offsets are off by about that much" in w
        for w in report["warnings"]
    )
