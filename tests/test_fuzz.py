"""Property-based fuzzing of the input layer: manifests and the stack readers.

The invariant: a damaged input gives either the clean result (what the undamaged files
give) or one clear error, an :class:`emccdcal.EmccdcalError` whose message is one line
naming the file; never a traceback from inside a library, never a different result
without a word. "The result" here is what a calibration reads: the manifest's
acquisitions, maps and every frame of every stack (``read_band``).

Byte flips inside a stack's pixel data change the counts: the file then holds other,
valid counts, which no reader can tell from the original. For those the expected result
is the original with that byte flipped; everywhere else (headers, page index, maps) it is
the original itself.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from emccdcal.data.manifest import read_manifest
from emccdcal.data.stacks import _layout, read_band
from emccdcal.errors import EmccdcalError

ROWS, COLS, FRAMES = 3, 4, 12
FUZZ = settings(
    max_examples=int(os.environ.get("FUZZ_EXAMPLES", 700)),
    deadline=None,
    derandomize=not os.environ.get("FUZZ_EXAMPLES"),
    suppress_health_check=[HealthCheck.too_slow],
)

MANIFEST = """\
e_per_adu = 3.859
adc_bits = 16

[[acquisition]]
name = "1x"
frames = "1x.tif"
em_gain_setpoint = 1
offset = "S0.tif"
read_noise = "sigma.tif"

[[acquisition]]
name = "25x"
frames = "25x.npy"
em_gain_setpoint = 25
offset = 588.0
read_noise = 15.5
skip_frames = 2
"""


def _frames(seed, low, high):
    return np.random.default_rng(seed).integers(low, high, (FRAMES, ROWS, COLS)).astype(np.uint16)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A valid manifest folder and what a calibration reads of it."""
    d = tmp_path_factory.mktemp("clean")
    tifffile.imwrite(d / "1x.tif", _frames(1, 600, 700), photometric="minisblack")
    np.save(d / "25x.npy", _frames(2, 600, 4000))
    tifffile.imwrite(
        d / "S0.tif", np.full((ROWS, COLS), 588.5, np.float32), photometric="minisblack"
    )
    tifffile.imwrite(
        d / "sigma.tif", np.full((ROWS, COLS), 15.2, np.float32), photometric="minisblack"
    )
    (d / "manifest.toml").write_text(MANIFEST)
    return d, _read(d / "manifest.toml")


def _read(path):
    """What a calibration reads: per acquisition (setpoint, skip, offset, read noise, frames)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a damaged page index read in full warns
        m = read_manifest(path)
        return [
            (
                a.em_gain_setpoint,
                a.skip_frames,
                np.array(a.offset),
                np.array(a.read_noise),
                read_band(a.frames_path, 0, ROWS, a.skip_frames),
            )
            for a in m.acquisitions
        ]


def _same(a, b) -> bool:
    return len(a) == len(b) and all(
        x[0] == y[0] and x[1] == y[1] and all(np.array_equal(u, v) for u, v in zip(x[2:], y[2:]))
        for x, y in zip(a, b)
    )


def _outcome(folder: Path, damaged: str):
    """The reading's result, or None after a clear error (asserted here)."""
    try:
        return _read(folder / "manifest.toml")
    except EmccdcalError as exc:
        msg = str(exc)
        assert "\n" not in msg, msg
        assert damaged in msg or "manifest.toml" in msg, msg
        return None


#: Where a file's values land in what :func:`_read` returns: (acquisition, field).
WHERE = {"1x.tif": (0, 4), "25x.npy": (1, 4), "S0.tif": (0, 2)}


def _data_span(path: Path):
    shape, dtype, offset, _ = _layout(path)
    return offset, offset + int(np.prod(shape)) * dtype.itemsize


