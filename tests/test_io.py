"""Tests of emccdcal.io: the manifest and the readers."""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile

from emccdcal import errors
from emccdcal.data import manifest as manifest_module
from emccdcal.data import stacks
from emccdcal.data.dark import maps_from_dark
from emccdcal.data.manifest import Source, read_manifest
from emccdcal.data.stacks import read_map, read_stack
from conftest import write_real_manifest

from emccdcal.errors import InputError, ManifestError

SHAPE = (3, 4)  # rows != cols, so that a transposition cannot pass
N_FRAMES = 20


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
def imwrite(path, data, **kwargs):
    """Write a TIFF; grey-scale pages even when the last axis is short (not RGB)."""
    tifffile.imwrite(path, data, photometric="minisblack", **kwargs)


def stack(seed=0, n=N_FRAMES, shape=SHAPE, dtype=np.uint16, low=500, high=700):
    rng = np.random.default_rng(seed)
    return rng.integers(low, high, size=(n, *shape)).astype(dtype)


@pytest.fixture
def files(tmp_path):
    """A folder with two frames stacks, their maps, a dark and a gain map."""
    d = tmp_path / "data"
    d.mkdir()
    imwrite(d / "1x.tif", stack(1))
    imwrite(d / "5x.tif", stack(2))
    imwrite(d / "1x_S0.tif", np.full(SHAPE, 588.5, np.float32))
    imwrite(d / "1x_sigma.tif", np.linspace(15, 16, 12, dtype=np.float32).reshape(SHAPE))
    imwrite(d / "dark5x.tif", stack(3, n=50, low=570, high=600))
    imwrite(d / "phi.tif", np.full(SHAPE, 3.859, np.float32))
    return tmp_path


def write(folder: Path, text: str, name="manifest.toml") -> Path:
    p = folder / name
    p.write_text(text)
    return p


GOOD = """\
e_per_adu = "data/phi.tif"

[[acquisition]]
frames = "data/1x.tif"
em_gain_setpoint = 1
offset = "data/1x_S0.tif"
read_noise = "data/1x_sigma.tif"
level = "L1"

[[acquisition]]
frames = "data/5x.tif"
em_gain_setpoint = 5
dark = "data/dark5x.tif"
skip_frames = 4
"""

ONE_1X = """\
[[acquisition]]
frames = "data/1x.tif"
em_gain_setpoint = 1
offset = "data/1x_S0.tif"
read_noise = "data/1x_sigma.tif"
"""


def error_of(path) -> str:
    with pytest.raises(ManifestError) as info:
        read_manifest(path)
    msg = str(info.value)
    assert "\n" not in msg, "error messages are one line"
    assert isinstance(info.value, ValueError)
    return msg


# --------------------------------------------------------------------------------------
# A valid manifest
# --------------------------------------------------------------------------------------
def test_round_trip(files):
    path = write(files, GOOD)
    m = read_manifest(path)
    assert m.path == path
    assert m.content_hash == hashlib.sha256(path.read_bytes()).hexdigest()
    assert m.shape == SHAPE
    assert m.adc_max == 65535
    assert m.setpoints == (1.0, 5.0)
    assert m.levels == ("L1",)
    assert isinstance(m.e_per_adu, np.ndarray) and m.e_per_adu.dtype == np.float64
    np.testing.assert_allclose(m.e_per_adu, np.float32(3.859))
    assert m.e_per_adu_source == Source("map", files / "data/phi.tif")
    assert str(m.e_per_adu_source) == str(files / "data/phi.tif")

    a1, a5 = m.acquisitions
    assert (a1.name, a1.em_gain_setpoint, a1.level, a1.skip_frames) == ("1x", 1.0, "L1", 0)
    assert a1.frames_path == files / "data/1x.tif"
    assert a1.offset.dtype == np.float64 and a1.offset.shape == SHAPE
    np.testing.assert_array_equal(a1.offset, 588.5)
    sigma = np.linspace(15, 16, 12, dtype=np.float32).reshape(SHAPE)
    np.testing.assert_allclose(a1.read_noise, sigma)
    assert a1.offset_source == Source("map", files / "data/1x_S0.tif")
    assert a1.n_frames == N_FRAMES and a1.shape == SHAPE
    np.testing.assert_array_equal(a1.frames(), stack(1))

    # the dark stack gives both maps, exactly those of maps_from_dark
    assert (a5.em_gain_setpoint, a5.level, a5.skip_frames) == (5.0, None, 4)
    offset, read_noise = maps_from_dark(stack(3, n=50, low=570, high=600))
    np.testing.assert_allclose(a5.offset, offset, rtol=1e-15)
    np.testing.assert_allclose(a5.read_noise, read_noise, rtol=1e-13)
    assert a5.offset_source == a5.read_noise_source == Source("dark", files / "data/dark5x.tif")
    assert str(a5.offset_source) == f"dark {files / 'data/dark5x.tif'}"
    assert a5.n_frames_total == N_FRAMES and a5.n_frames == N_FRAMES - 4
    np.testing.assert_array_equal(a5.frames(), stack(2)[4:])
    assert a5.frames().shape == (N_FRAMES - 4, *SHAPE)
    assert m.warnings == []


