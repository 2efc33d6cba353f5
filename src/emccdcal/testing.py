"""Batteries for plug-in authors: does my register model, reader or tool do what emccdcal
asks of one? (As :func:`scipy.stats` checks its distributions.)

Each check runs the plug-in through emccdcal's own code, the way a verb would, and raises
:class:`AssertionError` with one line saying what is wrong; it returns nothing where all
is well. A plug-in not installed is registered for the check's duration, in this process
(a test's, not a thread of a running calibration). emccdcal's own plug-ins pass them (its test suite runs them), so a test of a
plug-in package can be one line::

    from emccdcal.testing import check_register
    from mypackage.register import MyRegister

    def test_my_register():
        check_register(MyRegister)

- :func:`check_register`: the interface, the distribution of counts (it sums to one, its
  mean and variance are those the model's excess-noise factor says), the gain from g·F²,
  and the register's sampler against its own mean.
- :func:`check_reader`: the interface, and a sample file of its format read through
  emccdcal (header, settings, every frame).
- :func:`check_tool`: the interface, and a calibration exported with it, read back by the
  audit and found to agree with itself.
"""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path

import numpy as np

from . import plugins

__all__ = ["check_register", "check_reader", "check_tool"]


def _fit_for(group: str, obj, what: str) -> None:
    problem = plugins._problem(group, obj)
    assert not problem, f"{what} {problem}"


@contextlib.contextmanager
def _registered(group: str, name: str, obj):
    """``obj`` under ``name`` in the loaded plug-ins of ``group`` for the block (where
    it is not there already), as an installed package's would be."""
    loaded = plugins.load(group)
    added = name not in loaded
    if added:
        loaded[name] = obj
    try:
        yield
    finally:
        if added:
            loaded.pop(name, None)


def check_register(cls, *, stages: int = 64, seed: int = 0) -> None:
    """Check a register model class (an ``emccdcal.registers`` plug-in).

    Parameters
    ----------
    cls : type
        The class, made as ``cls(stages)``; its ``name`` is what ``--em-model`` takes.
    stages : int
        The register's length to check it at (for a model that uses stages).
    seed : int
        Seed of the sampler's draws.

    Raises
    ------
    AssertionError
        One line naming what is wrong.

    Examples
    --------
    >>> from emccdcal import plugins
    >>> check_register(plugins.load(plugins.REGISTERS)["cascade"])  # emccdcal's own
    """
    from .model import RegisterModel, RegisterRows, noise

    register = cls(stages)
    name = getattr(register, "name", None)
    _fit_for(plugins.REGISTERS, register, f"register model {name!r}:")
    assert isinstance(register, RegisterModel), f"{name!r}: not a RegisterModel"
    E, g, phi, offset, sigma = 6.0, 30.0, 4.0, 500.0, 4.0
    rows = register.rows(np.array([E]), np.array([g]), np.array([phi]))
    assert isinstance(rows, RegisterRows), f"{name!r}: its rows are not RegisterRows"
    with _registered(plugins.REGISTERS, name, cls):
        model = noise.EMModel(name, stages)  # another package's: its normalisation checked
        assert noise.EMModel.from_attrs(model.attrs) == model, f"{name!r}: attrs do not round-trip"
        counts = np.arange(300, 2400)
        p = noise.pmf(counts, E, g, phi, offset, sigma, em_model=model)
    total = float(p.sum())
    assert abs(total - 1) < 1e-6, f"{name!r}: the distribution of counts sums to {total:.8g}"
    mean = float(np.sum(counts * p))
    var = float(np.sum((counts - mean) ** 2 * p))
    F2 = float(register.excess_noise_factor(np.array(g)))
    want_mean, want_var = offset + E * g / phi, sigma**2 + E * F2 * (g / phi) ** 2
    assert abs(mean / want_mean - 1) < 1e-6, (
        f"{name!r}: the counts' mean is {mean:.8g}, not offset + E·g/φ = {want_mean:.8g}"
    )
    assert abs(var / want_var - 1) < 1e-6, (
        f"{name!r}: the counts' variance is {var:.8g}, not σ² + E·F²·(g/φ)² = {want_var:.8g}"
    )
    gain, _ = register.gain_from_gain_f2(np.array([g * F2]))
    assert abs(float(gain[0]) / g - 1) < 1e-9, f"{name!r}: gain_from_gain_f2 does not invert g·F²"
    electrons = np.full(20000, 5)
    out = np.asarray(register.sample(electrons, g, np.random.default_rng(seed)), dtype=float)
    se = np.sqrt(5 * F2 * g**2 / electrons.size)
    assert abs(out.mean() - 5 * g) < 5 * se, (
        f"{name!r}: its sampler's mean output of 5 electrons is {out.mean():.6g}, not 5·g = "
        f"{5 * g:.6g} (within {5 * se:.3g})"
    )


