"""Plug-ins by entry points: another package adds a reader and a localization tool with
nothing changed in emccdcal, and ``scan``, ``calibrate``, ``export`` and ``audit`` use
them; a broken plug-in is left out with a warning and stops nothing.

The plug-in package is made here: its modules and its distribution metadata (the
``entry_points.txt`` that pip writes on installing it) in a folder put on ``PYTHONPATH``
of the commands, which is how Python finds an installed package's entry points.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import tifffile

from emccdcal.simulate.series import simulate_gain_series

DOCS_PAGE = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"
if not DOCS_PAGE.is_file():
    pytest.skip(
        "the example package is on docs/plugins.md: not a source tree", allow_module_level=True
    )


def _example(path: str) -> str:
    """The file ``path`` of docs/plugins.md's example package, as the page shows it."""
    text = DOCS_PAGE.read_text(encoding="utf-8")
    block = re.search(rf"^```\w+\n# {re.escape(path)}\n(.*?)^```", text, re.M | re.S)
    assert block, f"docs/plugins.md shows no {path}"
    return block.group(1)


READER, TOOL = _example("emccdcal_toy/rawx.py"), _example("emccdcal_toy/toyloc.py")
_PYPROJECT = _example("emccdcal-toy/pyproject.toml")
# the entry points pip writes from the page's pyproject.toml, and a broken one of ours
ENTRY_POINTS = (
    re.sub(r'\[project\.entry-points\."([\w.]+)"\]', r"[\1]", _PYPROJECT.split("\n\n", 1)[1])
    .replace('"', "")
    .replace("toyloc:TOOL\n", "toyloc:TOOL\nbroken = emccdcal_toy.missing:TOOL\n")
)


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    """The folder holding the installed toy plug-in package."""
    site = tmp_path_factory.mktemp("site")
    package = site / "emccdcal_toy"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "rawx.py").write_text(READER)
    (package / "toyloc.py").write_text(TOOL)
    (package / "napari.yaml").write_text(_example("emccdcal_toy/napari.yaml"))
    (package / "stages.py").write_text(_example("emccdcal_toy/stages.py"))
    info = site / "emccdcal_toy-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: emccdcal-toy\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(ENTRY_POINTS))
    return site


def _run(plugin, *args):
    """``python -m emccdcal ARGS`` in a fresh interpreter that has the plug-in package."""
    return _python(plugin, "-m", "emccdcal", *args)


def _python(plugin, *args):
    """``python ARGS`` in a fresh interpreter with the plug-in package on its path."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(plugin), *filter(None, [os.environ.get("PYTHONPATH")])]),
    }
    return subprocess.run(
        [sys.executable, *map(str, args)], capture_output=True, text=True, env=env, timeout=300
    )


def test_a_plugin_reader_and_tool_are_used_by_scan_calibrate_export_and_audit(plugin, tmp_path):
    sim = simulate_gain_series(
        tmp_path / "gs", rows=3, cols=4, frames=400, seed=21, setpoints=(1, 25), progress=False
    )
    sys.path.insert(0, str(plugin))
    try:
        from emccdcal_toy import rawx
    finally:
        sys.path.remove(str(plugin))
    session = tmp_path / "session"
    session.mkdir()
    for tif in sorted((sim.manifest.parent / "gain-GS").glob("*x-gain*.tif")):
        frames = tifffile.imread(tif)
        if frames.ndim == 3:  # not a map
            sp = float(re.match(r"(\d+)x", tif.name).group(1))
            kind = "dark" if "no-signal" in tif.name else "signal"
            rawx.write(session / f"{kind}-{int(sp * 7)}.rawx", frames, sp)

    done = _run(plugin, "scan", session)
    assert done.returncode == 0, done.stderr
    manifest = (session / "manifest.toml").read_text()
    assert len(re.findall(r'^(?:frames|dark) = "[\w-]+\.rawx"$', manifest, re.M)) == 4
    assert "set-points recorded in the files" in manifest

    result = tmp_path / "result"
    done = _run(
        plugin,
        "calibrate",
        session / "manifest.toml",
        "-m",
        "gs",
        "--e-per-adu",
        sim.truth["e_per_adu"],
        "--em-model",
        "gamma",
        "-o",
        result,
        "-q",
    )
    assert done.returncode == 0, done.stderr
    reference = tmp_path / "reference"
    done = _run(
        plugin, "calibrate", sim.manifest, "-m", "gs", "--em-model", "gamma", "-o", reference, "-q"
    )
    assert done.returncode == 0, done.stderr
    from emccdcal import load_result

    got, want = load_result(result), load_result(reference)
    np.testing.assert_allclose(got.em_gain.values, want.em_gain.values, rtol=1e-6)

    out = tmp_path / "toyloc"
    done = _run(plugin, "export", result, "--to", "toyloc", "-o", out, "--setpoint", 25)
    assert done.returncode == 0, done.stderr
    assert (out / "toyloc.json").is_file()
    # the broken plug-in is named, left out, and stops nothing
    assert (
        "plug-in 'broken' (emccdcal_toy.missing:TOOL, package 'emccdcal-toy') of "
        "emccdcal.tools: could not be loaded: ModuleNotFoundError"
    ) in done.stderr
    assert done.stderr.count("left out") == 1

    done = _run(plugin, "audit", out / "toyloc.json", "--calibration", result)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.startswith("ToyLoc: toyloc (set-point 25x)")
    assert "baseline_adu" in done.stdout


def test_without_the_plugin_its_files_and_tool_are_unknown(plugin, tmp_path):
    """The same commands without the package on the path: emccdcal knows neither."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "export",
            tmp_path,
            "--to",
            "toyloc",
            "-o",
            tmp_path / "x",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 2 and "invalid choice: 'toyloc'" in done.stderr


