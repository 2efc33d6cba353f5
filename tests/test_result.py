"""The result dataset, its files (calibration.nc, summary.json), and their checks."""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pytest
import xarray as xr

import emccdcal
from emccdcal.errors import EmccdcalError
from emccdcal._output import write_netcdf
from emccdcal import result
from emccdcal.result import format_setpoint, load, make_dataset, save, summarize

HASH = "3f" * 32
SETPOINTS = [1, 5, 25, 100, 300]
R, C = 3, 4


def gs_dataset(**overrides):
    """A gain-series-like result with one non-converged outlier pixel at (2, 3)."""
    rng = np.random.default_rng(0)
    gains = np.array(SETPOINTS, float)[:, None, None] * np.ones((1, R, C))
    gains[1:] *= rng.uniform(0.9, 0.95, size=(4, R, C))
    gain_se = np.where(gains == 1, 0.0, 0.01 * gains)
    conv = np.ones((R, C), bool)
    conv[2, 3] = False
    E = rng.normal(370, 2, size=(R, C))
    E[2, 3] = 1e6  # must not reach the summary statistics
    kw = dict(
        method="gs",
        setpoints=SETPOINTS,
        e_per_adu=3.859,
        e_per_adu_se=0.0,
        em_gain=gains,
        em_gain_se=gain_se,
        photoelectrons=E,
        photoelectrons_se=np.full((R, C), 1.5),
        loglik=rng.normal(-4e4, 10, size=(R, C)),
        converged=conv,
        manifest_hash=HASH,
        manifest_path="/data/run/manifest.toml",
        extra={
            "offset": (("setpoint", "row", "col"), rng.normal(580, 5, (5, R, C)), "ADU"),
            "n_saturated": (
                ("setpoint", "row", "col"),
                np.zeros((5, R, C), np.int64),
                "1",
                "frames at the ADC maximum, excluded",
            ),
        },
        attrs={"skip_frames": 1000, "fixed_e_per_adu": True},
    )
    kw.update(overrides)
    return make_dataset(**kw)


def is_dataset():
    rng = np.random.default_rng(1)
    return make_dataset(
        method="mv-adu",
        levels=["L1", "L2", "L3"],
        e_per_adu=rng.normal(3.8, 0.05, (R, C)),
        e_per_adu_se=np.full((R, C), 0.04),
        photoelectrons=rng.uniform(100, 3000, (3, R, C)),
        photoelectrons_se=np.full((3, R, C), 10.0),
        converged=True,
        manifest_hash=HASH,
    )


# --------------------------------------------------------------------------------------
# make_dataset
# --------------------------------------------------------------------------------------
def test_dataset_layout_units_and_attributes():
    ds = gs_dataset()
    assert dict(ds.sizes) == {"row": R, "col": C, "setpoint": 5}
    assert ds.setpoint.values.tolist() == [1.0, 5.0, 25.0, 100.0, 300.0]
    assert ds.setpoint.dtype == np.float64
    assert ds.em_gain.dims == ("setpoint", "row", "col")
    assert ds.photoelectrons.dims == ("row", "col")
    assert ds.converged.dtype == bool and ds.converged.dims == ("row", "col")
    for name in ("e_per_adu", "adu_per_e", "em_gain", "photoelectrons"):
        assert name + "_se" in ds
    for name, var in ds.variables.items():  # data variables and coordinates
        assert isinstance(var.attrs.get("units"), str), name
        assert var.attrs.get("long_name"), name
    assert ds.e_per_adu.attrs["units"] == "e-/ADU"
    assert ds.adu_per_e.attrs["units"] == "ADU/e-"
    assert ds.em_gain.attrs["units"] == "1"
    assert ds.photoelectrons.attrs["units"] == "e-"
    assert ds.loglik.attrs["units"] == "nat"
    assert ds.offset.attrs["units"] == "ADU"
    assert ds.n_saturated.attrs["long_name"] == "frames at the ADC maximum, excluded"
    np.testing.assert_allclose(ds.adu_per_e, 1 / 3.859)
    np.testing.assert_array_equal(ds.em_gain.sel(setpoint=1), 1.0)
    np.testing.assert_array_equal(ds.em_gain_se.sel(setpoint=1), 0.0)
    a = ds.attrs
    assert a["method"] == "gs" and a["emccdcal_version"] == emccdcal.__version__
    assert a["manifest_sha256"] == HASH
    assert a["manifest_path"] == "/data/run/manifest.toml"
    created = dt.datetime.fromisoformat(a["created"].replace("Z", "+00:00"))
    assert created.utcoffset() == dt.timedelta(0)
    assert "e-/ADU" in a["units_note"]
    assert a["skip_frames"] == 1000 and a["fixed_e_per_adu"] == 1  # bool stored as 0/1


