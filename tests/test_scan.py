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
    return simulate_gain_series(d / "gs", rows=4, cols=5, frames=600, seed=21,
                                setpoints=(1, 25, 300))


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


@pytest.mark.parametrize("suffix", [".spe", ".ome.tif"])
def test_scanned_session_calibrates_as_the_written_manifest(series, tmp_path, suffix, capsys):
    folder = _session(series, tmp_path / "session", suffix)
    assert cli.main(["scan", str(folder)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("gain-series: 3 stack(s) at set-point(s) 1, 25, 300, 3 dark(s)")
    text = (folder / "manifest.toml").read_text()
    assert "set-points recorded in the files" in text and "adc_bits = 16" in text
    assert text.count("[[acquisition]]") == 3 and text.count("dark = ") == 3
    # φ is not in a camera's files: given, as the written manifest gives it
    scanned = quiet(calibrate, folder / "manifest.toml", "gs", e_per_adu=3.859)
    written = quiet(calibrate, series.manifest, "gs")
    # the same frames; the maps from the same darks (here reduced by the reader)
    np.testing.assert_allclose(scanned.em_gain.values, written.em_gain.values, rtol=1e-6)
    np.testing.assert_allclose(scanned.photoelectrons.values, written.photoelectrons.values,
                               rtol=1e-6)
    # an existing manifest is kept unless told
    assert cli.main(["scan", str(folder)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err


def test_readout_rate_changing_mid_series_is_refused(series, tmp_path):
    folder = _session(series, tmp_path / "session", ".spe",
                      readout=lambda sp: 5.0 if sp == 300 else 10.0)
    with pytest.raises(InputError, match=r"readout rate \(MHz\) 5(\.0)? in '.*-2100\.spe' "
                                         r"but 10(\.0)? in '.*': a series is taken with one"):
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
    tifffile.imwrite(nameless / "stack.tif", np.zeros((3, 2, 2), np.uint16), photometric="minisblack")
    with pytest.raises(InputError, match=r"stack\.tif': no EM gain set-point"):
        scan(nameless)
    nodark = tmp_path / "nodark"
    nodark.mkdir()
    tifffile.imwrite(nodark / "5x.tif", np.ones((3, 2, 2), np.uint16), photometric="minisblack")
    with pytest.raises(InputError, match="no dark stack at set-point 5"):
        scan(nodark)