def test_napari_reads_what_the_packages_own_readers_read():
    """napari's manifest cannot ask the registry: its patterns are the package's own
    readers' suffixes (every one, in either case where it lists a case)."""
    from pathlib import Path

    import yaml

    import emccdcal
    from emccdcal import plugins

    manifest = yaml.safe_load(
        (Path(emccdcal.__file__).parent / "napari" / "napari.yaml").read_text()
    )
    patterns = manifest["contributions"]["readers"][0]["filename_patterns"]
    own = {
        s
        for r in plugins.load(plugins.READERS).values()
        if r.__name__.startswith("emccdcal.")
        for s in r.SUFFIXES
    }
    assert {p.removeprefix("*").lower() for p in patterns} == own


def test_an_installed_register_model_simulates_and_calibrates_from_the_command_line(
    plugin, tmp_path
):
    """The page's register model (a subclass of Register stating its transform only),
    installed as its package's entry point, is a choice of ``--multiplication`` and
    ``--em-model``: a series simulated with it from the command line calibrates with it
    from the command line, the result standing and every gain within 4 SE of the truth."""
    series, out = tmp_path / "gs", tmp_path / "out"
    model = ("poisson-stages", "--stages", "24")
    done = _run(
        plugin, "simulate", "gain-series", "-o", series, "--multiplication", *model,
        "--setpoints", "1,10,60", "--photoelectrons", "40", "--rows", "2", "--cols", "3",
        "--frames", "400", "--seed", "31", "-q",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = _run(plugin, "calibrate", series / "manifest.toml", "-m", "gs", "--em-model", *model,
                "-o", out, "-q")  # fmt: skip
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    code = (
        "import json, sys, numpy as np, emccdcal\n"
        "ds = emccdcal.load_result(sys.argv[1])\n"
        "truth = json.load(open(sys.argv[2]))\n"
        "want = np.array([a['em_gain'] for a in truth['acquisitions']])[:, None, None]\n"
        "z = np.abs(ds.em_gain.values - want) / ds.em_gain_se.values\n"
        "print(ds.attrs['em_model'], ds.attrs['register_stages'], ds.attrs['verdict'],\n"
        "      bool(np.nanmax(z) < 4))\n"
    )
    read = _python(plugin, "-c", code, out, series / "truth.json")
    assert read.stdout.split() == ["poisson-stages", "24", "stands", "True"], read.stderr


def test_napari_opens_a_plugin_readers_file_through_its_packages_manifest(plugin, tmp_path):
    """napari's plug-in manager (npe2), in a fresh interpreter with the example package
    installed, offers emccdcal-toy's manifest (and no other) for a .rawx file, and
    reading it gives the lazy stack emccdcal's reader makes."""
    pytest.importorskip("npe2")
    sys.path.insert(0, str(plugin))
    try:
        from emccdcal_toy import rawx
    finally:
        sys.path.remove(str(plugin))
    path = tmp_path / "dark-25.rawx"
    rawx.write(path, np.arange(2 * 3 * 4, dtype=np.uint16).reshape(2, 3, 4), 25.0)
    code = (
        "import sys, npe2\n"
        "pm = npe2.PluginManager.instance()\n"
        "pm.discover()\n"
        "print(sorted({r.plugin_name for r in pm.iter_compatible_readers([sys.argv[1]])}))\n"
        "data, meta, kind = npe2.read([sys.argv[1]], stack=False)[0]\n"
        "print(kind, tuple(data.shape), int(data[1].sum()), meta['metadata']['emccdcal_path'])\n"
    )
    done = _python(plugin, "-c", code, path)
    assert done.returncode == 0, done.stderr
    offered, read = done.stdout.splitlines()
    assert offered == "['emccdcal-toy']"
    assert read == f"image (2, 3, 4) {sum(range(12, 24))} {path}"


def test_without_registered_readers_a_file_says_why(monkeypatch, tmp_path):
    """A source tree used without installing it has no entry points: one clear line."""
    from emccdcal.data import stacks
    from emccdcal.errors import InputError

    monkeypatch.setattr(stacks, "_READERS", {})
    path = tmp_path / "a.tif"
    path.write_bytes(b"")
    with pytest.raises(InputError, match="no reader is registered.*pip install -e"):
        stacks._reader(path)


# --- broken and partial plug-ins, installed beside a working emccdcal ---------------------

BROKEN = {
    "half.py": '''
class Half:
    """A register model with 4 of its interface's members."""
    name = "half"
    uses_stages = False

    def __init__(self, stages):
        pass

    def rows(self, E, g, phi, cic=None):
        raise AssertionError("never reached: left out at load")

    def excess_noise_factor(self, g):
        return 2.0
''',
    "boom.py": 'raise RuntimeError("\\x1b[31mred\\x1b[0m\\nsecond line")\n',
    "tool.py": """
from emccdcal.plugins import Tool

def write(*args):
    raise AssertionError("never reached: the name is the package's own")

TOOL = Tool("picasso", "Not Picasso", write)
NO_WRITE = type("NoWrite", (), {"name": "nowrite", "title": "x", "read": None,
                                "recognizes": None})()
""",
    "shifted.py": """
from emccdcal.model._gamma import Gamma


class _Plus:
    \"\"\"Rows whose cumulant generating function is 5 too large: probabilities times e^5.\"\"\"

    def __init__(self, rows):
        self._rows = rows

    def __getattr__(self, name):
        return getattr(self._rows, name)

    def take(self, index):
        return _Plus(self._rows.take(index))

    def cgf(self, s, order=0, names=()):
        K, *rest = self._rows.cgf(s, order, names)
        return (K + 5.0, *rest)


class Shifted(Gamma):
    name = "shifted"

    def rows(self, *args, **kwargs):
        return _Plus(super().rows(*args, **kwargs))

    def rows_at(self, *args, **kwargs):
        return _Plus(super().rows_at(*args, **kwargs))
""",
    "odd.py": """
# Readers of toy files (.rawy, .rawz: 4 x 3 x 2 uint16 after 16 bytes) that make a
# mistake each: rawy gives its dtype as text (fine) and no offset, and opens an array of
# another shape; rawz gives its settings as a dict. A tool whose reader raises.
import numpy as np
from emccdcal.data.settings import CameraSettings
from emccdcal.plugins import Tool

SUFFIXES = (".rawy",)


def header(path):
    return (4, 3, 2), "<u2", None, None


def open_stack(path):
    return np.zeros((2, 3, 4), np.uint16)


def settings(path):
    return CameraSettings()


class Z:
    SUFFIXES = (".rawz",)

    @staticmethod
    def header(path):
        return (4, 3, 2), np.dtype("<u2"), 16, None

    @staticmethod
    def settings(path):
        return {"em_gain_setpoint": 5}


def _read(path, text, doc, setpoint, tool_gain):
    return doc["raising"]["missing"]


RAISING = Tool("raising", "Raising", lambda *a: [], _read,
               lambda path, text, doc: isinstance(doc, dict) and "raising" in doc)
""",
    "reader.py": """
SUFFIXES = (".tif",)

def header(path):
    raise AssertionError("never reached: the suffix is taken")

def settings(path):
    raise AssertionError("never reached")
""",
}

BROKEN_ENTRY_POINTS = """
[emccdcal.registers]
half = emccdcal_bad.half:Half
boom = emccdcal_bad.boom:Model

shifted = emccdcal_bad.shifted:Shifted

[emccdcal.tools]
picasso = emccdcal_bad.tool:TOOL
nowrite = emccdcal_bad.tool:NO_WRITE
raising = emccdcal_bad.odd:RAISING

[emccdcal.readers]
tif2 = emccdcal_bad.reader
rawy = emccdcal_bad.odd
rawz = emccdcal_bad.odd:Z
"""


@pytest.fixture(scope="module")
def broken(tmp_path_factory):
    """A folder holding a package of broken and partial plug-ins, and an older
    ``emccdcal-0.0.1.dist-info`` (no entry points) that stands before the real one."""
    site = tmp_path_factory.mktemp("broken-site")
    package = site / "emccdcal_bad"
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name, text in BROKEN.items():
        (package / name).write_text(text)
    info = site / "emccdcal_bad-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: emccdcal-bad\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(BROKEN_ENTRY_POINTS))
    stale = site / "emccdcal-0.0.1.dist-info"
    stale.mkdir()
    (stale / "METADATA").write_text("Metadata-Version: 2.1\nName: emccdcal\nVersion: 0.0.1\n")
    return site


@pytest.fixture(scope="module")
def small_series(tmp_path_factory):
    return simulate_gain_series(
        tmp_path_factory.mktemp("small"),
        rows=3,
        cols=4,
        frames=300,
        seed=22,
        setpoints=(1, 25),
        progress=False,
    )


def _calibrate_gamma(site, manifest, out):
    """``calibrate MANIFEST -m gs --em-model gamma -o OUT -q`` with ``site`` on the path."""
    return _run(site, "calibrate", manifest, "-m", "gs", "--em-model", "gamma", "-o", out, "-q")


def _lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip()]


