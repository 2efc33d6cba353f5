"""``emccdcal.testing``: the batteries offered to plug-in authors pass every plug-in of
emccdcal's own and the docs' example, and fail, in one line, the broken ones."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import tifffile

from emccdcal import plugins
from emccdcal.model._gamma import Gamma
from emccdcal.simulate.series import simulate_gain_series
from emccdcal.testing import check_reader, check_register, check_tool


@pytest.mark.parametrize("name", sorted(plugins.load(plugins.REGISTERS)))
def test_the_packages_own_registers_pass(name):
    check_register(plugins.load(plugins.REGISTERS)[name])


def test_a_register_written_from_the_interface_passes():
    from test_registers import Noiseless

    check_register(Noiseless)


class _Wider(Gamma):
    """The gamma register, claiming an excess noise it does not have."""

    name = "wider"

    def excess_noise_factor(self, g):
        return 1.1 * super().excess_noise_factor(g)


class _Halving(Gamma):
    """The gamma register, whose sampler gives half the electrons it should."""

    name = "halving"

    def sample(self, electrons, g, rng, **options):
        return 0.5 * np.asarray(super().sample(electrons, g, rng, **options))


@pytest.mark.parametrize(
    "cls, says", [(_Wider, "variance"), (_Halving, "sampler's mean")], ids=["F2", "sampler"]
)
def test_a_register_that_contradicts_itself_fails_in_one_line(cls, says):
    with pytest.raises(AssertionError, match=says) as caught:
        check_register(cls)
    assert "\n" not in str(caught.value)


def test_the_packages_readers_pass_on_files_of_their_formats(tmp_path):
    data = np.random.default_rng(1).integers(0, 4000, (3, 5, 4)).astype(np.uint16)
    readers = plugins.load(plugins.READERS)
    tifffile.imwrite(tmp_path / "stack.tif", data)
    np.save(tmp_path / "stack.npy", data)
    check_reader(readers["tiff"], tmp_path / "stack.tif", data)
    check_reader(readers["npy"], tmp_path / "stack.npy", data)
    with pytest.raises(AssertionError, match="not those the file holds"):
        check_reader(readers["tiff"], tmp_path / "stack.tif", data + 1)


def test_the_docs_example_reader_passes_and_a_lying_one_fails(tmp_path):
    import types

    from test_plugins import READER

    rawx = types.ModuleType("rawx")
    exec(compile(READER, "rawx.py", "exec"), rawx.__dict__)
    data = np.random.default_rng(2).integers(0, 4000, (4, 3, 5)).astype(np.uint16)
    rawx.write(tmp_path / "s.rawx", data, 25.0)
    check_reader(rawx, tmp_path / "s.rawx", data)
    lying = types.SimpleNamespace(**{k: getattr(rawx, k) for k in ("SUFFIXES", "settings")})
    size = rawx._HEAD.size
    lying.header = lambda path: ((4, 5, 3), np.dtype("<u2"), size, None)  # rows, cols swapped
    with pytest.raises(AssertionError, match=r"reads \(4, 5, 3\), the file holds \(4, 3, 5\)"):
        check_reader(lying, tmp_path / "s.rawx", data)


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    sim = simulate_gain_series(
        tmp_path_factory.mktemp("gs"),
        rows=4,
        cols=4,
        frames=400,
        setpoints=(1, 10),
        seed=3,
        progress=False,
    )
    from emccdcal import calibrate

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)


@pytest.mark.parametrize("name", sorted(plugins.load(plugins.TOOLS)))
def test_the_packages_own_tools_audit_their_own_files_ok(name, calibration):
    check_tool(plugins.load(plugins.TOOLS)[name], calibration, setpoint=10)


def test_a_tool_that_writes_a_wrong_number_fails(calibration):
    thunderstorm = plugins.load(plugins.TOOLS)["thunderstorm"]

    def write(cal, setpoint, values, out, *rest):
        values = {
            **values,
            "e_per_adu": {**values["e_per_adu"], "median": 2 * values["e_per_adu"]["median"]},
        }
        return thunderstorm.write(cal, setpoint, values, out, *rest)

    broken = dataclasses.replace(thunderstorm, name="broken-storm", write=write)
    with pytest.raises(AssertionError, match="does not audit OK"):
        check_tool(broken, calibration, setpoint=10)


def test_the_docs_example_tool_passes(calibration):
    import types

    from test_plugins import TOOL

    toyloc = types.ModuleType("toyloc")
    exec(compile(TOOL, "toyloc.py", "exec"), toyloc.__dict__)
    check_tool(toyloc.TOOL)  # as the docs' test of the package calls it
    check_tool(toyloc.TOOL, calibration, setpoint=10)
