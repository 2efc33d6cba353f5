"""Every command and Python example of README.md and docs/*.md, run as written.

The examples are read from the pages' fenced blocks: in ``sh``/``console``/plain blocks
each line that starts with ``emccdcal`` (or ``$ emccdcal``), joined ``&&`` commands
split; every ``python`` block. A page's examples run in order, in a copy of one small
world of simulated data named as the docs name it (``gs/``, ``out-adu``, ``out-gs``,
``darks-300x.tif``, ``movie.tif`` …), as a reader runs them: each page in one fresh
interpreter that has imported nothing (its Python blocks in order), each command through
the installed ``emccdcal`` command in its own process. A command
passes when it exits 0, or 1 (this command line's "a finding": a strict check, an audit
that is off, a flagged comparison), never 2 (a refused input or option) or with a
traceback. ``simulate`` commands get a small ``--frames``/``--rows``/``--cols`` where
they name none (``simulate beads``: one bead on the world's sensor, so that the world's
calibrations cover it): the docs show the verbs and options, not the data's size.

What cannot run here is listed in ``NOT_RUN`` with the reason (installs, real hardware,
a cluster, a GPU, placeholders such as ``RESULT``); the list is checked against the
pages, so that it cannot outlive the commands it excuses. The pages on the published
ProEM data run where ``../shared/data/lanl-proem`` is present.

The pages' runs (marker ``docs_examples``, a few minutes: three MCMC samplings, two
demos, several reports) are ``make test-docs``, which CI runs beside ``make test``.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import tifffile

import emccdcal
from emccdcal import cli

import camera_files
from conftest import console_script

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
pytestmark = pytest.mark.skipif(not (ROOT / "docs").is_dir(), reason="not a source tree")

# Commands that cannot run in a test, each with the reason; a key is the start of the
# command as the page writes it (after any "$ ", before its comment), or the whole of it
# where the key ends in "$".
NOT_RUN = {
    "make ": "the Makefile's own targets: CI runs `make test` and `make docs`, test_cli the demo",
    "pip install": "an install into the reader's environment",
    "emccdcal scan session/$": "the example plug-in package installed (tests/test_plugins.py "
    "builds it from docs/plugins.md and runs these commands)",
    "emccdcal calibrate session/manifest.toml -o result": "the example plug-in package",
    "emccdcal export result --to toyloc": "the example plug-in package",
    "emccdcal audit toyloc/toyloc.json": "the example plug-in package",
    "emccdcal calibrate gs/manifest.toml -m gs -o out --scheduler tcp://": "a Dask "
    "cluster at a named host (tests/test_streaming.py starts a local one)",
    "emccdcal calibrate gs/manifest.toml -m gs -o out --device cuda": "an NVIDIA GPU",
    "emccdcal validate BEAD_MANIFEST": "the command's synopsis, with placeholders",
    "emccdcal calibrate session/manifest.toml --method gs --e-per-adu RESULT": "a "
    "placeholder (RESULT) for the user's own φ",
    "emccdcal db list [--camera": "the command's synopsis ([optional] options)",
    "emccdcal db relocate 7 /new/place/out-gs": "a path that stands for the user's",
    "emccdcal posterior: refused": "a message the command prints, not a command",
    "emccdcal export out-em17 out-em10 out-conv3": "three read-out modes' calibrations "
    "(tests/test_export.py merges them)",
    "emccdcal report out-*/ --validation beads-out/": "a shell glob over the user's results",
    "echo $?": "the shell's, after the command above it",
    "emccdcal db add out-gs$": "stacks that record a camera serial (tests/test_export.py "
    "reads them from camera files); the world's simulated stacks record none",
}

# Python blocks that cannot run, by their first line, each with the reason.
NOT_RUN_PYTHON = {
    "from dask_jobqueue import SLURMCluster": "a SLURM cluster's batch system",
    "from emccdcal.data import stats": "a call's signature, each argument explained in "
    "its comment (tests/test_gof.py calls it)",
    "# tests/test_plugin.py of your package": "a test of the example plug-in package, "
    "which tests/test_testing.py runs on the page's tool",
}

# Commands run in another form here: a real camera's recording by the simulated camera.
STAND_IN = {
    "emccdcal acquire plan/plan.toml -o session/ --mm-config MMConfig.cfg --camera Andor": (
        "emccdcal acquire plan/plan.toml -o session/ --simulated --seed 1 --roi 0,0,16,16"
    ),
}


def _commands(block: str) -> list[tuple[int, str, list[str]]]:
    """``(line offset, command, shown output)`` of every emccdcal/make/pip line of a shell
    block; the output is what the block shows after a ``$ `` prompt's command, up to the
    next prompt."""
    out: list[tuple[int, str, list[str]]] = []
    prompt = False
    for i, line in enumerate(block.splitlines()):
        text = line.strip()
        if text.startswith("$ "):
            text, prompt = text[2:], True
        elif prompt and out and not text.startswith("emccdcal"):
            out[-1][2].append(text)  # what the command above printed
            continue
        if not text.startswith(("emccdcal", "make ", "pip install", "echo $?")):
            continue
        for part in text.split(" && "):
            out.append((i, part.strip(), []))
    return out


def examples(page: Path) -> list[tuple[int, str, str, list[str]]]:
    """``(line, kind, text, shown output)`` of the page's examples, in order: kind "shell"
    (one command) or "python" (a whole block)."""
    text = page.read_text(encoding="utf-8")
    found = []
    for m in re.finditer(r"^```([^\n]*)\n(.*?)^```", text, re.M | re.S):
        line = text.count("\n", 0, m.start()) + 2
        lang = m.group(1).strip()
        if lang == "python":
            found.append((line, "python", m.group(2), []))
        elif lang in ("sh", "bash", "console", "shell", ""):
            found += [(line + i, "shell", c, shown) for i, c, shown in _commands(m.group(2))]
    return found


def _normal(line: str, numbers: bool) -> str:
    """A printed line as compared: spaces collapsed, times of day and run times masked,
    and every number where the data differ from the page's (``numbers`` False)."""
    line = re.sub(r"\d+(\.\d+)? s\b", "# s", " ".join(line.split()))
    line = re.sub(r"\d{4}-\d\d-\d\dT[\d:]+Z?", "#", line)
    line = re.sub(r"/\S*/", "/", line)  # folders of the reader's machine
    return line if numbers else re.sub(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", "#", line)


def missing_output(shown: list[str], printed, numbers: bool) -> list[str]:
    """The lines a page shows for a command that it did not print, in order ("…" stands
    for lines left out). ``printed`` is the text, or the texts of the streams a terminal
    shows interleaved (stdout, stderr): each shown line is looked for in the order of its
    own stream, as a terminal keeps each stream's order but not their interleaving."""
    streams = [printed] if isinstance(printed, str) else list(printed)
    got = [[_normal(line, numbers) for line in text.splitlines()] for text in streams]
    at = [0] * len(got)
    missing = []
    for line in shown:
        if not line or line == "…":
            continue
        # "…" within a line stands for the words left out of it
        want = re.compile(".*".join(map(re.escape, _normal(line, numbers).split("…"))))
        for k, lines in enumerate(got):
            hit = next((j for j in range(at[k], len(lines)) if want.fullmatch(lines[j])), None)
            if hit is not None:
                at[k] = hit + 1
                break
        else:
            missing.append(line)
    return missing


def _stand_in(command: str) -> str:
    """The command as it runs here: itself, or its stand-in (a simulated camera for a
    real one)."""
    return next((other for key, other in STAND_IN.items() if command.startswith(key)), command)


def _excused(key: str, command: str) -> bool:
    """Whether a ``NOT_RUN`` key names the command (its comment left off)."""
    bare = command.split(" #")[0].strip()
    return bare == key[:-1] if key.endswith("$") else bare.startswith(key)


def _not_run(command: str) -> str | None:
    return next((why for key, why in NOT_RUN.items() if _excused(key, command)), None)


def test_every_excuse_still_names_a_command_of_the_docs():
    commands = [c for p in PAGES for _, kind, c, _ in examples(p) if kind == "shell"]
    blocks = [c.splitlines()[0] for p in PAGES for _, kind, c, _ in examples(p) if kind == "python"]
    stale = [key for key in NOT_RUN if not any(_excused(key, c) for c in commands)]
    stale += [key for key in STAND_IN if not any(c.startswith(key) for c in commands)]
    stale += [key for key in NOT_RUN_PYTHON if key not in blocks]
    assert not stale, f"NOT_RUN excuses commands no page shows any more: {stale}"
    assert sum(1 for p in PAGES for _ in examples(p)) > 100  # the reader finds the blocks


# The pages whose commands read the published ProEM folders (ADU/, gain-GS/).
ON_REAL_DATA = {"first-calibration.md", "formats.md", "index.md"}


# --- the world the docs' commands run in -------------------------------------------------

ROWS = COLS = 16  # the size the README simulates
FRAMES = 300
SMALL = f"--rows {ROWS} --cols {COLS} --frames {FRAMES}"


def _run(where: Path, command: str) -> None:
    """Run an emccdcal command line in ``where``; it must succeed."""
    here = os.getcwd()
    os.chdir(where)
    try:
        code = cli.main(shlex.split(command))
    finally:
        os.chdir(here)
    assert code == 0, f"making the docs' world: emccdcal {command} -> {code}"


def _manifest_at(src: Path, dst: Path) -> None:
    """A copy of the manifest ``src`` written at ``dst``, its paths made relative to it."""
    rel = os.path.relpath(src.parent, dst.parent)
    text = re.sub(
        r'^(\s*(?:frames|offset|read_noise|dark) = ")',
        rf"\g<1>{rel}/",
        src.read_text(encoding="utf-8"),
        flags=re.M,
    )
    dst.write_text(text, encoding="utf-8")


# The world's results and camera files, made by the command line itself.
WORLD = (
    f"""
simulate intensity-series -o adu --seed 1 {SMALL} --levels 2000,8000,32000
simulate gain-series -o gs --seed 2 {SMALL} --setpoints 1,5,25,50,100,300 --cic 0.05
simulate gain-series -o gs3 --seed 3 {SMALL} --setpoints 1,25,300
calibrate adu/manifest.toml --method is-adu -o out-adu -q
calibrate gs/manifest.toml --method gs --e-per-adu out-adu -o out-gs -q
calibrate gs/manifest.toml --method gs --e-per-adu out-adu --em-model gamma -o out-gamma -q
simulate beads -o beads --seed 5 --beads 4 --rows 48 --cols 48 --frames 30 --dark-frames 100
"""
    + "".join(  # is-gain results, one set-point each
        f"simulate intensity-series -o is-{s} --seed {10 + s} --setpoint {s} --levels 20,40,80 "
        f"{SMALL}\ncalibrate is-{s}/manifest.toml --method is-gain --e-per-adu out-adu "
        f"-o out-g{s} -q\n"
        for s in (5, 25, 100, 300)
    )
    + "".join(  # the camera's calibrations in the database, one read-out state
        f"db add {name} --camera 12345 --readout 'Electron Multiplying, 10 MHz, analog gain 2' "
        "--db home/calibrations.sqlite\n"
        for name in ("out-adu", "out-g5", "out-g25", "out-g100", "out-g300", "out-gamma")
    )
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The files and results the docs' examples name, on a small simulated camera: gain
    and intensity series with their results, manifests at the top (manifest.toml,
    gain.toml with three set-points for the posterior's example, adu.toml), dark stacks
    and movies that record their set-point (by name, by Micro-Manager's tags, SPE),
    a folder of camera files, beads, a Picasso configuration typed by hand and a
    calibration database of camera 12345."""
    w = tmp_path_factory.mktemp("docs-world")
    (w / "home").mkdir()
    for command in WORLD.strip().splitlines():
        _run(w, command)
    for name, src in (("manifest.toml", "gs"), ("gain.toml", "gs3"), ("adu.toml", "adu")):
        _manifest_at(w / src / "manifest.toml", w / name)
    shutil.copytree(w / "out-gs", w / "OUT")
    darks = tifffile.imread(w / "gs/gain-GS/300x-gain_no-signal.tif")
    tifffile.imwrite(w / "darks-300x.tif", darks)  # the set-point in its name
    camera_files.write_micromanager_tiff(w / "darks.tif", darks, em_gain=300)  # in its tags
    light = tifffile.imread(w / "gs/gain-GS/300x-gain.tif")
    movie = light.copy()
    movie[:, :8] = darks[: len(movie), :8]  # masked rows, as on a frame-transfer sensor
    camera_files.write_micromanager_tiff(w / "movie.tif", movie, em_gain=300)
    tifffile.imwrite(w / "movie-50x.tif", tifffile.imread(w / "gs/gain-GS/50x-gain.tif"))
    for name, g in (("movie.spe", 300), ("movie-50x.spe", 50)):
        camera_files.write_spe(w / name, light, em_gain=g)
    (w / "session").mkdir()  # a folder of camera files for scan
    for f in (w / "gs/gain-GS").glob("*.tif"):
        shutil.copy(f, w / "session" / f.name)
    # Picasso's settings as a user typed them: φ and the baseline right, the set-point in
    # its EM gain box
    baseline = float(emccdcal.load_result(w / "out-gs").offset.sel(setpoint=300).median())
    phi = float(emccdcal.load_result(w / "out-adu").e_per_adu.median())
    (w / "home/.picasso").mkdir()
    (w / "home/.picasso/config.yaml").write_text(
        f"Cameras:\n  ProEM:\n    Baseline: {baseline:.1f}\n    Sensitivity: {phi:.4f}\n",
        encoding="utf-8",
    )
    return w


def _small(argv: list[str]) -> list[str]:
    """A ``simulate`` command made small where it names no size."""
    if argv[:1] != ["simulate"]:
        return argv
    size = (
        (
            ("--frames", 30),
            ("--dark-frames", 100),
            ("--rows", ROWS),
            ("--cols", COLS),
            ("--beads", 1),
        )  # one bead on the world's sensor: its calibrations fit it
        if argv[1:2] == ["beads"]
        else (("--frames", FRAMES), ("--rows", ROWS), ("--cols", COLS))
    )
    return argv + [str(v) for flag, value in size if flag not in argv for v in (flag, value)]


def _output(argv: list[str]) -> Path | None:
    """Where a command writes (``-o``), if it says."""
    for flag in ("-o", "--out"):
        if flag in argv[:-1]:
            return Path(argv[argv.index(flag) + 1])
    return None


def _shell(command: str) -> list[str]:
    argv = shlex.split(command, comments=True)
    assert argv[0] == "emccdcal", command
    return _small(argv[1:])  # "~" is the page's reader's home: the runner expands it


def _steps(page: Path, items, work: Path) -> list[dict]:
    """The page's examples as the runner's steps (tests/docs_page_runner.py), in order:
    its Python blocks, and its commands with their arguments as they run here and what
    each must find removed before it (its output, where the world has a copy)."""
    steps, made, db_used = [], set(), False
    for item, (line, kind, text, _) in enumerate(items):
        where = f"{page.name}:{line}"
        if kind == "python":
            if text.splitlines()[0] not in NOT_RUN_PYTHON:
                steps.append({"item": item, "where": where, "kind": "python", "code": text})
            continue
        if text == "echo $?" or _not_run(text):
            continue
        argv = _shell(_stand_in(text))
        reset_db = argv[:2] == ["db", "add"] and not db_used  # the page starts its own
        db_used |= argv[0] == "db" or "--camera" in argv
        out = _output(argv)
        remove = None
        if out is not None and out not in made:  # the page makes it: not the world's copy
            remove, made = str(work / out), made | {out}
        steps.append(
            {"item": item, "where": where, "kind": "shell", "argv": argv, "remove": remove}
            | {"reset_db": reset_db}
        )
    return steps


@pytest.mark.slow
@pytest.mark.docs_examples
@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_examples_of_a_page_run_as_written(page, world, tmp_path, request):
    """The page's examples as its reader runs them: its Python blocks in order in one
    fresh interpreter that has imported nothing (tests/docs_page_runner.py), its commands
    through the installed ``emccdcal`` command, each in its own process."""
    items = examples(page)
    if not items:
        pytest.skip(f"{page.name} has no example")
    real = request.getfixturevalue("real_data") if page.name in ON_REAL_DATA else None
    work = tmp_path / "w"
    shutil.copytree(world, work)
    if real is not None:  # the published camera's folders, and a movie of it
        for name in ("ADU", "gain-GS"):
            shutil.copytree(real / name, work / name)
        if page.name == "first-calibration.md":  # its movie is of that camera, at 300x
            shutil.copy(real / "gain-GS/300x-gain.tif", work / "movie.tif")
    steps = _steps(page, items, work)
    files = ("steps.json", "results.json")  # beside the page's folder, not in it
    (tmp_path / files[0]).write_text(json.dumps(steps), encoding="utf-8")
    env = {
        **os.environ,
        "HOME": str(work / "home"),
        "EMCCDCAL_DB": str(work / "home" / "calibrations.sqlite"),
        "MPLBACKEND": "Agg",
    }
    for name in ("PYTHONPATH", "PYTHONSTARTUP"):  # nothing of the test's own set-up
        env.pop(name, None)
    runner = (Path(__file__).parent / "docs_page_runner.py").read_text(encoding="utf-8")
    done = subprocess.run(
        [sys.executable, "-c", runner, *(str(tmp_path / f) for f in files), console_script()],
        cwd=work,
        env={**env, "PWD": str(work)},
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, f"the page's runner failed: {done.stderr[-3000:]}"
    results = {r["item"]: r for r in json.loads((tmp_path / files[1]).read_text())}
    failures, seconds, code = [], [], None
    for item, (line, kind, text, shown) in enumerate(items):
        where = f"{page.name}:{line}"
        if text == "echo $?" and shown:  # the exit status the page shows
            if shown[0] != str(code):
                failures.append(f"{where}: the command above exited {code}, not {shown[0]}")
            continue
        if item not in results:  # not run here (NOT_RUN, NOT_RUN_PYTHON)
            continue
        r = results[item]
        if kind == "python":
            if r["error"]:
                failures.append(f"{where}: python block: {r['error']}")
            continue
        code = r["code"]
        seconds.append((r["seconds"], text))
        argv = _shell(_stand_in(text))
        exact = real is not None or argv[0] == "plan"  # the page's own data, or none
        lost = missing_output(shown, (r["out"], r["err"]), numbers=exact)
        if lost:
            failures.append(f"{where}: `{text}` did not print, as the page shows: {lost}")
        if code not in (0, 1):
            failures.append(f"{where}: `{text}` exited {code}: {r['err'].strip()[-600:]}")
    print("slowest:", *(f"{t:.1f} s {c}" for t, c in sorted(seconds)[::-1][:5]), sep="\n  ")
    assert not failures, "\n".join(failures)