def test_broken_plugins_leave_a_user_who_did_not_ask_for_them_unaffected(
    broken, small_series, tmp_path
):
    """Each broken plug-in is one escaped line naming what is wrong; the built-in
    readers, tools and models all work (an older emccdcal dist-info on the path hides
    none of them), and the numbers are those without the broken package."""
    done = _run(broken, "--version")
    assert done.stdout.strip() != "emccdcal 0.0.1" and done.returncode == 0
    out = tmp_path / "with"
    done = _calibrate_gamma(broken, small_series.manifest, out)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and "\x1b" not in done.stderr
    lines = _lines(done.stderr)
    assert all(line.startswith("warning: plug-in '") for line in lines), lines
    half = next(line for line in lines if "'half'" in line)
    assert "lacks parameters, misfit_hint, description, register_for" in half
    boom = next(line for line in lines if "'boom'" in line)
    assert "could not be loaded: RuntimeError: \\u001b[31mred" in boom and "\\n" in boom
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    ref = tmp_path / "without"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "calibrate",
            str(small_series.manifest),
            "-m",
            "gs",
            "--em-model",
            "gamma",
            "-o",
            str(ref),
            "-q",
        ],
        env=env,
        check=True,
        capture_output=True,
        timeout=300,
    )
    from emccdcal import load_result

    np.testing.assert_array_equal(load_result(out).em_gain.values, load_result(ref).em_gain.values)

    exported = tmp_path / "picasso"
    done = _run(broken, "export", out, "--to", "picasso", "-o", exported, "--setpoint", 25)
    assert done.returncode == 0, done.stderr
    tool = next(line for line in _lines(done.stderr) if "emccdcal_bad.tool:TOOL" in line)
    assert "the name is taken" in tool
    assert "lacks write" in next(line for line in _lines(done.stderr) if "'nowrite'" in line)
    assert list(exported.iterdir())  # the built-in Picasso wrote
    done = _run(
        broken, "scan", small_series.manifest.parent / "gain-GS", "-o", tmp_path / "scan.toml"
    )
    assert done.returncode == 0, done.stderr
    assert "suffix '.tif' is taken" in done.stderr