def test_frames_are_memory_mapped_when_possible_and_read_otherwise(files):
    imwrite(files / "data/zip.tif", stack(2), compression="zlib")
    path = write(files, GOOD.replace("data/5x.tif", "data/zip.tif"))
    m = read_manifest(path)
    assert isinstance(m.acquisitions[0].frames(), np.memmap)
    compressed = m.acquisitions[1].frames()
    assert not isinstance(compressed, np.memmap)
    np.testing.assert_array_equal(compressed, stack(2)[4:])


def test_scalars_expand_to_maps_and_e_per_adu_number(files):
    text = """\
e_per_adu = 3.859
[[acquisition]]
frames = "data/1x.tif"
em_gain_setpoint = 1
offset = 100
read_noise = 15.5
"""
    m = read_manifest(write(files, text))
    assert m.e_per_adu == 3.859 and isinstance(m.e_per_adu, float)
    assert m.e_per_adu_source == Source("value", value=3.859)
    assert str(m.e_per_adu_source) == "value 3.859"
    a = m.acquisitions[0]
    assert a.offset.shape == SHAPE and a.offset.dtype == np.float64
    np.testing.assert_array_equal(a.offset, 100.0)
    np.testing.assert_array_equal(a.read_noise, 15.5)
    assert str(a.read_noise_source) == "value 15.5"


def test_no_e_per_adu_and_paths_relative_to_the_manifest(files, monkeypatch, tmp_path):
    path = write(files, ONE_1X)
    monkeypatch.chdir(tmp_path / "data")  # the working directory must not matter
    m = read_manifest(path)
    assert m.e_per_adu is None and m.e_per_adu_source is None


def test_absolute_paths_name_and_level_as_number(files):
    absolute = f'"{files / "data/1x.tif"}"'
    text = ONE_1X.replace('"data/1x.tif"', absolute) + 'name = "ref"\nlevel = 3\n'
    m = read_manifest(write(files, text))
    assert m.acquisitions[0].name == "ref"
    assert m.acquisitions[0].level == "3"


def test_npy_stacks_and_maps(files):
    np.save(files / "data/s.npy", stack(5))
    np.save(files / "data/o.npy", np.full(SHAPE, 7.0))
    text = ONE_1X.replace("data/1x.tif", "data/s.npy").replace("data/1x_S0.tif", "data/o.npy")
    a = read_manifest(write(files, text)).acquisitions[0]
    np.testing.assert_array_equal(a.frames(), stack(5))
    np.testing.assert_array_equal(a.offset, 7.0)


def test_adc_max_from_dtype_and_from_adc_bits(files):
    imwrite(files / "data/u8.tif", stack(1, low=0, high=200, dtype=np.uint8))
    u8 = ONE_1X.replace("1x.tif", "u8.tif")
    # an offset map above what 8-bit counts can hold: other units, or a wrong adc_bits
    msg = error_of(write(files, u8))
    assert "offset 588.5 at pixel (0, 0)" in msg and "at or above the ADC maximum 255 ADU" in msg
    assert "set adc_bits in the manifest" in msg
    assert read_manifest(write(files, u8.replace('"data/1x_S0.tif"', "50"))).adc_max == 255
    # float data default to a 16-bit ADC
    imwrite(files / "data/f.tif", stack(1).astype(np.float32))
    assert read_manifest(write(files, ONE_1X.replace("1x.tif", "f.tif"))).adc_max == 65535
    m = read_manifest(write(files, "adc_bits = 12\n" + ONE_1X))
    assert m.adc_max == 4095


