"""The full-sensor engine: tiles, one pass over the data, resumable runs, Dask, bad pixels."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from conftest import console_script, quiet

from emccdcal import calibrate, cli, result
from emccdcal.errors import OptionError
from emccdcal.runstore import RUN_DIR
from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    base = tmp_path_factory.mktemp("streaming")
    gs = simulate_gain_series(
        base / "gs", rows=12, cols=10, frames=300, seed=7, setpoints=(1, 5, 25, 100)
    )
    adu = simulate_intensity_series(
        base / "adu", rows=12, cols=10, frames=300, seed=8, levels=(2000, 8000, 32000)
    )
    return gs.manifest, adu.manifest


@pytest.fixture(scope="module")
def long_run(tmp_path_factory):
    """A series whose calibration, one row per tile, takes a few seconds: long enough to
    be interrupted after its first tiles, whatever the machine's speed."""
    base = tmp_path_factory.mktemp("long")
    return simulate_gain_series(
        base / "gs", rows=12, cols=10, frames=1000, seed=9, setpoints=(1, 5, 25, 100)
    ).manifest


def _assert_same(a, b, rtol=1e-12):
    assert set(a.data_vars) == set(b.data_vars)
    for name in a.data_vars:
        x, y = a[name].values, b[name].values
        if x.dtype.kind == "f":
            ok = np.isfinite(x)
            np.testing.assert_array_equal(ok, np.isfinite(y), err_msg=name)
            np.testing.assert_allclose(x[ok], y[ok], rtol=rtol, atol=0, err_msg=name)
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.attrs.get("quality") == b.attrs.get("quality")


