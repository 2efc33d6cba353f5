"""Camera file formats: SPE 3.0 (with per-frame metadata) and 2.x, their settings, and the
same series calibrating identically whatever it is stored in."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest
import tifffile
from camera_files import write_fits, write_micromanager_tiff, write_spe, write_zarr
from conftest import quiet

from emccdcal import calibrate, result
from emccdcal.data.manifest import read_manifest
from emccdcal.data.stacks import load_stack, read_band, stack_header, stack_settings
from emccdcal.errors import EmccdcalError, InputError
from emccdcal.export import database
from emccdcal.simulate.series import simulate_gain_series


def _frames(n=7, h=5, w=6, seed=0):
    return np.random.default_rng(seed).integers(0, 65535, (n, h, w)).astype(np.uint16)


@pytest.mark.parametrize("metadata", [True, False])
def test_spe3_frames_are_found_through_the_stride(tmp_path, metadata):
    data = _frames()
    path = write_spe(tmp_path / "s.spe", data, em_gain=300, frame_metadata=metadata)
    assert stack_header(path) == ((7, 5, 6), np.dtype("<u2"))
    np.testing.assert_array_equal(np.asarray(load_stack(path)), data)
    np.testing.assert_array_equal(read_band(path, 1, 4, 2), data[2:, 1:4])
    np.testing.assert_array_equal(read_band(path, 0, 5, 3), data[3:])  # whole frames


def test_spe3_settings(tmp_path):
    path = write_spe(
        tmp_path / "s.spe",
        _frames(),
        em_gain=25,
        analog_gain="Low",
        speed_mhz=10,
        bit_depth=16,
        exposure_ms=30,
        temperature=-65.5,
        serial="0512",
        model="ProEM-HS: 512BX3",
        roi=(100, 200),
        binning=(1, 1),
    )
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.analog_gain, s.readout_rate_mhz, s.adc_bits) == (
        25,
        "Low",
        10,
        16,
    )
    assert s.amplifier == "ElectronMultiplied"  # LightField's Adc/Quality: the output port
    assert (s.exposure_ms, s.temperature_c, s.serial, s.model) == (
        30,
        -65.5,
        "0512",
        "ProEM-HS: 512BX3",
    )
    assert s.roi == (100, 200, 6, 5) and s.binning == (1, 1)
    assert stack_settings(tmp_path / "s.spe").known()["em_gain_setpoint"] == 25
    tif = tmp_path / "t.tif"
    tifffile.imwrite(tif, _frames())
    assert stack_settings(tif).known() == {}


def test_spe2_header(tmp_path):
    data = _frames(n=4)
    head = bytearray(4100)
    struct.pack_into("<f", head, 10, 0.02)  # exposure, s
    struct.pack_into("<f", head, 36, -70.0)  # detector temperature
    struct.pack_into("<H", head, 42, 6)
    struct.pack_into("<h", head, 108, 3)  # uint16
    struct.pack_into("<h", head, 194, 16)  # ADC resolution
    struct.pack_into("<H", head, 656, 5)
    struct.pack_into("<i", head, 1446, 4)
    struct.pack_into("<f", head, 1992, 2.5)
    struct.pack_into("<H", head, 4098, 0x5555)
    path = tmp_path / "old.spe"
    path.write_bytes(bytes(head) + data.astype("<u2").tobytes())
    np.testing.assert_array_equal(np.asarray(load_stack(path)), data)
    s = stack_settings(path)
    assert s.exposure_ms == pytest.approx(20.0) and s.temperature_c == -70 and s.adc_bits == 16
    assert s.em_gain_setpoint is None  # SPE 2.x has no field for it


@pytest.mark.parametrize(
    "damage, message",
    [
        (
            dict(truncate=4500),
            r"footer offset 4632 is outside the file \(4500 bytes\): damaged or "
            r"truncated",
        ),
        (dict(truncate=6000), r"XML footer is not valid XML"),
        (dict(footer_offset=10**9), r"footer offset 1000000000 is outside the file"),
        (dict(stride=10), r"frame stride 10 bytes is smaller than a frame of 5 × 6"),
        (dict(stride=4000), r"truncated: the SPE 3.0 footer describes 7 frames of 4000 bytes"),
        (dict(xml_text="<SpeFormat><DataFormat>"), r"XML footer is not valid XML"),
        (dict(xml_text="<SpeFormat/>"), r"no DataFormat/DataBlock of type 'Frame'"),
        (dict(header=b"\x00\x00"), r"not an SPE file \(no 0x5555 at byte 4098\)"),
    ],
)
def test_damaged_spe_is_one_line_naming_the_file(tmp_path, damage, message):
    damage = dict(damage)
    truncate, header = damage.pop("truncate", None), damage.pop("header", None)
    path = write_spe(tmp_path / "bad.spe", _frames(), **damage)
    raw = path.read_bytes()
    if truncate is not None:
        raw = raw[:truncate]
    if header is not None:
        raw = raw[:4098] + header + raw[4100:]
    path.write_bytes(raw)
    with pytest.raises(InputError, match=message) as exc:
        load_stack(path)
    assert "bad.spe" in str(exc.value) and "\n" not in str(exc.value)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    return simulate_gain_series(
        d / "gs", rows=4, cols=6, frames=800, seed=11, setpoints=(1, 25, 300)
    )


WRITERS = {
    ".spe": write_spe,
    ".fits": write_fits,
    ".zarr": write_zarr,
    ".ome.tif": write_micromanager_tiff,
}


def _as_spe(series, name, *, gains=None, suffix=".spe"):
    """The series with every frames stack rewritten in another format (SPE 3.0 with
    per-frame metadata, or FITS with Andor's cards), its set-point recorded."""
    text = series.manifest.read_text()
    for tif in re.findall(r'frames = "([^"]+\.tif)"', text):
        src = series.manifest.parent / tif
        sp = float(re.search(r"(\d+)x-gain", tif).group(1))
        gain = sp if gains is None else gains.get(sp, sp)
        WRITERS[suffix](src.with_name(src.stem + suffix), tifffile.imread(src), em_gain=gain)
        text = text.replace(f'"{tif}"', f'"{tif[:-4]}{suffix}"')
    path = series.manifest.with_name(name)
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "suffix", [".spe", ".fits", pytest.param(".zarr", marks=pytest.mark.slow), ".ome.tif"]
)
def test_same_series_in_another_format_calibrates_identically(series, suffix, tmp_path):
    other = _as_spe(series, f"other{suffix}.toml", suffix=suffix)
    a = quiet(calibrate, series.manifest, "gs", tile_pixels=12)
    b = quiet(calibrate, other, "gs", tile_pixels=12)  # two tiles: bands of rows
    for name in ("em_gain", "em_gain_se", "photoelectrons", "photoelectrons_se", "loglik"):
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
    assert "camera" not in a.attrs  # plain TIFFs record no camera
    if suffix == ".spe":  # what the files record: the identity the database keys on
        assert json.loads(b.attrs["camera"]) == {
            "serial": "12345678",
            "model": "ProEM+: 512B",
            "amplifier": "ElectronMultiplied",
            "readout_rate_mhz": 10.0,
            "analog_gain": "High",
            "adc_bits": 16,
        }
        result.save(b, tmp_path / "res")
        e = database.add(tmp_path / "res", db=tmp_path / "db.sqlite")
        assert (e.camera, e.readout) == (
            "12345678",
            "ElectronMultiplied, 10 MHz, analog gain High, 16-bit",
        )
        assert sorted(e.gains) == [25.0, 300.0]