@pytest.mark.slow
@pytest.mark.parametrize("name", ["1x.tif", "25x.npy", "S0.tif"])
@FUZZ
@given(data=st.data())
def test_damaged_file_gives_the_clean_result_or_one_clear_error(clean, name, data):
    folder, expected = clean
    original = (folder / name).read_bytes()
    damaged = bytearray(original)
    flips = data.draw(
        st.lists(st.tuples(st.integers(0, len(original) - 1), st.integers(1, 255)), max_size=3),
        label="flips",
    )
    for at, xor in flips:
        damaged[at] ^= xor
    cut = data.draw(st.one_of(st.none(), st.integers(0, len(original))), label="truncate at")
    if cut is not None:
        damaged = damaged[:cut]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        shutil.copytree(folder, tmp, dirs_exist_ok=True)
        (tmp / name).write_bytes(bytes(damaged))
        got = _outcome(tmp, name)
    if got is None:
        return
    # Read without an error: the clean result, except for values whose bytes were flipped.
    lo, hi = _data_span(folder / name)
    in_data = [(at, xor) for at, xor in flips if lo <= at < hi]
    if in_data:
        raw = bytearray(original)
        for at, xor in in_data:
            raw[at] ^= xor
        a, field = WHERE[name]
        old = expected[a][field]
        shape, dtype, *_ = _layout(folder / name)
        values = np.frombuffer(bytes(raw[lo:hi]), dtype=dtype).reshape(shape)
        if field == 4:  # the frames from skip_frames on
            values = values[expected[a][1] :]
        expected = list(expected)
        expected[a] = tuple(
            values.astype(old.dtype) if i == field else v for i, v in enumerate(expected[a])
        )
    assert _same(got, expected), f"silently different result after {flips}, cut {cut}"


KEYS = [
    "e_per_adu",
    "adc_bits",
    "name",
    "frames",
    "em_gain_setpoint",
    "offset",
    "read_noise",
    "skip_frames",
    "dark",
    "dark_frames",
    "level",
    "acquisition",
]
VALUES = st.one_of(
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=12),
    st.sampled_from(['"1x.tif"', '"S0.tif"', '"nope.tif"']),
    st.lists(st.integers(-3, 3), max_size=3),
)


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(v), repr(v))
    if isinstance(v, str) and not v.startswith('"'):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(str(x) for x in v) + "]"
    return str(v)


@pytest.mark.slow
@FUZZ
@given(
    lines=st.lists(
        st.one_of(
            st.tuples(st.sampled_from(KEYS), VALUES).map(
                lambda kv: f"{kv[0]} = {_toml_value(kv[1])}"
            ),
            st.sampled_from(
                [
                    "[[acquisition]]",
                    "[acquisition]",
                    "[[dark]]",
                    "",
                    "# c",
                    "x =",
                    "= 3",
                    '"unterminated',
                    '[[acquisition]]\nframes = "1x.tif"\nem_gain_setpoint = 1',
                ]
            ),
            st.text(max_size=20),
        ),
        max_size=12,
    )
)
def test_random_toml_gives_a_manifest_or_one_clear_error(clean, lines):
    folder, _ = clean
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        shutil.copytree(folder, tmp, dirs_exist_ok=True)
        (tmp / "manifest.toml").write_text("\n".join(lines), encoding="utf-8", errors="replace")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = read_manifest(tmp / "manifest.toml")
        except EmccdcalError as exc:
            assert "\n" not in str(exc) and "manifest.toml" in str(exc), str(exc)
            return
        # A manifest that reads is a usable one: every acquisition has its frames and maps.
        assert m.acquisitions
        for a in m.acquisitions:
            assert a.n_frames >= 2 and a.offset.shape == a.shape == m.shape
            assert np.all(np.isfinite(a.offset)) and np.all(a.read_noise > 0)


# --------------------------------------------------------------------------------------
# The damaged files of a user's report, each as one case
# --------------------------------------------------------------------------------------
def _copy(clean, tmp_path):
    folder, _ = clean
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True)
    return tmp_path