def test_loglik_absent_is_nan_and_levels_dims():
    ds = is_dataset()
    assert ds.photoelectrons.dims == ("level", "row", "col")
    assert ds.level.values.tolist() == ["L1", "L2", "L3"]
    assert np.isnan(ds.loglik).all()
    assert "em_gain" not in ds
    assert ds.converged.all()


def test_photoelectrons_dims_rule():
    E3 = np.full((5, R, C), 40.0)
    base = dict(
        method="is-gain",
        e_per_adu=3.8,
        e_per_adu_se=0.0,
        converged=True,
        manifest_hash=HASH,
        photoelectrons_se=1.0,
    )
    ds = make_dataset(setpoints=SETPOINTS, photoelectrons=E3, **base)
    assert ds.photoelectrons.dims == ("setpoint", "row", "col")
    # both coordinates given: a 3-D array is ambiguous unless the dims are named
    with pytest.raises(ValueError, match="pass photoelectrons_dims"):
        make_dataset(setpoints=SETPOINTS, levels=list("abcde"), photoelectrons=E3, **base)
    ds = make_dataset(
        setpoints=SETPOINTS,
        levels=list("abcde"),
        photoelectrons=E3,
        photoelectrons_dims=("level", "row", "col"),
        **base,
    )
    assert ds.photoelectrons.dims == ("level", "row", "col")
    E4 = np.full((5, 2, R, C), 40.0)
    ds = make_dataset(
        setpoints=SETPOINTS,
        levels=["a", "b"],
        photoelectrons=E4,
        photoelectrons_dims=("setpoint", "level", "row", "col"),
        **base,
    )
    assert ds.photoelectrons_se.shape == (5, 2, R, C)
    with pytest.raises(ValueError, match="conflicting sizes for dimension 'setpoint'"):
        make_dataset(setpoints=SETPOINTS, photoelectrons=E3[:4], **base)


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"e_per_adu": np.ones((C, R))}, "sizes for dimension 'row'.*'e_per_adu'"),
        ({"em_gain": np.ones((4, R, C))}, "sizes for dimension 'setpoint'.*'em_gain'"),
        ({"setpoints": None}, "em_gain needs setpoints"),
        ({"setpoints": [1, 5, 5, 100, 300]}, "distinct"),
        ({"converged": np.ones((R, C + 1), bool)}, "sizes for dimension 'col'.*'converged'"),
        ({"loglik": np.ones(R)}, "Variable 'loglik'"),
        ({"manifest_hash": "abc"}, "manifest_hash"),
        ({"attrs": {"method": "x"}}, "cannot be replaced"),
        ({"attrs": {"bad": {"a": 1}}}, "attribute 'bad'"),
        ({"extra": {"e_per_adu": (("row", "col"), np.ones((R, C)), "1")}}, "clashes"),
        (
            {"extra": {"offset": (("setpoint", "row", "col"), np.ones((2, R, C)), "ADU")}},
            "sizes for dimension 'setpoint'.*'offset'",
        ),
        ({"extra": {"offset": (("row", "col"), np.ones((R, C)))}}, "must be"),
        ({"em_gain_se": None}, "together"),
    ],
)
def test_make_dataset_validation(overrides, message):
    with pytest.raises(ValueError, match=message):
        gs_dataset(**overrides)


def test_unit_gain_must_be_one():
    ds = gs_dataset()
    bad = ds.em_gain.values.copy()
    bad[0, 0, 0] = 1.02
    with pytest.raises(ValueError, match="set-point 1 must be 1"):
        gs_dataset(em_gain=bad)


def test_origin_sets_sensor_coordinates():
    ds = gs_dataset(origin=(64, 128))
    assert ds.row.values.tolist() == [64, 65, 66]
    assert ds.col.values.tolist() == [128, 129, 130, 131]