def test_fits_stack_is_read_by_sections_with_its_settings(tmp_path):
    data = _frames()
    path = write_fits(
        tmp_path / "s.fits",
        data,
        em_gain=200,
        exposure_s=0.03,
        temperature=-80,
        readtime=1e-7,
        binning=(2, 2),
    )
    assert stack_header(path) == ((7, 5, 6), np.dtype("uint16"))
    np.testing.assert_array_equal(np.asarray(load_stack(path)), data)
    np.testing.assert_array_equal(read_band(path, 1, 3, 4), data[4:, 1:3])
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.exposure_ms, s.temperature_c) == (200, 30, -80)
    assert s.readout_rate_mhz == pytest.approx(10.0) and s.binning == (2, 2)
    assert (s.serial, s.model, s.analog_gain) == ("X-1234", "DU897_BV", "2.0")
    assert s.amplifier == "Electron Multiplying"
    path.write_bytes(path.read_bytes()[:3000])  # header 2880 bytes, data 420
    with pytest.raises(InputError, match=r"s\.fits': truncated: its header describes 7 × 5 × 6"):
        load_stack(path)


def test_setpoint_disagreeing_with_the_file_is_said(series):
    spe = _as_spe(series, "spe-wrong.toml", gains={25: 50})
    with pytest.warns(
        UserWarning,
        match=r"acquisition 2 \(25x\): the manifest says EM gain "
        r"set-point 25, but '.*25x-gain\.spe' records 50",
    ):
        read_manifest(spe)