def test_integer_valued_float_and_signed_data_are_accepted(files):
    imwrite(files / "data/f.tif", stack(1).astype(np.float32))
    imwrite(files / "data/i.tif", stack(1).astype(np.int32))
    for name in ("f.tif", "i.tif"):
        a = read_manifest(write(files, ONE_1X.replace("1x.tif", name))).acquisitions[0]
        np.testing.assert_array_equal(a.frames(), stack(1))


def test_read_noise_growth_warns(files):
    imwrite(files / "data/hi_sigma.tif", np.full(SHAPE, 23.3, np.float32))
    text = (
        ONE_1X
        + """
[[acquisition]]
frames = "data/5x.tif"
em_gain_setpoint = 300
offset = 566
read_noise = "data/hi_sigma.tif"
"""
    )
    with pytest.warns(errors.ReadNoiseGrowthWarning, match="clock-induced charge"):
        m = read_manifest(write(files, text))
    assert len(m.warnings) == 1
    assert "set-point 300" in m.warnings[0] and "manifest.toml" in m.warnings[0]


def test_a_dark_used_twice_is_reduced_once(files, monkeypatch):
    calls = []
    real = manifest_module.resolve.read_out_maps  # of 1x darks and multiplied darks

    def counting(stack_, *args, **kw):
        calls.append(1)
        return real(stack_, *args, **kw)

    monkeypatch.setattr(manifest_module.resolve, "read_out_maps", counting)
    text = (
        GOOD
        + """
[[acquisition]]
frames = "data/1x.tif"
em_gain_setpoint = 5
dark = "data/dark5x.tif"
level = "L1"
""".replace("data/1x.tif", "data/other.tif")
    )
    imwrite(files / "data/other.tif", stack(9))
    m = read_manifest(write(files, text))
    assert len(calls) == 1
    np.testing.assert_array_equal(m.acquisitions[1].offset, m.acquisitions[2].offset)
    assert m.acquisitions[1].offset is not m.acquisitions[2].offset


# --------------------------------------------------------------------------------------
# Bad manifests: one line, naming the file and the problem
# --------------------------------------------------------------------------------------
def test_missing_manifest(tmp_path):
    msg = error_of(tmp_path / "nope.toml")
    assert "manifest file not found" in msg and "nope.toml" in msg
    assert str((tmp_path / "nope.toml").resolve()) in msg


def test_toml_syntax_error_names_file_and_line(files):
    path = write(files, ONE_1X + "em_gain_setpoint = \n")
    msg = error_of(path)
    assert str(path) in msg and "invalid TOML" in msg and "line 6" in msg


@pytest.mark.parametrize(
    "text, key, suggestion",
    [
        (ONE_1X.replace("offset =", "ofset ="), "ofset", "offset"),
        (
            ONE_1X.replace("em_gain_setpoint", "em_gain_setpiont"),
            "em_gain_setpiont",
            "em_gain_setpoint",
        ),
        ("e_per_adus = 3.8\n" + ONE_1X, "e_per_adus", "e_per_adu"),
        (ONE_1X + "skipframes = 3\n", "skipframes", "skip_frames"),
    ],
)
def test_unknown_key_is_named_with_a_suggestion(files, text, key, suggestion):
    msg = error_of(write(files, text))
    assert "manifest.toml" in msg
    assert f"unknown key '{key}'" in msg and f"did you mean '{suggestion}'" in msg


def test_unknown_key_without_close_match(files):
    msg = error_of(write(files, ONE_1X + "colour = 'red'\n"))
    assert "unknown key 'colour'" in msg and "did you mean" not in msg and "allowed:" in msg


def test_no_acquisition_and_wrong_table_kind(files):
    assert "no [[acquisition]]" in error_of(write(files, "e_per_adu = 3.0\n"))
    text = ONE_1X.replace("[[acquisition]]", "[acquisition]")
    assert "[[acquisition]]" in error_of(write(files, text))