def test_truncated_stack_names_manifest_acquisition_and_file(clean, tmp_path, capsys):
    from emccdcal import cli

    d = _copy(clean, tmp_path)
    data = (d / "1x.tif").read_bytes()
    (d / "1x.tif").write_bytes(data[:400])  # inside the pixel data of frame 5
    assert cli.main(["check", str(d / "manifest.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tifffile" not in err.lower().replace("tifffile.py", "")
    assert "manifest.toml: acquisition 1 (1x)" in err or "manifest.toml: acquisition 1" in err
    assert "1x.tif': truncated: its header describes 12 × 3 × 4 values" in err
    assert "whole frame(s) of 12" in err


def test_stack_cut_to_one_frame_and_one_frame_stacks(clean, tmp_path):
    d = _copy(clean, tmp_path)
    tifffile.imwrite(d / "1x.tif", _frames(1, 600, 700)[0], photometric="minisblack")
    with pytest.raises(
        EmccdcalError,
        match=r"acquisition 1 .*holds one image of 3 × 4 "
        r"pixels, not a stack of frames",
    ):
        read_manifest(d / "manifest.toml")
    tifffile.imwrite(d / "1x.tif", _frames(1, 600, 700)[:1], photometric="minisblack")
    with pytest.raises(
        EmccdcalError,
        match=r"acquisition 1 .*has 1 frame: a histogram of "
        r"a pixel's counts needs at least 2",
    ):
        read_manifest(d / "manifest.toml")


def test_tifffile_log_lines_do_not_reach_the_terminal(clean, tmp_path, capfd):
    # a damaged tag outside the frames: read in full, with one warning naming the file
    d = _copy(clean, tmp_path)
    raw = bytearray((d / "1x.tif").read_bytes())
    with tifffile.TiffFile(d / "1x.tif") as tif:
        software = tif.pages[0].tags["Software"]
        at = software.offset + 10  # the third byte of the tag's value offset
    raw[at] ^= 0x01  # now beyond the end of the file
    (d / "1x.tif").write_bytes(bytes(raw))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_manifest(d / "manifest.toml")
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    damaged = [str(w.message) for w in caught if "damaged TIFF" in str(w.message)]
    assert len(damaged) == 1 and "1x.tif" in damaged[0] and "read in full" in damaged[0]


# --------------------------------------------------------------------------------------
# The newer inputs: plan files, session records, Zarr settings, tools' settings files
# --------------------------------------------------------------------------------------
NEWER = settings(
    max_examples=int(os.environ.get("FUZZ_EXAMPLES", 150)),
    deadline=None,
    derandomize=not os.environ.get("FUZZ_EXAMPLES"),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
#: JSON-like values of every kind, nested a little.
JSONISH = st.recursive(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(10**30), 10**30),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=12),
    ),
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def _one_clear_error(exc, name):
    assert isinstance(exc, EmccdcalError), repr(exc)
    assert "\n" not in str(exc) and name in str(exc), str(exc)


@pytest.fixture(scope="module")
def a_plan(tmp_path_factory):
    from emccdcal.acquire.plan import plan
    from emccdcal.acquire.plan_file import plan_text

    d = tmp_path_factory.mktemp("plan")
    text = plan_text(
        plan(
            method="gs",
            e_per_adu=3.9,
            read_noise=15.0,
            offset=600.0,
            setpoints=[1, 5, 25],
            target_se=2.0,
        )
    )
    (d / "plan.toml").write_text(text)
    return d, text


@NEWER
@given(
    edits=st.lists(
        st.tuples(
            st.integers(0, 200),
            st.sampled_from(
                [
                    "",
                    "x",
                    "= 3",
                    "[[acquisition]]",
                    "frames = -1",
                    "frames = 99999999999999999999",
                    "em_gain_setpoint = 1",
                    "photoelectrons = 1e300",
                    'camera = "abc"',
                    "acquisition = [1,2]",
                    'adc_bits = "16"',
                    "e_per_adu = nan",
                    "[camera]",
                    "stages = 100000000",
                ]
            ),
        ),
        max_size=4,
    )
)
def test_edited_plans_predict_or_give_one_clear_error(a_plan, edits):
    from emccdcal.acquire.plan_file import read_plan

    folder, text = a_plan
    lines = text.splitlines()
    for at, line in edits:
        lines.insert(at % (len(lines) + 1), line)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "edited.toml"
        path.write_text("\n".join(lines) + "\n")
        try:
            p = read_plan(path)
        except Exception as exc:  # noqa: BLE001 - the property under test
            _one_clear_error(exc, "edited.toml")
            return
        assert all(a.frames >= 2 for a in p.acquisitions)


@NEWER
@given(
    state=st.dictionaries(
        st.sampled_from(["stacks", "runs", "plan_sha256", "status", "simulated", "roi"]),
        JSONISH,
        max_size=6,
    ),
    stack=st.dictionaries(
        st.sampled_from(["name", "file", "frames", "done", "reached_se"]), JSONISH, max_size=5
    ),
)
def test_session_records_load_or_give_one_clear_error(a_plan, state, stack):
    import json

    from emccdcal.acquire.plan_file import read_plan
    from emccdcal.acquire.session import SESSION_FILE, Session, stacks_of

    folder, _ = a_plan
    plan = read_plan(folder / "plan.toml")
    good = [
        {"name": s.name, "file": s.file, "frames": 0, "done": False, "reached_se": None}
        for s in stacks_of(plan)
    ]
    good[0].update(stack)
    state.setdefault("stacks", good)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        try:
            (tmp / SESSION_FILE).write_text(json.dumps(state))
        except ValueError:
            return
        try:
            session = Session.load(tmp, plan)
        except Exception as exc:  # noqa: BLE001 - the property under test
            _one_clear_error(exc, SESSION_FILE)
            return
        assert [s.file for s in session.stacks] == [s.file for s in stacks_of(plan)]


@NEWER
@given(
    record=st.dictionaries(
        st.sampled_from(
            [
                "em_gain_setpoint",
                "adc_bits",
                "roi",
                "binning",
                "serial",
                "readout_rate_mhz",
                "temperature_c",
                "exposure_ms",
            ]
        ),
        JSONISH,
        max_size=5,
    )
)
def test_zarr_settings_are_typed_or_one_clear_error(record):
    from emccdcal.data.settings import CameraSettings

    try:
        s = CameraSettings.from_record(record, "store.zarr")
    except Exception as exc:  # noqa: BLE001 - the property under test
        _one_clear_error(exc, "store.zarr")
        return
    if s.binning is not None:
        assert len(s.binning) == 2 and min(s.binning) >= 1
    if s.adc_bits is not None:
        assert isinstance(s.adc_bits, int) and 1 <= s.adc_bits <= 32


@pytest.fixture(scope="module")
def a_calibration(tmp_path_factory):
    from test_export import true_result

    from emccdcal.result import load_calibration

    return load_calibration(true_result(tmp_path_factory.mktemp("cal") / "r"))


@NEWER
@given(doc=JSONISH, yaml_text=st.booleans())
def test_tool_files_audit_or_give_one_clear_error(a_calibration, doc, yaml_text):
    import json

    import yaml

    from emccdcal.export.audit import audit

    doc = {"Cameras": {"cam": doc}} if isinstance(doc, dict) else doc
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("config.yaml" if yaml_text else "settings.json")
        try:
            path.write_text(yaml.safe_dump(doc) if yaml_text else json.dumps(doc))
        except (ValueError, yaml.YAMLError):
            return
        try:
            audit(path, a_calibration, setpoint=100)
        except Exception as exc:  # noqa: BLE001 - the property under test
            _one_clear_error(exc, path.name)