# --------------------------------------------------------------------------------------
# format_setpoint and summarize
# --------------------------------------------------------------------------------------
def test_format_setpoint():
    assert format_setpoint(5.0) == "5"
    assert format_setpoint(5) == "5"
    assert format_setpoint(np.float32(300.0)) == "300"
    assert format_setpoint(1.5) == "1.5"
    assert format_setpoint(0.1) == "0.1"
    assert format_setpoint(1e6) == "1000000"
    with pytest.raises(ValueError):
        format_setpoint(float("nan"))


def test_summary_keys_and_converged_only():
    ds = gs_dataset()
    s = summarize(ds, seconds=2.5)
    json.dumps(s, allow_nan=False)  # serialisable, no NaN
    assert s["method"] == "gs" and s["manifest_sha256"] == HASH
    assert s["emccdcal_version"] == emccdcal.__version__
    assert s["seconds"] == 2.5
    assert s["pixels"] == {"total": R * C, "converged": R * C - 1, "rows": R, "cols": C}
    assert "converged" in s["statistics_over"]
    params = s["parameters"]
    assert set(params) == {
        "e_per_adu",
        "adu_per_e",
        "em_gain",
        "photoelectrons",
        "loglik",
        "offset",
        "n_saturated",
    }
    assert list(params["em_gain"]["by_setpoint"]) == ["1", "5", "25", "100", "300"]
    assert list(params["offset"]["by_setpoint"]) == ["1", "5", "25", "100", "300"]
    conv = ds.converged.values
    E = params["photoelectrons"]
    assert E["units"] == "e-" and E["n"] == R * C - 1
    assert E["mean"] == pytest.approx(ds.photoelectrons.values[conv].mean())
    assert E["sd"] == pytest.approx(ds.photoelectrons.values[conv].std(ddof=1))
    assert E["median"] == pytest.approx(np.median(ds.photoelectrons.values[conv]))
    assert E["se_median"] == 1.5
    g5 = params["em_gain"]["by_setpoint"]["5"]
    assert g5["mean"] == pytest.approx(ds.em_gain.sel(setpoint=5).values[conv].mean())
    assert params["em_gain"]["by_setpoint"]["1"]["se_median"] == 0.0
    assert "se_median" not in params["loglik"]


def test_summary_leaves_out_interval_bounds():
    """Bounds may be infinite (a Fieller interval open above): per pixel only."""
    ds = gs_dataset()
    ds["photoelectrons_lower"] = ds.photoelectrons - 3.0
    ds["photoelectrons_upper"] = ds.photoelectrons.where(ds.photoelectrons < 0, np.inf)
    s = summarize(ds)
    assert "photoelectrons_lower" not in s["parameters"]
    assert "photoelectrons_upper" not in s["parameters"]
    json.dumps(s, allow_nan=False)


def test_summary_levels_and_missing_values():
    ds = is_dataset()
    s = summarize(ds)
    assert s["seconds"] is None
    assert list(s["parameters"]["photoelectrons"]["by_level"]) == ["L1", "L2", "L3"]
    ll = s["parameters"]["loglik"]
    assert ll["n"] == 0 and ll["mean"] is None  # all NaN → null, not NaN
    json.dumps(s, allow_nan=False)


# --------------------------------------------------------------------------------------
# save / load
# --------------------------------------------------------------------------------------
def test_round_trip(tmp_path):
    ds = gs_dataset()
    paths = save(ds, tmp_path / "out" / "nested", seconds=1.25)
    assert paths == {
        "calibration": tmp_path / "out/nested/calibration.nc",
        "summary": tmp_path / "out/nested/summary.json",
    }
    back = load(paths["calibration"])
    xr.testing.assert_identical(back, ds)  # values, dims, coords, attrs (units) alike
    assert back.converged.dtype == bool
    assert back.n_saturated.dtype == np.int64
    xr.testing.assert_identical(load(tmp_path / "out/nested"), ds)  # a directory works
    summary = json.loads(paths["summary"].read_text())
    assert summary == json.loads(json.dumps(summarize(ds, seconds=1.25)))
    assert not [p for p in paths["calibration"].parent.iterdir() if p.name.startswith(".")]
    # a loaded result can be saved again, over itself
    save(back, tmp_path / "out" / "nested")
    xr.testing.assert_identical(load(tmp_path / "out/nested"), ds)


def test_round_trip_levels(tmp_path):
    ds = is_dataset()
    save(ds, tmp_path)
    back = load(tmp_path)
    xr.testing.assert_identical(back, ds)
    assert back.level.values.tolist() == ["L1", "L2", "L3"]