def test_unsupported_suffix_lists_the_readable_ones(tmp_path):
    (tmp_path / "x.nd2").write_bytes(b"ND2 file")
    with pytest.raises(EmccdcalError, match=r"unsupported file type '\.nd2' \(supported: .*\.spe"):
        load_stack(tmp_path / "x.nd2")


def test_zarr_store_with_its_settings(tmp_path):
    data = _frames()
    path = write_zarr(
        tmp_path / "s.zarr", data, em_gain=100, readout_rate_mhz=10.0, roi=[0, 0, 6, 5]
    )
    assert stack_header(path) == ((7, 5, 6), np.dtype("uint16"))
    np.testing.assert_array_equal(read_band(path, 2, 4, 1), data[1:, 2:4])
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.readout_rate_mhz, s.roi) == (100, 10.0, (0, 0, 6, 5))
    bad = write_zarr(tmp_path / "bad.zarr", data, em_gian=3)
    with pytest.raises(InputError, match=r"bad\.zarr': unknown camera setting\(s\) em_gian"):
        stack_settings(bad)


@pytest.mark.parametrize(
    "style, model, serial, analog, amplifier",
    [
        ("andor", "DU897_BV", "9876", "Gain 2", "Electron Multiplying"),
        ("photometrics", "Evolve512", "A17C", "1", "Multiplication gain"),
    ],
)
def test_micromanager_properties_are_the_settings(
    tmp_path, style, model, serial, analog, amplifier
):
    data = _frames()
    path = write_micromanager_tiff(
        tmp_path / "mm.ome.tif", data, em_gain=200, style=style, readout="10 MHz", temperature=-80
    )
    np.testing.assert_array_equal(np.asarray(load_stack(path)), data)
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.readout_rate_mhz, s.temperature_c) == (200, 10, -80)
    assert (s.model, s.serial, s.analog_gain, s.adc_bits) == (model, serial, analog, 16)
    assert s.amplifier == amplifier
    assert s.exposure_ms == 10 and s.roi == (0, 0, 6, 5) and s.binning == (1, 1)


def test_settings_changing_within_a_stack_are_refused():
    # (tifffile writes one copy of a tag value that all pages share, so the pages of a
    # stack whose settings change are stood in for here)
    from types import SimpleNamespace

    from camera_files import micromanager_properties

    from emccdcal.data import micromanager

    def page(readout):
        md = micromanager_properties("andor", readout=readout)
        return SimpleNamespace(tags={micromanager.TAG: SimpleNamespace(value=md)})

    tif = SimpleNamespace(pages=[page("17.000 MHz")] * 6 + [page("10.000 MHz")])
    with pytest.raises(
        InputError,
        match=r"'mm\.tif': the camera's readout_rate_mhz changes "
        r"within the stack \(17\.0 in its first frame, 10\.0",
    ):
        micromanager.stack_settings("mm.tif", tif)
    tif.pages[-1] = page("17.000 MHz")
    assert micromanager.stack_settings("mm.tif", tif).readout_rate_mhz == 17.0


def test_recorded_regions_place_the_stacks_on_the_sensor(series):
    # SPE files record their SensorMapping: the manifest knows where its pixels are
    spe = _as_spe(series, "region.toml")
    assert quiet(read_manifest, spe).origin == (0, 0)
    text = spe.read_text()
    moved = spe.with_name("moved.toml")
    moved.write_text("origin = [3, 4]\n" + text)
    with pytest.warns(UserWarning, match=r"origin = \[3, 4\], but the files record \[0, 0\]"):
        assert read_manifest(moved).origin == (3, 4)