# gs-hierarchical under the gamma model, 4x cheaper: the tiling is the same for both
# models, and gs shows the default (the exact register) does not depend on it either
@pytest.mark.parametrize(
    "method, which, model",
    [
        ("gs", 0, None),
        ("is-adu", 1, None),
        ("mv-gain", 0, None),
        pytest.param("gs-hierarchical", 0, "gamma", marks=pytest.mark.slow),
    ],
)
def test_tiles_and_workers_do_not_change_the_result(series, method, which, model):
    manifest = series[which]
    one = quiet(
        calibrate, manifest, method, block_size=8, tile_pixels=120, workers=1, em_model=model
    )
    many = quiet(
        calibrate, manifest, method, block_size=8, tile_pixels=16, workers=2, em_model=model
    )
    _assert_same(one, many)
    if method == "gs-hierarchical":  # three fits in one: the two runs above suffice
        return
    rows = quiet(
        calibrate, manifest, method, block_size=8, tile_pixels=10, workers=3, em_model=model
    )
    _assert_same(one, rows)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """A Dask cluster started as its documentation says, by the ``dask`` commands of this
    environment: a scheduler on 127.0.0.1 and two worker processes of one thread each.
    Nothing of it lives in the test's process; it is stopped at the end."""
    pytest.importorskip("distributed")
    dask = console_script("dask")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = tmp_path_factory.mktemp("dask-logs")
    commands = [
        [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
        [dask, "worker", address, "--nworkers", "2", "--nthreads", "1", "--no-dashboard"],
    ]
    started = []
    try:
        for i, command in enumerate(commands):
            with open(logs / f"{i}.log", "wb") as log:
                started.append(
                    subprocess.Popen(
                        command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
                    )
                )
            if i == 0:
                _wait_for_port(port, started[0], logs / "0.log")
        _wait_for_workers(address, 2)
        yield address
    finally:
        # As a user ends a cluster (Client.shutdown: the scheduler closes its workers and
        # itself in a fraction of a second); the `dask worker` command then lingered 8 s
        # before exiting: after a grace period its session (it and its worker processes)
        # is killed, so that nothing of the cluster outlives the tests.
        if len(started) == 2:
            _shutdown(address)
        for process in reversed(started):
            process.terminate()
        for process in reversed(started):
            try:
                process.wait(timeout=2)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(process.pid, signal.SIGKILL)
                except ProcessLookupError:  # it and its workers ended meanwhile
                    pass
                process.wait()


def _wait_for_port(port, process, log, limit=120.0):
    import socket

    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"dask scheduler exited: {log.read_text()[-2000:]}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.2)
    pytest.fail(f"dask scheduler did not listen within {limit:.0f} s")


def _scheduler_state(address, function):
    """``function(dask_scheduler)`` run on the scheduler, from a client made for it and
    closed at once (never while a run under test is going)."""
    import distributed

    with distributed.Client(address, timeout="60s", set_as_default=False) as client:
        return client.run_on_scheduler(function)


def _shutdown(address):
    import distributed

    try:
        with distributed.Client(address, timeout="10s", set_as_default=False) as client:
            client.shutdown()
    except (OSError, TimeoutError):
        pass  # the processes are terminated anyway


def _wait_for_workers(address, n):
    import distributed

    with distributed.Client(address, timeout="60s", set_as_default=False) as client:
        client.wait_for_workers(n, timeout=180)


# The tiles the scheduler's workers have computed (the prefix counts the tasks that ever
# reached each state); a lambda, pickled by value: the scheduler cannot import this module
_tiles_run = lambda dask_scheduler: getattr(  # noqa: E731
    dask_scheduler.task_prefixes.get("run_tile"), "state_counts", {}
).get("memory", 0)


@pytest.mark.slow
def test_a_dask_cluster_started_by_the_dask_commands_gives_the_local_result(
    series, dask_cluster, tmp_path
):
    """``emccdcal calibrate --scheduler tcp://...`` from the command line and
    ``calibrate(scheduler=...)`` in a fresh interpreter, neither holding a client of its
    own: the tiles run on the cluster and the numbers are the local ones."""
    local = quiet(calibrate, series[0], "gs", block_size=16, tile_pixels=32)
    tiles = -(-local.sizes["row"] * local.sizes["col"] // 32)
    before = _scheduler_state(dask_cluster, _tiles_run)
    cli_out = tmp_path / "cli"
    run = subprocess.run(
        [
            console_script(),
            "calibrate",
            str(series[0]),
            "-m",
            "gs",
            "-o",
            str(cli_out),
            "--block-size",
            "16",
            "--tile-pixels",
            "32",
            "--scheduler",
            dask_cluster,
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    after_cli = _scheduler_state(dask_cluster, _tiles_run)
    assert after_cli - before == tiles  # the scheduler ran every tile
    py_out = tmp_path / "py"
    code = (
        "import emccdcal, sys\n"
        f"ds = emccdcal.calibrate({str(series[0])!r}, 'gs', block_size=16, tile_pixels=32, "
        f"scheduler={dask_cluster!r}, out={str(py_out)!r})\n"
        "assert 'distributed' not in sys.modules or "
        "not __import__('distributed').client._global_clients\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert _scheduler_state(dask_cluster, _tiles_run) - after_cli == tiles
    for out in (cli_out, py_out):
        _assert_same(local, result.load(out), rtol=1e-9)


@pytest.mark.slow
def test_local_processes_give_the_local_result(series, tmp_path):
    """``scheduler="processes"``: the tiles in two spawned processes, one thread each,
    written and resumable as any run; the numbers those of the threads here."""
    local = quiet(calibrate, series[0], "gs", block_size=16, tile_pixels=32)
    apart = quiet(
        calibrate,
        series[0],
        "gs",
        block_size=16,
        tile_pixels=32,
        scheduler="processes",
        workers=2,
        out=tmp_path / "out",
    )
    _assert_same(local, apart)
    assert (tmp_path / "out" / "calibration.nc").is_file()


def test_a_large_sensor_goes_to_local_processes_by_default():
    """Where the caller names no scheduler, a sensor of 4096 pixels or more in at least
    two tiles per worker runs in local processes (faster than threads on the same
    cores: docs/benchmarks.md); a small one, one worker, a GPU, or a daemonic process
    (a pool's worker, which may not start processes) keep threads here; a caller's
    choice always stands, ``"threads"`` included."""
    import multiprocessing

    from emccdcal.calibration.schedulers import choose_scheduler

    sensor = 512 * 512
    assert choose_scheduler(None, sensor, 256, 2, "cpu") == "processes"
    assert choose_scheduler(None, 64 * 64, 4, 2, None) == "processes"
    assert choose_scheduler(None, 32 * 32, 4, 2, "cpu") is None  # too small to pay
    assert choose_scheduler(None, sensor, 3, 2, "cpu") is None  # too few tiles
    assert choose_scheduler(None, sensor, 256, 1, "cpu") is None
    assert choose_scheduler(None, sensor, 256, 2, "cuda") is None
    assert choose_scheduler("threads", sensor, 256, 2, "cpu") is None
    assert choose_scheduler("tcp://127.0.0.1:8786", sensor, 256, 2, "cpu") == (
        "tcp://127.0.0.1:8786"
    )
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        in_a_worker = pool.apply(choose_scheduler, (None, sensor, 256, 2, "cpu"))
    assert in_a_worker is None


@pytest.mark.slow
def test_a_script_without_a_main_guard_calibrates_in_local_processes(series, tmp_path):
    """A user's script that calls calibrate at its top level, with no
    ``if __name__ == "__main__":`` (a notebook exported as a script has none), run in a
    fresh interpreter with the tiles in two local processes: the workers do not run the
    script again (a spawned process imports its parent's script first), so it starts
    once, finishes, and writes the local result."""
    script = tmp_path / "calibrate_my_camera.py"
    out = tmp_path / "out"
    script.write_text(
        "import warnings\n"
        "from emccdcal import calibrate\n"
        "print('script started', flush=True)\n"
        "warnings.simplefilter('ignore')\n"
        f"calibrate({str(series[0])!r}, 'gs', block_size=16, tile_pixels=32,\n"
        f"          scheduler='processes', workers=2, out={str(out)!r}, progress=False)\n"
        "print('script finished', flush=True)\n"
    )
    run = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.count("script started") == 1, run.stdout
    assert run.stdout.count("script finished") == 1, run.stdout
    local = quiet(calibrate, series[0], "gs", block_size=16, tile_pixels=32)
    _assert_same(local, result.load(out))


def test_an_occupied_output_is_refused_without_resume_or_overwrite(series, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["calibrate", str(series[0]), "-o", str(out), "-q", "--no-checks"]
    assert cli.main(argv) == 0
    from emccdcal.report.html import write_report

    write_report([out], out / "report.html")  # the old run's report
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "finished result" in err and "--overwrite" in err
    assert cli.main(argv + ["--overwrite"]) == 0
    assert not (out / "report.html").exists()  # nothing of the old run is left beside it
    assert sorted(p.name for p in out.iterdir()) == ["calibration.nc", "summary.json"]
    # a report.html made by hand is the user's: never removed
    (out / "report.html").write_text("<html>my own notes</html>")
    assert cli.main(argv + ["--overwrite"]) == 0
    assert (out / "report.html").read_text() == "<html>my own notes</html>"
    (out / "report.html").unlink()
    assert cli.main(argv + ["--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err


def test_an_unwritable_output_is_found_before_any_computing(series, tmp_path, capsys, monkeypatch):
    from emccdcal import calibration

    def computed(*args, **kwargs):  # decided by what ran, not by how long it took
        raise AssertionError("a tile was computed before the output was found unwritable")

    monkeypatch.setattr(calibration.schedulers, "run_tile", computed)
    monkeypatch.setattr(calibration.profiling, "run_tile", computed)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert cli.main(["calibrate", str(series[0]), "-o", str(blocker / "out"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "cannot write the output directory" in err and err.count("\n") == 1


def _run(argv, **kw):
    # A shell without job control starts background jobs with SIGINT ignored, and Python
    # then installs no KeyboardInterrupt handler: give the child the default back.
    return subprocess.Popen(
        [sys.executable, "-m", "emccdcal", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        **kw,
    )


def _wait_for_tiles(out, n, proc, timeout=120):
    t0 = time.perf_counter()
    while len(list((out / RUN_DIR).glob("tile-*.npz"))) < n:
        assert proc.poll() is None, proc.communicate()
        assert time.perf_counter() - t0 < timeout
        time.sleep(0.05)


@pytest.mark.slow
def test_a_killed_run_resumes_to_the_uninterrupted_result(long_run, tmp_path):
    manifest = long_run
    argv = ["calibrate", str(manifest), "-q", "--tile-pixels", "10", "--block-size", "8"]
    whole = tmp_path / "whole"
    assert _run(argv + ["-o", str(whole)]).wait() == 0
    out = tmp_path / "killed"
    proc = _run(argv + ["-o", str(out)])
    _wait_for_tiles(out, 2, proc)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    kept = len(list((out / RUN_DIR).glob("tile-*.npz")))
    assert 2 <= kept < 12 and not (out / "calibration.nc").exists()
    again = _run(argv + ["-o", str(out)])
    assert again.wait() == 2 and "--resume" in again.stderr.read()
    changed = _run(argv + ["-o", str(out), "--resume", "--no-checks"])
    assert changed.wait() == 2 and "checks" in changed.stderr.read()
    # Mark one kept tile: a resumed run that reuses it carries the mark into the result;
    # one that recomputed every tile would not.
    marked = sorted((out / RUN_DIR).glob("tile-*.npz"))[0]
    with np.load(marked) as f:
        arrays = {k: f[k] for k in f.files}
    first_pixel = int(marked.stem.split("-")[2])
    arrays["photoelectrons"] = arrays["photoelectrons"].copy()
    arrays["photoelectrons"][0] *= 1.5
    with open(marked, "wb") as fh:
        np.savez(fh, **arrays)
    resumed = _run(argv + ["-o", str(out), "--resume"])
    assert resumed.wait() == 0, resumed.stderr.read()
    assert sorted(p.name for p in out.iterdir()) == ["calibration.nc", "summary.json"]
    a, b = result.load(whole), result.load(out)
    row, col = divmod(first_pixel, a.sizes["col"])
    assert float(b.photoelectrons[row, col]) == pytest.approx(
        1.5 * float(a.photoelectrons[row, col]), rel=1e-12
    )  # the kept tile was used
    b["photoelectrons"][row, col] = a.photoelectrons[row, col]
    b.attrs["quality"] = a.attrs["quality"]  # its findings quote the light the doctored tile moved
    _assert_same(a, b)
    a = json.loads((whole / "summary.json").read_text())
    b = json.loads((out / "summary.json").read_text())
    assert a["parameters"]["em_gain"] == b["parameters"]["em_gain"]


@pytest.mark.slow
def test_ctrl_c_says_what_is_kept_and_exits_130(long_run, tmp_path):
    out = tmp_path / "out"
    proc = _run(
        [
            "calibrate",
            str(long_run),
            "-q",
            "--tile-pixels",
            "10",
            "--block-size",
            "8",
            "-o",
            str(out),
        ]
    )
    _wait_for_tiles(out, 1, proc)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    code = proc.wait()
    err = proc.stderr.read().strip().splitlines()
    assert code == 130 and len(err) == 1, err
    assert "tiles kept in" in err[0] and "--resume" in err[0]


@pytest.mark.slow
def test_bad_pixels_are_left_out_named_and_the_run_completes(tmp_path):
    sim = simulate_gain_series(
        tmp_path / "gs", rows=32, cols=32, frames=100, seed=3, setpoints=(1, 5, 25)
    )
    stacks = {s: sim.outdir / f"gain-GS/{s}x-gain.tif" for s in ("1", "25")}
    data = tifffile.imread(stacks["25"])
    data[:, 3, 4] = 65535  # saturated in every frame of one stack
    tifffile.imwrite(stacks["25"], data)
    data = tifffile.imread(stacks["1"])
    data[:, 9, 2] = 0  # dead: never changes
    tifffile.imwrite(stacks["1"], data)
    with pytest.warns(UserWarning) as caught:
        ds = calibrate(
            sim.manifest, "gs", out=tmp_path / "out", checks=False, tile_pixels=256
        )  # four tiles
    text = [str(w.message) for w in caught]
    left_out = [t for t in text if "left out" in t]
    assert len(left_out) == 1 and "2 of 1024 pixel(s)" in left_out[0]
    assert "(3, 4)" in left_out[0] and "(9, 2)" in left_out[0]
    assert not ds.converged.values[3, 4] and not ds.converged.values[9, 2]
    assert np.isnan(ds.em_gain.values[:, 3, 4]).all() and np.isnan(ds.photoelectrons.values[9, 2])
    n_converged = int(ds.converged.values.sum())
    assert 1022 - 10 <= n_converged <= 1022  # every other pixel is fitted (≥ 99 % converge)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["pixels"]["converged"] == n_converged


def test_resume_and_overwrite_are_exclusive_and_checked(series, tmp_path):
    with pytest.raises(OptionError, match="not both"):
        calibrate(series[0], "gs", out=tmp_path / "o", resume=True, overwrite=True)
    with pytest.raises(OptionError, match="tile_pixels"):
        calibrate(series[0], "gs", tile_pixels=0)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_the_check_verb_reads_in_bands_and_agrees_with_the_calibration(series):
    from emccdcal import check, read_manifest

    ds = quiet(calibrate, series[0], "gs", tile_pixels=16, block_size=8)
    report = quiet(check, quiet(read_manifest, series[0]))
    calibrated = json.loads(ds.attrs["quality"])["acquisitions"]
    fitted = float(ds.photoelectrons.where(ds.converged).median())

    def without_light(acqs):  # calibrate's findings quote the light its fit found
        return {
            k: {
                f: v
                for f, v in a.items()
                if f
                not in (
                    "photoelectrons_estimate",
                    "photoelectrons_source",
                    "drift_absorbed",
                    "estimate_relative_se",
                )
            }
            for k, a in acqs.items()
        }

    assert without_light(calibrated) == without_light(report["acquisitions"])
    for a in calibrated.values():
        assert a["photoelectrons_source"] == "fit"
        assert a["photoelectrons_estimate"] == pytest.approx(fitted, rel=1e-9)


def test_no_temporary_files_are_left(series, tmp_path):
    out = tmp_path / "out"
    quiet(calibrate, series[0], "gs", out=out, tile_pixels=16, block_size=8)
    leftovers = [p for p in Path(out).rglob("*") if p.name.startswith(".")]
    assert leftovers == [] and not (out / RUN_DIR).exists()
    assert sorted(os.listdir(out)) == ["calibration.nc", "summary.json"]


@pytest.mark.parametrize("kind", ["tif", "npy-big-endian"])
@pytest.mark.parametrize("per_call", [1, 3, 100])
def test_read_band_reads_exactly_the_rows_of_the_memory_map(tmp_path, kind, per_call, monkeypatch):
    from emccdcal.data import stacks
    from emccdcal.data.stacks import load_stack, read_band

    monkeypatch.setattr(stacks, "_READ_BYTES", per_call * 5 * 6 * 2)  # whole frames per call
    data = np.random.default_rng(0).integers(0, 60000, (7, 5, 6)).astype(np.uint16)
    if kind == "tif":
        path = tmp_path / "s.tif"
        tifffile.imwrite(path, data)
    else:
        path = tmp_path / "s.npy"
        np.save(path, data.astype(">u2"))
    for rows, skip in (((0, 5), 0), ((1, 3), 2), ((4, 5), 6)):
        band = read_band(path, *rows, skip)
        np.testing.assert_array_equal(band, np.asarray(load_stack(path))[skip:, rows[0] : rows[1]])
        assert band.dtype == load_stack(path).dtype


def test_read_band_of_a_truncated_stack_is_one_clear_error(tmp_path):
    from emccdcal.data.stacks import read_band
    from emccdcal.errors import InputError

    path = tmp_path / "s.tif"
    tifffile.imwrite(path, np.zeros((50, 8, 8), np.uint16))
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size // 4)  # inside the data of the frames
    with pytest.raises(InputError, match=r"s\.tif") as exc:
        read_band(path, 0, 8)
    assert "\n" not in str(exc.value)
    # the header's promise is checked against the file's size before any data are read
    from emccdcal.data.stacks import _raw_layout

    full = tmp_path / "full.tif"
    tifffile.imwrite(full, np.zeros((50, 8, 8), np.uint16))
    whole = (path.stat().st_size - _raw_layout(full)[2]) // (8 * 8 * 2)
    assert str(exc.value).endswith(
        f"truncated: its header describes 50 × 8 × 8 values of 2 "
        f"bytes from byte 256, 6656 bytes, but the file has "
        f"{path.stat().st_size}: {whole} whole frame(s) of 50"
    )


def test_removing_a_run_removes_only_what_a_run_wrote(tmp_path):
    """remove_run acts on a run directory only where emccdcal's fingerprint marks it, and
    there on the tiles and temporaries a run writes, never on a user's file."""
    from emccdcal.runstore import RunStore, remove_run

    users = tmp_path / "users" / RUN_DIR
    users.mkdir(parents=True)
    (users / "tile-pixels-000000000-000000010.npz").write_bytes(b"mine")
    (users / "fingerprint.json").write_text("{}")  # not emccdcal's
    remove_run(users.parent)
    assert sorted(p.name for p in users.iterdir()) == [
        "fingerprint.json",
        "tile-pixels-000000000-000000010.npz",
    ]
    out = tmp_path / "out"
    store = RunStore(out, {"emccdcal_version": "test", "method": "gs"})
    store.save_tile("pixels-000000000-000000010", {"x": np.zeros(3)})
    (out / RUN_DIR / "notes.txt").write_text("a user's")
    (out / RUN_DIR / "tile-mine.npz").write_bytes(b"a user's, named like a tile")
    remove_run(out)
    assert sorted(p.name for p in (out / RUN_DIR).iterdir()) == ["notes.txt", "tile-mine.npz"]


def _children(pid: int) -> set[int]:
    """The processes whose parent is ``pid`` (from /proc: nothing needed beyond Linux)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _gone(pids, limit) -> set[int]:
    """Those of ``pids`` still alive after waiting up to ``limit`` s for them to end."""
    deadline = time.monotonic() + limit
    alive = set(pids)
    while alive and time.monotonic() < deadline:
        alive = {p for p in alive if Path(f"/proc/{p}").exists() and not _zombie(p)}
        time.sleep(0.1)
    return alive


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return False


@pytest.fixture(scope="module")
def longer_run(tmp_path_factory):
    """24 tiles of 10 pixels: two local processes are still busy after the first."""
    base = tmp_path_factory.mktemp("longer")
    return simulate_gain_series(
        base / "gs", rows=24, cols=10, frames=1000, seed=9, setpoints=(1, 5, 25, 100)
    ).manifest


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc (Linux)")
@pytest.mark.parametrize("stop", ["ctrl-c", "sigkill"])
def test_local_processes_stop_with_their_parent(longer_run, tmp_path, stop):
    """``--scheduler processes``: Ctrl-C stops the run in seconds (it waited a minute
    for the workers' tiles) with what was kept said, and a parent killed outright takes
    its workers with it (they ran on, re-parented). Decided from the processes that
    are there, with bounds of seconds, not from timings."""
    out = tmp_path / "out"
    argv = ["calibrate", str(longer_run), "-q", "--tile-pixels", "10", "--block-size", "8"]
    proc = _run([*argv, "--scheduler", "processes", "--workers", "2", "-o", str(out)])
    _wait_for_tiles(out, 1, proc, timeout=300)
    workers = _children(proc.pid)
    assert len(workers) >= 2, workers  # the two workers (and the resource tracker)
    assert proc.poll() is None, "the run ended before it could be stopped"
    if stop == "ctrl-c":
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=15)
        err = proc.stderr.read().strip().splitlines()
        assert code == 130 and len(err) == 1 and "--resume" in err[0], err
    else:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=15)
    assert not _gone(workers, 15), "workers outlived their parent"


@pytest.fixture
def listener():
    """A TCP listener on 127.0.0.1 that is not a Dask scheduler: one that says nothing
    until asked (a web server), or one that greets with its own banner (an SSH server).
    Yields a function: the kind → its address."""
    import socket
    import threading

    servers, stop = [], threading.Event()

    def serve(server, banner):
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn:
                if banner:
                    conn.sendall(banner)
                stop.wait(2.0)

    def start(kind):
        server = socket.socket()
        server.bind(("127.0.0.1", 0))
        server.listen()
        servers.append(server)
        banner = b"SSH-2.0-OpenSSH_9.6\r\n" if kind == "banner" else b""
        threading.Thread(target=serve, args=(server, banner), daemon=True).start()
        return f"tcp://127.0.0.1:{server.getsockname()[1]}"

    yield start
    stop.set()
    for server in servers:
        server.close()


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["silent", "banner", "inproc", "ws-refused"])
def test_a_scheduler_that_is_not_dask_is_one_line_in_seconds(series, listener, tmp_path, kind):
    """What is not a Dask scheduler is refused in one line within 20 s, through the
    installed command: a listener that says nothing, one that greets as another server
    (Dask read its bytes as a length of exabytes: 66 lines), an address of another
    process's memory (inproc://), a WebSocket address where nothing listens."""
    pytest.importorskip("distributed")
    address = {
        "silent": lambda: listener("silent"),
        "banner": lambda: listener("banner"),
        "inproc": lambda: "inproc://127.0.0.1/1/1",
        "ws-refused": lambda: f"ws://127.0.0.1:{_free_port()}",
    }[kind]()
    argv = [console_script(), "calibrate", str(series[0]), "-q", "-o", str(tmp_path / "o")]
    done = subprocess.run(
        [*argv, "--scheduler", address], capture_output=True, text=True, timeout=20
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr[-2000:]
    assert lines[0].startswith(f"emccdcal calibrate: error: scheduler '{address}'"), lines
    assert not (tmp_path / "o").exists()  # refused before the output was begun