def test_parsing_opens_no_data_file_and_gives_frozen_entries(files, monkeypatch):
    """The manifest in two steps: parse (keys, types, ranges) touches only the TOML file;
    resolve opens the stacks and maps."""
    import dataclasses

    path = write(files, GOOD.replace("data/", "elsewhere/"))
    opened = []
    real_open = Path.open

    def spy(self, *args, **kwargs):
        opened.append(self.name)
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", spy)
    entries = manifest_module.parse_manifest(path)
    assert set(opened) <= {"manifest.toml"}
    monkeypatch.undo()
    assert [a.em_gain_setpoint for a in entries.acquisitions] == [1.0, 5.0]
    assert entries.acquisitions[1].skip_frames == 4 and entries.acquisitions[0].skip_frames == 0
    assert entries.acquisitions[1].dark_path == files / "elsewhere/dark5x.tif"
    with pytest.raises(dataclasses.FrozenInstanceError):
        entries.acquisitions[0].skip_frames = 3
    # the files are looked for only when the entries are resolved
    with pytest.raises(ManifestError, match="frames file not found: 'elsewhere/1x.tif'"):
        manifest_module.resolve_manifest(entries)
    ok = manifest_module.resolve_manifest(manifest_module.parse_manifest(write(files, GOOD)))
    assert ok.shape == SHAPE and ok.acquisitions[1].n_frames == N_FRAMES - 4


def test_the_key_table_gives_the_allowed_keys_and_defaults():
    keys = {k.name: k for k in manifest_module.parse._ACQUISITION_KEYS}
    assert tuple(keys) == manifest_module.ACQUISITION_KEYS
    assert keys["skip_frames"].default == 0 and keys["offset"].unit == "ADU"
    # em_gain_setpoint: required unless camera_kind names a camera without an EM register
    assert keys["frames"].missing and keys["em_gain_setpoint"].missing is None
    assert keys["dark_frames"].problem(1) and keys["dark_frames"].problem(2) is None


def test_missing_frames_file_names_written_and_resolved_path(files):
    path = write(files, ONE_1X.replace("data/1x.tif", "data/missing.tif"))
    msg = error_of(path)
    assert "frames file not found: 'data/missing.tif'" in msg
    assert str((files / "data/missing.tif").resolve()) in msg
    assert "acquisition 1" in msg and "manifest.toml" in msg


@pytest.mark.parametrize("key", ["offset", "read_noise"])
def test_missing_map_file(files, key):
    written = "data/1x_S0.tif" if key == "offset" else "data/1x_sigma.tif"
    msg = error_of(write(files, ONE_1X.replace(written, "data/gone.tif")))
    assert f"{key} file not found: 'data/gone.tif'" in msg


def test_missing_dark_and_e_per_adu_files(files):
    msg = error_of(write(files, GOOD.replace("dark5x.tif", "nodark.tif")))
    assert "dark file not found: 'data/nodark.tif'" in msg and "acquisition 2" in msg
    msg = error_of(write(files, GOOD.replace("phi.tif", "nophi.tif")))
    assert "e_per_adu file not found: 'data/nophi.tif'" in msg


def test_unreadable_and_unsupported_files(files):
    (files / "data/junk.tif").write_text("not a tiff")
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "junk.tif")))
    assert "junk.tif" in msg and "cannot read" in msg
    (files / "data/x.fits").write_text("")
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "x.fits")))
    assert "x.fits': not a FITS file: Empty or corrupt FITS file" in msg
    (files / "data/x.nd2").write_text("")
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "x.nd2")))
    assert "x.nd2" in msg and "unsupported file type" in msg


def test_stack_not_3d(files):
    imwrite(files / "data/flat.tif", stack(1)[0])
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "flat.tif")))
    assert "flat.tif" in msg and "one image of 3 × 4 pixels, not a stack" in msg


def test_stacks_of_different_shapes(files):
    imwrite(files / "data/big.tif", stack(1, shape=(4, 4)))
    text = ONE_1X + ONE_1X.replace("1x.tif", "big.tif")
    msg = error_of(write(files, text))
    assert "big.tif" in msg and "acquisition 2" in msg
    assert "(4, 4)" in msg and "(3, 4)" in msg and "same pixels" in msg