def test_interrupted_netcdf_write_keeps_the_old_file(tmp_path, monkeypatch):
    old = gs_dataset(method="gs-no1x")
    paths = save(old, tmp_path)
    before_nc = paths["calibration"].read_bytes()
    before_json = paths["summary"].read_bytes()

    def write_half_then_fail(self, path, *args, **kwargs):
        with open(path, "wb") as fh:
            fh.write(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
        raise KeyboardInterrupt  # as if the user hit ctrl-C mid-write

    monkeypatch.setattr(xr.Dataset, "to_netcdf", write_half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        save(gs_dataset(), tmp_path)
    assert paths["calibration"].read_bytes() == before_nc
    assert paths["summary"].read_bytes() == before_json
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.nc", "summary.json"]
    monkeypatch.undo()
    assert load(tmp_path).attrs["method"] == "gs-no1x"


def test_interrupted_write_leaves_no_partial_file(tmp_path, monkeypatch):
    def fail(self, path, *args, **kwargs):
        with open(path, "wb") as fh:
            fh.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", fail)
    with pytest.raises(EmccdcalError, match="disk full"):  # one line, the file named
        save(gs_dataset(), tmp_path / "out")
    assert list((tmp_path / "out").iterdir()) == []


def test_interrupted_summary_write_keeps_the_old_summary(tmp_path, monkeypatch):
    paths = save(gs_dataset(method="gs-no1x"), tmp_path)
    before_json = paths["summary"].read_bytes()
    real_write_text = type(tmp_path).write_text

    def fail(self, text, *args, **kwargs):
        real_write_text(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError("interrupted")

    monkeypatch.setattr(type(tmp_path), "write_text", fail)
    with pytest.raises(EmccdcalError, match="interrupted"):
        save(gs_dataset(), tmp_path)
    assert paths["summary"].read_bytes() == before_json
    assert json.loads(before_json)["method"] == "gs-no1x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.nc", "summary.json"]


def test_load_rejects_netcdf_that_is_not_ours(tmp_path):
    path = tmp_path / "other.nc"
    xr.Dataset({"t": ("x", np.arange(3.0))}).to_netcdf(path, engine="h5netcdf")
    with pytest.raises(ValueError, match=r"other\.nc.*not an emccdcal result file"):
        load(path)
    write_netcdf(xr.Dataset({"t": ("x", np.arange(3.0))}), path)  # checksummed, not a result
    with pytest.raises(ValueError, match=r"other\.nc.*not an emccdcal calibration result"):
        load(path)


def test_load_rejects_missing_variables(tmp_path):
    ds = gs_dataset().drop_vars("loglik")
    path = tmp_path / "calibration.nc"
    write_netcdf(ds, path)
    with pytest.raises(ValueError, match=r"calibration\.nc.*missing variables: loglik"):
        load(path)


def test_load_rejects_other_major_version(tmp_path):
    ds = gs_dataset()
    ds.attrs["emccdcal_version"] = "99.0.0"
    path = tmp_path / "calibration.nc"
    write_netcdf(ds, path)
    with pytest.raises(ValueError, match=r"calibration\.nc.*99\.0\.0.*not compatible"):
        load(path)


def test_load_rejects_non_netcdf_and_missing_files(tmp_path):
    path = tmp_path / "calibration.nc"
    path.write_text("not a netcdf file\n")
    with pytest.raises(ValueError, match=r"calibration\.nc.*not an emccdcal result file"):
        load(path)
    with pytest.raises(FileNotFoundError, match="nothing.nc"):
        load(tmp_path / "nothing.nc")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="calibration.nc"):
        load(tmp_path / "empty")


def test_version_major_parsing():
    assert result.schema._major("1.2.3") == 1
    assert result.schema._major("0+unknown") == 0
    assert result.schema._major("dev") is None


def test_docs_results_md_names_every_standard_variable():
    from pathlib import Path

    doc = Path(__file__).parents[1] / "docs" / "results.md"
    text = doc.read_text(encoding="utf-8")
    for name in (
        "e_per_adu",
        "adu_per_e",
        "em_gain",
        "photoelectrons",
        "loglik",
        "converged",
        "setpoint",
        "level",
        "calibration.nc",
        "summary.json",
    ):
        assert f"`{name}" in text, name
    for units in set(result.UNITS.values()):
        assert f"`{units}`" in text, units