SIF = Path(__file__).parent / "data" / "sif"


@pytest.mark.parametrize(
    "name, shape, gain, binning, temperature",
    [
        ("image.sif", (1, 512, 512), 1000, (1, 1), -100),
        ("test.sif", (1, 256, 256), 56, (2, 2), None),
    ],
)
def test_real_andor_sif_files(name, shape, gain, binning, temperature):
    path = SIF / name
    assert stack_header(path)[0] == shape
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.binning, s.temperature_c, s.model) == (
        gain,
        binning,
        temperature,
        "DU897_BV",
    )
    assert s.readout_rate_mhz == pytest.approx(10.0)
    band = read_band(path, 10, 12)
    np.testing.assert_array_equal(band, np.asarray(load_stack(path))[:, 10:12])
    assert band.dtype == np.float32  # (image.sif holds processed, non-integer values)


def test_one_frame_sif_in_a_manifest_is_refused_in_one_line(tmp_path):
    (tmp_path / "m.toml").write_text(
        f'[[acquisition]]\nframes = "{SIF / "image.sif"}"\nem_gain_setpoint = 1000\n'
        "offset = 100.0\nread_noise = 10.0\n"
    )
    with pytest.raises(EmccdcalError, match=r"image\.sif' has 1 frame: a histogram"):
        quiet(read_manifest, tmp_path / "m.toml")


def test_damaged_sif_is_one_line(tmp_path):
    bad = tmp_path / "bad.sif"
    bad.write_bytes((SIF / "test.sif").read_bytes()[:3000])
    with pytest.raises(InputError, match=r"bad\.sif': not a readable SIF file") as exc:
        load_stack(bad)
    assert "\n" not in str(exc.value)


def test_multi_frame_sif_derived_from_a_real_one(tmp_path):
    from camera_files import multi_frame_sif

    rng = np.random.default_rng(4)
    frames = rng.integers(500, 4000, (12, 256, 256)).astype(np.float32)
    path = multi_frame_sif(SIF / "test.sif", tmp_path / "multi.sif", frames)
    assert stack_header(path) == ((12, 256, 256), np.dtype("float32"))
    np.testing.assert_array_equal(read_band(path, 100, 103, 2), frames[2:, 100:103])
    s = stack_settings(path)
    assert (s.em_gain_setpoint, s.binning, s.model) == (56, (2, 2), "DU897_BV")


def test_binning_travels_with_the_result_and_must_match(series, tmp_path):
    spe = _as_spe(series, "binned.toml")
    assert quiet(read_manifest, spe).binning == (1, 1)
    adu_like = quiet(calibrate, spe, "gs", out=tmp_path / "r")
    assert list(adu_like.attrs["binning"]) == [1, 1] and list(adu_like.attrs["sensor_origin"]) == [
        0,
        0,
    ]
    # an is-adu result of 2 × 2 binned pixels cannot give φ to unbinned ones
    from emccdcal.simulate.series import simulate_intensity_series

    adu = simulate_intensity_series(
        tmp_path / "adu", rows=4, cols=6, frames=300, seed=3, levels=(2000, 8000, 32000)
    )
    text = adu.manifest.read_text()
    for tif in re.findall(r'frames = "([^"]+\.tif)"', text):
        src = adu.manifest.parent / tif
        write_spe(src.with_suffix(".spe"), tifffile.imread(src), em_gain=1, binning=(2, 2))
        text = text.replace(f'"{tif}"', f'"{tif[:-4]}.spe"')
    binned = adu.manifest.with_name("binned.toml")
    binned.write_text(text)
    quiet(calibrate, binned, "is-adu", out=tmp_path / "phi")
    with pytest.raises(InputError, match=r"binning 1x1 \(calibration: 2x2\)"):
        quiet(calibrate, spe, "gs", e_per_adu=tmp_path / "phi")


def test_imagej_hyperstack_reads_as_the_plain_tiff(tmp_path):
    data = _frames()
    path = tmp_path / "ij.tif"
    tifffile.imwrite(path, data, imagej=True)
    assert stack_header(path) == ((7, 5, 6), np.dtype("uint16"))
    np.testing.assert_array_equal(read_band(path, 1, 3, 2), data[2:, 1:3])