def test_dark_of_different_shape(files):
    imwrite(files / "data/dark5x.tif", stack(1, shape=(3, 3)))
    msg = error_of(write(files, GOOD))
    assert "dark5x.tif" in msg and "(3, 3)" in msg and "(3, 4)" in msg


@pytest.mark.parametrize(
    "key, file", [("offset", "1x_S0.tif"), ("read_noise", "1x_sigma.tif"), ("e_per_adu", "phi.tif")]
)
def test_map_of_wrong_shape(files, key, file):
    imwrite(files / "data" / file, np.ones((4, 3), np.float32))
    msg = error_of(write(files, GOOD))
    assert file in msg and f"{key} map has shape (4, 3)" in msg and "(3, 4)" in msg


def test_dark_and_maps_both_or_neither(files):
    both = ONE_1X + 'dark = "data/dark5x.tif"\n'
    msg = error_of(write(files, both))
    assert "either 'dark' or 'offset' and 'read_noise', not both" in msg
    neither = "[[acquisition]]\nframes = 'data/1x.tif'\nem_gain_setpoint = 1\n"
    msg = error_of(write(files, neither))
    assert "no offset and read noise" in msg and "acquisition 1" in msg
    half = neither + "offset = 500\n"
    msg = error_of(write(files, half))
    assert "'offset' is given but 'read_noise' is missing" in msg


@pytest.mark.parametrize(
    "line, expected",
    [
        ("", "missing 'em_gain_setpoint'"),
        ("em_gain_setpoint = 0.5", "'em_gain_setpoint' must be >= 1"),
        ("em_gain_setpoint = 'high'", "'em_gain_setpoint' must be a number"),
        ("em_gain_setpoint = nan", "'em_gain_setpoint' must be a number"),
    ],
)
def test_bad_setpoint(files, line, expected):
    text = ONE_1X.replace("em_gain_setpoint = 1", line)
    msg = error_of(write(files, text))
    assert expected in msg and "acquisition 1" in msg and "1x.tif" in msg


def test_skip_frames(files):
    msg = error_of(write(files, ONE_1X + f"skip_frames = {N_FRAMES}\n"))
    assert f"skip_frames = {N_FRAMES} leaves no frames" in msg and "1x.tif" in msg
    assert f"has {N_FRAMES} frames" in msg
    msg = error_of(write(files, ONE_1X + "skip_frames = -1\n"))
    assert "'skip_frames' must be an integer >= 0" in msg
    msg = error_of(write(files, ONE_1X + "skip_frames = 2.5\n"))
    assert "'skip_frames' must be an integer >= 0" in msg


def test_float_data_not_integer_valued(files):
    data = stack(1).astype(np.float32)
    data[7, 2, 1] += 0.5
    imwrite(files / "data/f.tif", data)
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "f.tif")))
    assert "f.tif" in msg and "not integer-valued" in msg and "frame 7, pixel (2, 1)" in msg


def test_nan_data(files):
    data = stack(1).astype(np.float64)
    data[3, 0, 2] = np.nan
    imwrite(files / "data/nan.tif", data)
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "nan.tif")))
    assert "nan.tif" in msg and "NaN" in msg and "frame 3, pixel (0, 2)" in msg


@pytest.mark.parametrize("dtype", [np.int16, np.float32])
def test_negative_data(files, dtype):
    data = stack(1).astype(dtype)
    data[11, 1, 3] = -4
    imwrite(files / "data/neg.tif", data)
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "neg.tif")))
    assert "neg.tif" in msg and "negative values" in msg and "frame 11, pixel (1, 3)" in msg


def test_negative_data_in_a_dark(files):
    data = stack(3, n=50).astype(np.int32)
    data[0, 0, 0] = -1
    imwrite(files / "data/dark5x.tif", data)
    msg = error_of(write(files, GOOD))
    assert "dark5x.tif" in msg and "negative values" in msg and "acquisition 2" in msg


def test_data_above_adc_bits(files):
    msg = error_of(write(files, "adc_bits = 8\n" + ONE_1X))
    assert "1x.tif" in msg and "above the ADC maximum 255" in msg and "adc_bits = 8" in msg
    msg = error_of(write(files, "adc_bits = 40\n" + ONE_1X))
    assert "adc_bits must be an integer from 1 to 32" in msg


