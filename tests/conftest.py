"""Shared fixtures: the real camera data, a real-data manifest builder, the demo run.

The real ProEM data of Ryan et al. (2021) live outside the repository, in
``../shared/data/lanl-proem`` relative to the project root; they are read from there
and never copied. Tests that need them carry ``@pytest.mark.real_data`` and are skipped
cleanly where the data are absent.
"""

from __future__ import annotations

import io
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

#: The one place the real data's path is spelled.
REAL_DATA = (
    Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lanl-proem"
).resolve()

#: Gain set-points of the real gain series; levels of the real 1x intensity series.
REAL_SETPOINTS = (1, 5, 25, 100, 300)
REAL_LEVELS = tuple(range(1, 7))


# Hypothesis draws its examples from a fixed seed (derandomize): every run of the suite
# tests the same cases, in the same time; a failure is reproduced by running it again.
try:
    from hypothesis import settings as _hypothesis_settings

    _hypothesis_settings.register_profile(
        "emccdcal", derandomize=True, deadline=None, print_blob=True
    )
    _hypothesis_settings.load_profile("emccdcal")
except ImportError:  # hypothesis is a test dependency; without it those tests fail to import
    pass


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "real_data: needs ../shared/data/lanl-proem (skipped where absent)"
    )


#: Test files that run the verbs end to end (simulated or real stacks through files,
#: subprocesses, kills, a viewer, a browser): the whole of each is marked ``slow``, so
#: ``make test-fast`` runs the library's own tests (models, fits, readers, the command
#: line's parsing) and ``make test`` everything. A test elsewhere that takes more than
#: about 2 s carries ``@pytest.mark.slow`` itself.
END_TO_END = frozenset(
    {
        "test_acquire.py",
        "test_audit.py",
        "test_browser.py",
        "test_chaining.py",
        "test_export.py",
        "test_faults.py",
        "test_first_calibration.py",
        "test_formats.py",
        "test_fuzz.py",
        "test_gain_check.py",
        "test_guarantees.py",
        "test_napari.py",
        "test_new_user.py",
        "test_plan.py",
        "test_plugins.py",
        "test_reliability.py",
        "test_report.py",
        "test_streaming.py",
        "test_validation.py",
    }
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in END_TO_END:
            item.add_marker(pytest.mark.slow)
    if REAL_DATA.is_dir():
        return
    skip = pytest.mark.skip(reason=f"real ProEM data not present ({REAL_DATA})")
    for item in items:
        if "real_data" in item.keywords:
            item.add_marker(skip)


def console_script(name: str = "emccdcal") -> str:
    """The installed command ``name`` of this environment (``emccdcal``, ``dask``), as a
    user's shell finds it once the environment is active."""
    path = Path(sys.executable).parent / name
    if not path.is_file():
        pytest.skip(f"no '{name}' command beside {sys.executable}")
    return str(path)


def kill_at_random(argv, n, check, rng):
    """SIGKILL ``emccdcal argv`` at ``n`` random moments of its run, ``check()`` holding
    after each; returns (runs killed, runs that finished before their moment). ``argv``
    may be a function giving each run's (a run that resumes what the killed one left).

    Decided from what happened, never from a timing guess that load could upset: one
    whole run is timed; each later run is killed after a random delay within that time
    (past the end of its imports, where a kill tests more than a kill of nothing), and a
    kill counts only where it landed (the run ended by the signal, not by finishing).
    A run that finished first (the machine quieter than when timed) narrows the moments
    to before its own, and another is started: the test ends with ``n`` kills landed
    (at most ``5 n`` runs), however busy the machine."""

    def command():
        return [sys.executable, "-m", "emccdcal", *map(str, argv() if callable(argv) else argv)]

    t0 = time.perf_counter()
    subprocess.run([*command()[:3], "--version"], check=True, stdout=subprocess.DEVNULL)
    started = time.perf_counter() - t0
    t0 = time.perf_counter()
    subprocess.run(command(), check=True, stdout=subprocess.DEVNULL)
    whole = time.perf_counter() - t0
    check()
    low, high = min(started, 0.5 * whole), 0.97 * whole
    kills = finished = 0
    while kills < n and kills + finished < 5 * n:
        delay = rng.uniform(min(low, 0.5 * high), high)
        proc = subprocess.Popen(command(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)  # a no-op on a process that ended (not yet reaped)
        if proc.wait() == -signal.SIGKILL:
            kills += 1
        else:
            assert proc.returncode == 0, f"{command()}: exited {proc.returncode} before its kill"
            finished += 1
            high = 0.7 * delay
        check()
    assert kills == n, f"{command()}: {kills} of {n} kills landed in {kills + finished} runs"
    return kills, finished


def run_measured(argv, **kw):
    """``emccdcal argv`` in its own process, as a user runs it: (the completed process,
    its peak resident memory in bytes). The peak is measured, not guessed: a fresh
    interpreter waits for the command and reads its child's ``ru_maxrss``."""
    code = (
        "import resource, subprocess, sys\n"
        "done = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
        "sys.stdout.write(done.stdout); sys.stderr.write(done.stderr)\n"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, file=sys.stderr)\n"
        "sys.exit(done.returncode)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, sys.executable, "-m", "emccdcal", *map(str, argv)],
        capture_output=True,
        text=True,
        **kw,
    )
    *lines, peak = done.stderr.rstrip("\n").split("\n")
    done.stderr = "\n".join(lines) + ("\n" if lines else "")
    return done, int(peak)


def quiet(fn, *args, **kw):
    """``fn(*args, **kw)`` with its warnings silenced (those are not what a test checks)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kw)


def write_real_manifest(directory, kind, *, setpoints=REAL_SETPOINTS):
    """A manifest of the real data in ``directory``: ``"gs"`` (the gain series with its ADU
    map) or ``"adu"`` (the 1x intensity series, levels L1-L6). Returns its path."""
    lines = []
    if kind == "gs":
        lines.append(f'e_per_adu = "{REAL_DATA}/gain-GS/ADU_map.tif"')
        for g in setpoints:
            lines += [
                "[[acquisition]]",
                f'frames = "{REAL_DATA}/gain-GS/{g}x-gain.tif"',
                f"em_gain_setpoint = {g}",
                f'offset = "{REAL_DATA}/gain-GS/{g}x-gain_no-signal_S0.tif"',
                f'read_noise = "{REAL_DATA}/gain-GS/{g}x-gain_no-signal_sigma.tif"',
            ]
    elif kind == "adu":
        for level in REAL_LEVELS:
            lines += [
                "[[acquisition]]",
                f'frames = "{REAL_DATA}/ADU/1x-gain_level-0{level}.tif"',
                "em_gain_setpoint = 1",
                f'level = "L{level}"',
                f'offset = "{REAL_DATA}/ADU/1x-gain_no-signal_S0.tif"',
                f'read_noise = "{REAL_DATA}/ADU/1x-gain_no-signal_sigma.tif"',
            ]
    else:
        raise ValueError(f"unknown kind {kind!r}")
    path = Path(directory) / f"{kind}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="session")
def real_data():
    """The real data's folder (the test is skipped where it is absent)."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real ProEM data not present ({REAL_DATA})")
    return REAL_DATA


#: The demo of the session: a tiny sensor, not square (a transposed map would not fit).
DEMO_ROWS, DEMO_COLS, DEMO_FRAMES = 4, 3, 300


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``run_demo`` of a tiny sensor with its report, once per test session:
    ``({"adu", "gs", "outdir", "report"}, what it printed)``."""
    from emccdcal.demo import run_demo

    printed = io.StringIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # chance non-stationarity findings of tiny series
        run = run_demo(
            tmp_path_factory.mktemp("demo") / "demo",
            rows=DEMO_ROWS,
            cols=DEMO_COLS,
            frames=DEMO_FRAMES,
            seed=5,
            report=True,
            out=printed,
        )
    return run, printed.getvalue()