def test_a_partial_register_asked_for_is_refused_in_one_line_before_any_fitting(
    broken, small_series, tmp_path
):
    out = tmp_path / "out"
    done = _run(
        broken, "calibrate", small_series.manifest, "-m", "gs", "--em-model", "half", "-o", out
    )
    assert done.returncode == 2
    assert "Traceback" not in done.stderr and not out.exists()
    error = [line for line in _lines(done.stderr) if not line.startswith("warning:")]
    assert len(error) == 1, done.stderr
    assert "register model 'half' was left out" in error[0]
    assert "lacks parameters, misfit_hint, description, register_for" in error[0]
    done = _run(
        broken, "calibrate", small_series.manifest, "-m", "gs", "--em-model", "nothing", "-o", out
    )
    assert done.returncode == 2 and "invalid choice: 'nothing'" in done.stderr
    assert "half" not in done.stderr.split("invalid choice")[1]  # not offered


def test_the_python_api_names_what_a_left_out_register_lacks(broken, small_series):
    code = (
        "import warnings, emccdcal\n"
        "warnings.simplefilter('ignore')\n"
        "try:\n"
        f"    emccdcal.calibrate({str(small_series.manifest)!r}, 'gs', em_model='half')\n"
        "except emccdcal.EmccdcalError as e:\n"
        "    print(e)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(broken)}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "em_model 'half' was left out" in done.stdout and "lacks" in done.stdout


def test_what_a_plugin_gives_is_checked_before_use(broken, small_series, tmp_path):
    """A register whose distribution sums to e^5 (its gains unmoved, its log-likelihood
    off by 72 %), a reader whose array has another shape than its header says, one whose
    settings are a dict, a tool whose reader raises: each one line, exit 2."""
    done = _run(
        broken,
        "calibrate",
        small_series.manifest,
        "-m",
        "gs",
        "--em-model",
        "shifted",
        "-o",
        tmp_path / "o",
    )
    error = [line for line in _lines(done.stderr) if not line.startswith("warning:")]
    assert done.returncode == 2 and len(error) == 1, done.stderr
    assert "its distribution of counts sums to 148.413, not 1" in error[0]
    for suffix, says in (
        (".rawy", "opens an array of shape (2, 3, 4)"),
        (".rawz", "gives its settings as dict"),
    ):
        path = tmp_path / f"a{suffix}"
        path.write_bytes(bytes(16 + 4 * 3 * 2 * 2))
        done = _run(broken, "gain-check", path, "--e-per-adu", 3.9, "--setpoint", 5)
        error = [line for line in _lines(done.stderr) if not line.startswith("warning:")]
        assert done.returncode == 2 and len(error) == 1, done.stderr
        assert f"'{path}': " in error[0] and says in error[0], error
    settings = tmp_path / "raising.json"
    settings.write_text('{"raising": {}}')
    cal = tmp_path / "cal"
    done = _calibrate_gamma(broken, small_series.manifest, cal)
    assert done.returncode == 0, done.stderr
    done = _run(broken, "audit", settings, "--calibration", cal)
    error = [line for line in _lines(done.stderr) if not line.startswith("warning:")]
    assert done.returncode == 2 and len(error) == 1, done.stderr
    assert f"'{settings}': Raising cannot read it (KeyError: 'missing')" in error[0], error


def test_a_result_of_a_register_model_not_installed_loads_exports_and_applies(tmp_path):
    """A result fitted with another package's register model, read where that package is
    absent: its numbers need no model, so it loads, exports, applies and is reported;
    what would compute with the register refuses in one line naming the model."""
    import warnings

    import emccdcal
    from emccdcal import result
    from emccdcal.errors import OptionError

    sim = simulate_gain_series(
        tmp_path / "gs", rows=3, cols=3, frames=300, seed=31, setpoints=(1, 10), progress=False
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    ds.attrs.update(em_model="someone-elses-register", register_stages=600)
    result.save(ds, tmp_path / "theirs")

    loaded = emccdcal.load_result(tmp_path / "theirs")
    cal = emccdcal.load_calibration(loaded)
    assert str(cal.em_model) == "someone-elses-register (600 stages)"
    (config,) = emccdcal.export_calibration(cal, "picasso", tmp_path / "p", setpoint=10)
    assert "someone-elses-register" in config.read_text()  # its provenance, as recorded
    out = emccdcal.apply_calibration(
        loaded,
        sim.outdir / "gain-GS" / "10x-gain.tif",
        tmp_path / "e.tif",
        setpoint=10,
        progress=False,
    )
    assert tifffile.imread(out).shape == (300, 3, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # figures that need the register are left out
        report = emccdcal.write_report(loaded, tmp_path / "report.html", progress=False)
    assert "someone-elses-register (600 stages) (not installed here)" in report.read_text()
    with pytest.raises(OptionError, match="someone-elses-register.*not installed here"):
        cal.em_model.register  # noqa: B018 - what computes with it refuses
