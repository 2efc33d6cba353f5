"""``emccdcal scan``: camera sessions → manifests that calibrate as the hand-written ones."""

from __future__ import annotations

import re

import numpy as np
import pytest
import tifffile
from camera_files import write_micromanager_tiff, write_spe
from conftest import quiet

from emccdcal import calibrate, cli
from emccdcal.data.scan import scan
from emccdcal.errors import InputError
from emccdcal.simulate.series import simulate_gain_series


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("scan")
    return simulate_gain_series(
        d / "gs", rows=4, cols=5, frames=600, seed=21, setpoints=(1, 25, 300)
    )


def _session(series, folder, suffix, *, readout=lambda sp: 10.0):
    """The series' stacks (signal and darks) saved as a camera would, recording settings;
    names that do not say the set-point, so that only the files can."""
    folder.mkdir()
    for tif in sorted((series.manifest.parent / "gain-GS").glob("*x-gain*.tif")):
        data = tifffile.imread(tif)
        if data.ndim != 3:
            continue  # maps
        sp = float(re.match(r"(\d+)x", tif.name).group(1))
        kind = "dark" if "no-signal" in tif.name else "signal"
        name = folder / f"{kind}-{int(sp * 7)}{suffix}"  # not the set-point
        if suffix == ".spe":
            write_spe(name, data, em_gain=sp, speed_mhz=readout(sp))
        else:
            write_micromanager_tiff(name, data, em_gain=sp, readout=f"{readout(sp):.3f} MHz")
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".spe", ".ome.tif"])
def test_scanned_session_calibrates_as_the_written_manifest(series, tmp_path, suffix, capsys):
    folder = _session(series, tmp_path / "session", suffix)
    assert cli.main(["scan", str(folder)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("gain-series: 3 set-points (1, 25, 300); darks: 3 dark stack(s)\n")
    text = (folder / "manifest.toml").read_text()
    assert "set-points recorded in the files" in text and "adc_bits = 16" in text
    assert text.count("[[acquisition]]") == 3 and text.count("dark = ") == 3
    # φ is not in a camera's files: given, as the written manifest gives it
    scanned = quiet(calibrate, folder / "manifest.toml", "gs", e_per_adu=3.859)
    written = quiet(calibrate, series.manifest, "gs")
    # the same frames; the maps from the same darks (here reduced by the reader)
    np.testing.assert_allclose(scanned.em_gain.values, written.em_gain.values, rtol=1e-6)
    np.testing.assert_allclose(
        scanned.photoelectrons.values, written.photoelectrons.values, rtol=1e-6
    )
    # an existing manifest is kept unless told
    assert cli.main(["scan", str(folder)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err


def test_readout_rate_changing_mid_series_is_refused(series, tmp_path):
    folder = _session(
        series, tmp_path / "session", ".spe", readout=lambda sp: 5.0 if sp == 300 else 10.0
    )
    with pytest.raises(
        InputError,
        match=r"readout rate \(MHz\) 5(\.0)? in '.*-2100\.spe' "
        r"but 10(\.0)? in '.*': a series is taken with one",
    ):
        scan(folder)


def test_names_stand_in_for_missing_settings_and_say_so(series, tmp_path):
    # the simulator's own TIFFs record nothing: set-points and darks come from the names
    session = scan(series.manifest.parent / "gain-GS")
    assert [f.setpoint for f in session.signal] == [1, 25, 300]
    assert all(f.setpoint_rule == "name" for f in session.signal)
    assert any(r.startswith("set-points from the file names: ") for r in session.rules)
    out = tmp_path / "m.toml"
    from emccdcal.data.scan import write_manifest

    write_manifest(session, out)
    text = out.read_text()
    assert "# from the file name" in text and "adc_bits" in text
    ds = quiet(calibrate, out, "gs", e_per_adu=3.859)
    assert bool(ds.converged.all())


def test_sessions_that_cannot_be_scanned(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no stack of frames"):
        scan(empty)
    nameless = tmp_path / "nameless"
    nameless.mkdir()
    tifffile.imwrite(
        nameless / "stack.tif", np.zeros((3, 2, 2), np.uint16), photometric="minisblack"
    )
    with pytest.raises(InputError, match=r"stack\.tif': no EM gain set-point"):
        scan(nameless)
    nodark = tmp_path / "nodark"
    nodark.mkdir()
    tifffile.imwrite(nodark / "5x.tif", np.ones((3, 2, 2), np.uint16), photometric="minisblack")
    with pytest.raises(
        InputError,
        match=r"no dark at set-point 5: name a dark stack with its "
        r"set-point and 'dark' \(e\.g\. '5x-dark\.tif'\), or an offset and a "
        r"read-noise map \('5x_S0\.tif' and '5x_sigma\.tif'\); or write the "
        r"manifest by hand, each acquisition with dark = ",
    ):
        scan(nodark)
    # maps seen but not usable are named in that one message, each with its reason
    tifffile.imwrite(nodark / "5x_S0.tif", np.full((2, 2), 100, np.float32))
    tifffile.imwrite(nodark / "25x_sigma.tif", np.full((2, 2), 3, np.float32))
    tifffile.imwrite(nodark / "5x_sigma.tif", np.full((3, 3), 3, np.float32))
    with pytest.raises(
        InputError,
        match=r"seen and not used: 25x_sigma\.tif \(a map at "
        r"set-point 25, where no illuminated stack is\), 5x_sigma\.tif \(a 3 × "
        r"3 px map; the frames are 2 × 2 px\), 5x_S0\.tif \(no read-noise map "
        r"at set-point 5 to pair it with\)",
    ):
        scan(nodark)
    # a folder of sessions: the message names the subfolders to scan
    with pytest.raises(
        InputError,
        match=r"no stack of frames .*; its subfolders nameless, "
        r"nodark hold some: scan each",
    ):
        scan(tmp_path)


def test_dark_stacks_are_preferred_to_maps_and_the_maps_are_listed(series, tmp_path, capsys):
    # the simulator's folder holds both: each set-point's dark stack and its two maps
    folder = series.manifest.parent / "gain-GS"
    session = scan(folder)
    assert {sp: d.path.name for sp, d in session.darks.items()} == {
        1: "1x-gain_no-signal.tif",
        25: "25x-gain_no-signal.tif",
        300: "300x-gain_no-signal.tif",
    }
    skipped = dict(session.skipped)
    assert skipped["25x-gain_no-signal_S0.tif"] == (
        "the dark stack 25x-gain_no-signal.tif at set-point 25 is used instead"
    )
    assert len(skipped) == 6
    # without the stacks, the maps are the darks: the manifest names them
    maps_only = tmp_path / "maps"
    maps_only.mkdir()
    for tif in folder.glob("*.tif"):
        if not tif.stem.endswith("no-signal"):
            (maps_only / tif.name).write_bytes(tif.read_bytes())
    assert cli.main(["scan", str(maps_only), "-o", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(
        "gain-series: 3 set-points (1, 25, 300); darks: 3 offset/read-noise "
        "map pair(s)\nused:\n  1x-gain.tif (set-point 1, name); offset "
        "1x-gain_no-signal_S0.tif, read noise 1x-gain_no-signal_sigma.tif\n"
    )
    text = (tmp_path / "out" / "manifest.toml").read_text()  # -o a folder, as every verb's
    assert text.count("offset = ") == 3 and "dark = " not in text
    assert "taken as exact; add dark_frames = N" in text
    ds = quiet(calibrate, tmp_path / "out" / "manifest.toml", "gs", e_per_adu=3.859)
    assert bool(ds.converged.all())
    # -o naming a .toml file writes that file
    assert cli.main(["scan", str(maps_only), "-o", str(tmp_path / "gs.toml"), "-q"]) == 0
    assert (tmp_path / "gs.toml").read_text().count("[[acquisition]]") == 3


@pytest.mark.slow
@pytest.mark.real_data
def test_the_papers_folders_scan_as_they_are(real_data, tmp_path, capsys):
    # copied as published: no manifest written by hand
    import shutil

    from conftest import write_real_manifest

    for name in ("ADU", "gain-GS"):
        shutil.copytree(real_data / name, tmp_path / name)
    assert cli.main(["scan", str(tmp_path / "ADU")]) == 0
    out = capsys.readouterr().out
    # one line per level, never "set-point(s) 1, 1, 1, 1, 1, 1"
    assert out.startswith(
        "intensity-series: 6 levels at set-point 1; darks: 1 offset/read-noise map pair(s)\n"
    )
    assert cli.main(["scan", str(tmp_path / "gain-GS")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(
        "gain-series: 5 set-points (1, 5, 25, 100, 300); darks: 5 offset/read-noise map pair(s)\n"
    )
    assert "skipped:\n  ADU_map.tif: a map named for e⁻/ADU, not a dark" in out
    text = (tmp_path / "gain-GS" / "manifest.toml").read_text()
    assert '# e_per_adu = "ADU_map.tif"' in text
    # the scanned manifests calibrate as the hand-written ones, to the bit
    for kind, folder, method in (("adu", "ADU", "is-adu"), ("gs", "gain-GS", "gs")):
        extra = (
            {"e_per_adu": tifffile.imread(tmp_path / "gain-GS" / "ADU_map.tif")}
            if kind == "gs"
            else {}
        )
        scanned = quiet(
            calibrate, tmp_path / folder / "manifest.toml", method, em_model="gamma", **extra
        )
        written = quiet(calibrate, write_real_manifest(tmp_path, kind), method, em_model="gamma")
        for name in ("em_gain", "photoelectrons", "e_per_adu"):
            np.testing.assert_array_equal(scanned[name].values, written[name].values)