def test_float_data_above_the_default_adc_maximum(files):
    imwrite(files / "data/f.tif", stack(1, low=70000, high=70010, dtype=np.float32))
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "f.tif")))
    assert "f.tif" in msg and "above the ADC maximum 65535" in msg and "set adc_bits" in msg


@pytest.mark.parametrize(
    "key, file, value, expected",
    [
        ("read_noise", "1x_sigma.tif", 0.0, "read_noise map must be > 0"),
        ("read_noise", "1x_sigma.tif", -1.0, "read_noise map must be > 0"),
        ("read_noise", "1x_sigma.tif", np.nan, "read_noise map contains NaN"),
        ("offset", "1x_S0.tif", -3.0, "offset map must be >= 0"),
        ("offset", "1x_S0.tif", np.inf, "offset map contains NaN or infinite"),
        ("e_per_adu", "phi.tif", 0.0, "e_per_adu map must be > 0"),
    ],
)
def test_bad_map_values(files, key, file, value, expected):
    m = np.full(SHAPE, 5.0, np.float32)
    m[2, 3] = value
    imwrite(files / "data" / file, m)
    msg = error_of(write(files, GOOD))
    assert file in msg and expected in msg and "pixel (2, 3)" in msg


@pytest.mark.parametrize(
    "text, expected",
    [
        (ONE_1X.replace('"data/1x_sigma.tif"', "0"), "'read_noise' must be > 0"),
        (ONE_1X.replace('"data/1x_S0.tif"', "-2"), "'offset' must be >= 0"),
        (ONE_1X.replace('"data/1x_S0.tif"', "inf"), "'offset' must be finite"),
        (ONE_1X.replace('"data/1x_S0.tif"', "true"), "'offset' must be a number or the path"),
        ("e_per_adu = -3.8\n" + ONE_1X, "'e_per_adu' must be > 0"),
        ("e_per_adu = [3.8]\n" + ONE_1X, "'e_per_adu' must be a number or the path"),
    ],
)
def test_bad_scalar_values(files, text, expected):
    assert expected in error_of(write(files, text))


def test_a_constant_dark_pixel_is_marked_stuck_and_a_constant_dark_refused(files):
    """A pixel whose dark counts never change reads as read noise 0, marked stuck (the
    fit leaves it out); a dark constant everywhere is refused in one line."""
    data = stack(3, n=50)
    data[:, 1, 1] = 580
    imwrite(files / "data/dark5x.tif", data)
    (acq,) = [a for a in read_manifest(write(files, GOOD)).acquisitions if a.dark_stuck is not None]
    assert acq.read_noise[1, 1] == 0 and np.flatnonzero(acq.dark_stuck).tolist() == [
        1 * SHAPE[1] + 1
    ]
    data[:] = 580
    imwrite(files / "data/dark5x.tif", data)
    msg = error_of(write(files, GOOD))
    assert "dark5x.tif" in msg and "counts never change at any pixel" in msg


def test_dark_with_one_frame(files):
    np.save(files / "data/dark1.npy", stack(3, n=1))
    msg = error_of(write(files, GOOD.replace("dark5x.tif", "dark1.npy")))
    assert "dark1.npy" in msg and "has 1 frame(s); at least 2 are needed" in msg


def test_same_frames_file_twice(files):
    msg = error_of(write(files, ONE_1X + ONE_1X))
    assert "acquisition 2" in msg and "also acquisition 1" in msg and "1x.tif" in msg


def test_bad_level_and_name(files):
    assert "'level' must be a string" in error_of(write(files, ONE_1X + "level = 1.5\n"))
    assert "'name' must be a non-empty string" in error_of(write(files, ONE_1X + "name = ''\n"))


# --------------------------------------------------------------------------------------
# read_stack, read_map, check_counts on their own
# --------------------------------------------------------------------------------------
def test_read_stack_and_read_map(files):
    s = read_stack(files / "data/1x.tif")
    assert isinstance(s, np.memmap) and s.shape == (N_FRAMES, *SHAPE)
    np.testing.assert_array_equal(s, stack(1))
    m = read_map(files / "data/1x_S0.tif", SHAPE, name="offset")
    assert m.dtype == np.float64 and m.shape == SHAPE
    expected = r"1x_S0.tif.*offset map has shape \(3, 4\), but the stacks are \(4, 3\)"
    with pytest.raises(InputError, match=expected):
        read_map(files / "data/1x_S0.tif", (4, 3), name="offset")
    with pytest.raises(InputError, match="not a 3-D"):
        read_stack(files / "data/1x_S0.tif")
    with pytest.raises(InputError, match=r"file not found: '.*nothing.tif' \(resolved to"):
        read_stack(files / "nothing.tif")
    with pytest.raises(InputError, match=r"above the ADC maximum 600"):
        read_stack(files / "data/1x.tif", adc_max=600)