def check_reader(reader, path, frames=None) -> None:
    """Check a reader of camera files (an ``emccdcal.readers`` plug-in) on a sample file.

    Parameters
    ----------
    reader : module or object
        The reader: ``SUFFIXES``, ``header``, ``settings`` and, where ``header`` gives no
        data offset, ``open_stack``.
    path : str or Path
        A file of its format.
    frames : array_like (frames, rows, cols), optional
        What the file holds, to compare every frame read through emccdcal with.

    Raises
    ------
    AssertionError
        One line naming what is wrong (emccdcal's own error for the file, where it
        refuses it).

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from emccdcal import plugins
    >>> path = f"{tempfile.mkdtemp()}/stack.tif"
    >>> data = np.arange(2 * 3 * 4, dtype=np.uint16).reshape(2, 3, 4)
    >>> tifffile.imwrite(path, data)
    >>> check_reader(plugins.load(plugins.READERS)["tiff"], path, data)
    """
    from .data import stacks
    from .data.settings import CameraSettings
    from .errors import EmccdcalError

    path = Path(path)
    _fit_for(plugins.READERS, reader, "reader:")
    assert path.suffix.lower() in reader.SUFFIXES, (
        f"'{path}': its suffix is not one of the reader's {tuple(reader.SUFFIXES)}"
    )
    previous = stacks._READERS.get(path.suffix.lower())
    stacks._READERS[path.suffix.lower()] = reader
    try:
        try:
            shape, _ = stacks.stack_header(path)
            settings = stacks.stack_settings(path)
            data = np.asarray(stacks.load_stack(path))
        except EmccdcalError as exc:
            raise AssertionError(f"emccdcal refuses the file: {exc}") from None
    finally:
        if previous is None:
            stacks._READERS.pop(path.suffix.lower(), None)
        else:
            stacks._READERS[path.suffix.lower()] = previous
    assert isinstance(settings, CameraSettings), "its settings are not a CameraSettings"
    assert data.shape == tuple(shape), f"it reads {data.shape}, its header says {shape}"
    if frames is not None:
        want = np.asarray(frames)
        assert data.shape == want.shape, f"it reads {data.shape}, the file holds {want.shape}"
        assert np.array_equal(data, want), "the frames read are not those the file holds"


def check_tool(tool, calibration=None, *, setpoint=None) -> None:
    """Check a localization tool (an ``emccdcal.tools`` plug-in): its file, written from a
    calibration, read back by the audit, agrees with that calibration.

    Parameters
    ----------
    tool : emccdcal.plugins.Tool
        The tool.
    calibration : xarray.Dataset, Calibration, str or Path, optional
        A calibration to export (default: one of a small simulated gain series).
    setpoint : float, optional
        Its set-point to export at (where it has several).

    Raises
    ------
    AssertionError
        One line naming what is wrong.

    Examples
    --------
    >>> from emccdcal import plugins
    >>> check_tool(plugins.load(plugins.TOOLS)["thunderstorm"])  # doctest: +SKIP
    """
    import warnings

    from .errors import EmccdcalError
    from .export import audit, tools
    from .result import load_calibration

    _fit_for(plugins.TOOLS, tool, f"tool {getattr(tool, 'name', None)!r}:")
    with tempfile.TemporaryDirectory(prefix="emccdcal-check-tool-") as work:
        work = Path(work)
        if calibration is None:
            calibration, setpoint = _small_calibration(work), 10.0
        cal = load_calibration(calibration)
        with _registered(plugins.TOOLS, tool.name, tool), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # what a file cannot hold: the tool's to say
            written = tools.export(cal, tool.name, work / "out", setpoint=setpoint)
            assert written and all(Path(p).is_file() for p in written), (
                f"{tool.name!r}: wrote no file ({written})"
            )
            if tool.read is None and tool.read_file is None:
                return  # a tool the audit does not read
            s = None if tool.all_setpoints else tools.pick_setpoint(cal, setpoint)
            results, unread = [], []
            for p in written:  # a tool may write files the audit does not read (maps)
                try:
                    results += audit.audit(p, cal, setpoint=s or setpoint, tool=tool.name)
                except EmccdcalError as exc:
                    unread.append(str(exc))
        assert results, f"{tool.name!r}: the audit reads none of the files it wrote: {unread}"
        off = [line for a in results if not a.ok for line in a.lines()]
        assert not off, f"{tool.name!r}: its own file does not audit OK: {' / '.join(off)}"


def _small_calibration(work: Path):
    """A calibration of a small simulated gain series (1x and 10x)."""
    import warnings

    from .calibration import calibrate
    from .simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        work / "gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