def test_tiff_with_several_series_is_refused(files):
    with tifffile.TiffWriter(files / "data/two.tif") as tif:
        tif.write(stack(1), photometric="minisblack")
        tif.write(np.zeros((2, 2), np.uint16), photometric="minisblack")
    with pytest.raises(InputError, match=r"two.tif'.*holds 2 image series"):
        read_stack(files / "data/two.tif")
    msg = error_of(write(files, ONE_1X.replace("1x.tif", "two.tif")))
    assert "two.tif" in msg and "expected one (frames, rows, cols) stack" in msg


class _Untouchable:
    """A stack whose values must not be read."""

    def __init__(self, dtype):
        self.dtype = np.dtype(dtype)
        self.shape = (10**6, 512, 512)
        self.size = int(np.prod(self.shape))
        self.ndim = 3

    def __getitem__(self, item):
        raise AssertionError("data were read")


def test_unsigned_stacks_are_not_scanned():
    stacks.check_counts(_Untouchable(np.uint16), "x.tif")  # no read: passes
    stacks.check_counts(_Untouchable(np.uint16), "x.tif", adc_max=65535)
    with pytest.raises(AssertionError, match="data were read"):
        stacks.check_counts(_Untouchable(np.float32), "x.tif")
    with pytest.raises(AssertionError, match="data were read"):
        stacks.check_counts(_Untouchable(np.uint16), "x.tif", adc_max=4095)


class _Recording:
    """A stack that records how many frames each read asks for."""

    def __init__(self, data):
        self.data, self.dtype, self.shape, self.size = data, data.dtype, data.shape, data.size
        self.reads = []

    def __getitem__(self, item):
        out = self.data[item]
        self.reads.append(out.shape[0])
        return out


def test_scan_is_chunked_and_reports_the_right_frame(monkeypatch):
    monkeypatch.setattr(stacks, "_SCAN_ELEMENTS", 2 * 12)  # two (3, 4) frames per chunk
    data = stack(1).astype(np.float32)
    rec = _Recording(data)
    stacks.check_counts(rec, "x.tif")
    assert sum(rec.reads) == N_FRAMES and max(rec.reads) == 2
    data[13, 2, 0] = -1
    with pytest.raises(InputError, match=r"frame 13, pixel \(2, 0\)"):
        stacks.check_counts(data, "x.tif")


# --------------------------------------------------------------------------------------
# The real data (skipped where the folder is absent)
# --------------------------------------------------------------------------------------
def test_real_gain_series_manifest(real_data, tmp_path):
    path = write_real_manifest(tmp_path, "gs")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = read_manifest(path)
    assert m.content_hash == hashlib.sha256(path.read_bytes()).hexdigest()
    assert m.shape == (3, 3)
    assert m.setpoints == (1.0, 5.0, 25.0, 100.0, 300.0)
    assert m.adc_max == 65535
    np.testing.assert_allclose(m.e_per_adu, 3.859, rtol=1e-6)
    for a in m.acquisitions:
        assert a.n_frames == 5000 and a.frames().shape == (5000, 3, 3)
    # dark offset drifts down with set-point (docs/quality.md): about 588 at 1x, 566 at 300x
    offsets = [float(a.offset.mean()) for a in m.acquisitions]
    assert offsets == sorted(offsets, reverse=True)
    assert 585 < offsets[0] < 591 and 563 < offsets[-1] < 569
    # read noise grows at 300x (clock-induced charge): the manifest warns about it
    assert any("set-point 300" in w for w in m.warnings)
    assert any(issubclass(w.category, errors.ReadNoiseGrowthWarning) for w in caught)
    assert not any("set-point 5 " in w or "set-point 25 " in w for w in m.warnings)
