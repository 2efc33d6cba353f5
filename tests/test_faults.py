"""Fault injection: damaged results, killed runs, runs at once, hostile metadata.

The quick part runs in ``make test-fast``; the ones marked slow (more flips, real
SIGKILLs of calibrate, apply and export) in ``make test``. Each prints its counts (run
with ``-s``); docs/reliability.md has them.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib

import numpy as np
import pytest
import tifffile
from camera_files import write_spe
from conftest import kill_at_random
from hypothesis import given, settings
from hypothesis import strategies as st
from test_export import OFFSET, PHI, SHAPE, SIGMA, true_result

from emccdcal import result
from emccdcal._output import comment, file_sha256, slug, toml_line
from emccdcal.data.manifest import read_manifest
from emccdcal.errors import InputError
from emccdcal.simulate.camera import simulate_frames


def _numbers(ds):
    return {k: np.asarray(v.values) for k, v in ds.variables.items()} | {"attrs": ds.attrs}


def _same(a, b) -> bool:
    if a.keys() != b.keys():
        return False
    for k in a:
        if k == "attrs":
            if {x: str(y) for x, y in a[k].items()} != {x: str(y) for x, y in b[k].items()}:
                return False
        elif a[k].shape != b[k].shape or not (
            np.array_equal(a[k], b[k])
            if a[k].dtype.kind in "OUSb"
            else np.array_equal(a[k], b[k], equal_nan=True)
        ):
            return False
    return True


def flip_bytes(res, n, seed):
    """Flip one random byte of ``res`` ``n`` times (each from the original); counts of
    flips detected (load refuses the file), unchanged (loads, same numbers) and silently
    changed (loads, different numbers: must be 0)."""
    original = res.read_bytes()
    reference = _numbers(result.load(res))
    rng = np.random.default_rng(seed)
    counts = {"tried": 0, "detected": 0, "unchanged": 0, "silently_changed": 0}
    for _ in range(n):
        data = bytearray(original)
        at = int(rng.integers(len(data)))
        data[at] ^= int(rng.integers(1, 256))
        res.write_bytes(bytes(data))
        counts["tried"] += 1
        try:
            loaded = _numbers(result.load(res))
        except InputError:
            counts["detected"] += 1
            continue
        counts["unchanged" if _same(loaded, reference) else "silently_changed"] += 1
    res.write_bytes(original)
    return counts


def test_byte_flips_are_detected_or_harmless(tmp_path):
    counts = flip_bytes(true_result(tmp_path / "r"), 40, seed=1)
    print("byte flips (quick):", counts)
    assert counts["silently_changed"] == 0 and counts["detected"] > 0


@pytest.mark.slow
def test_many_byte_flips_are_detected_or_harmless(tmp_path):
    counts = flip_bytes(true_result(tmp_path / "r", spread=0.01), 400, seed=2)
    print("byte flips:", counts)
    assert counts["silently_changed"] == 0


# --------------------------------------------------------------------------------------
# Hostile metadata
# --------------------------------------------------------------------------------------
_HOSTILE = st.text(
    alphabet=st.characters(blacklist_categories=("Cs",)), max_size=40
) | st.sampled_from(
    [
        "../../../ESC",
        "a\nb = 1",
        'x"\n[[acquisition]]',
        "\x00\x1b[2J",
        "/",
        "..",
        ".",
        "",
        "\r\n# ok",
        "C:\\Windows",
        "a/../../b",
    ]
)


@settings(max_examples=300, deadline=None)
@given(_HOSTILE)
def test_text_from_files_never_escapes(text):
    name = slug(text)
    assert name and "/" not in name and "\\" not in name and not name.startswith(".")
    assert name not in ("..", ".") and len(name) <= 73
    assert tomllib.loads(toml_line("serial", text)) == {"serial": text}
    line = "# recorded: " + comment(text)
    assert tomllib.loads(line + "\nk = 1") == {"k": 1}


_FIELDS = [
    ("spe", "serial"),
    ("spe", "analog_gain"),
    ("spe", "model"),
    ("zarr", "serial"),
    ("zarr", "analog_gain"),
    ("zarr", "model"),
    ("micromanager", "analog_gain"),
]


def _hostile_file(folder, name, fmt, field, hostile, frames, em_gain):
    from camera_files import write_micromanager_tiff, write_zarr

    if fmt == "spe":  # as the XML holds it: the reader gets the quote back
        kw = {
            "serial": "S",
            "analog_gain": "High",
            "model": "M",
            field: hostile.replace('"', "&quot;"),
        }
        write_spe(folder / f"{name}.spe", frames, em_gain=em_gain, **kw)
    elif fmt == "zarr":
        pytest.importorskip("zarr")
        write_zarr(folder / f"{name}.zarr", frames, em_gain=em_gain, **{field: hostile})
    else:
        write_micromanager_tiff(folder / f"{name}.ome.tif", frames, em_gain=em_gain, preamp=hostile)


@pytest.mark.parametrize("fmt,field", _FIELDS)
def test_hostile_metadata_through_scan(tmp_path, capsys, fmt, field):
    """A camera file with a hostile recorded field: scan writes a manifest with no key
    but its own, every frame is used, and the field is kept whole, as data."""
    from emccdcal import cli

    folder = tmp_path / "s"
    folder.mkdir()
    hostile = '../..\n skip_frames = 25\n[x]\n"\t#'
    for i, name in enumerate(("1x-gain", "1x-gain_dark")):
        frames = simulate_frames(
            np.full((4, 4), 0.0 if "dark" in name else 400.0),
            em_gain=1.0,
            e_per_adu=PHI,
            offset=OFFSET,
            read_noise=SIGMA,
            frames=60,
            seed=i,
        )
        _hostile_file(folder, name, fmt, field, hostile, frames, 1)
    assert cli.main(["scan", str(folder), "-q"]) == 0
    doc = tomllib.loads((folder / "manifest.toml").read_text())
    assert set(doc) <= {"adc_bits", "acquisition"}
    assert all("skip_frames" not in a for a in doc["acquisition"])
    manifest = read_manifest(folder / "manifest.toml")
    assert [a.skip_frames for a in manifest.acquisitions] == [0]  # every frame is used
    recorded = manifest.camera.get(field)
    # kept as data, whole (XML folds white space in attributes: SPE's serial and model)
    assert recorded is not None and " ".join(recorded.split()) == " ".join(hostile.split())
    capsys.readouterr()


# --------------------------------------------------------------------------------------
# Killed runs: the previous output survives, nothing half-written loads
# --------------------------------------------------------------------------------------
@pytest.mark.slow
def test_sigkill_of_calibrate_apply_and_export_loses_nothing(tmp_path):
    from emccdcal import calibrate
    from emccdcal.simulate.series import simulate_gain_series

    rng = np.random.default_rng(7)
    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 5, 100), rows=8, cols=8, frames=600, dark_frames=300, seed=5
    )
    out = tmp_path / "out"
    calibrate(sim.manifest, "gs", out=out, progress=False)
    nc = out / result.CALIBRATION_FILE
    old = file_sha256(nc)
    reference = result.load(out)

    def calibrate_ok():
        ds = result.load(out)  # never half-written; old, or a complete new one
        assert file_sha256(nc) == old or np.allclose(ds.em_gain, reference.em_gain, equal_nan=True)
        assert (out / result.SUMMARY_FILE).is_file()

    totals = {}
    totals["calibrate"] = kill_at_random(
        ["calibrate", sim.manifest, "--method", "gs", "-o", out, "--overwrite", "-q"],
        4,
        calibrate_ok,
        rng,
    )

    res = true_result(tmp_path / "r")
    movie = tmp_path / "m.tif"
    tifffile.imwrite(
        movie,
        simulate_frames(
            np.full(SHAPE, 30.0),
            em_gain=90.06,
            e_per_adu=PHI,
            offset=OFFSET,
            read_noise=SIGMA,
            frames=3000,
            seed=1,
        ),
    )
    before_movie = file_sha256(movie)
    converted = tmp_path / "e.tif"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "apply",
            res,
            movie,
            "--setpoint",
            "100",
            "-o",
            converted,
            "-q",
        ],
        check=True,
    )
    first = tifffile.imread(converted)

    def apply_ok():
        assert file_sha256(movie) == before_movie
        np.testing.assert_array_equal(tifffile.imread(converted), first)

    totals["apply"] = kill_at_random(
        ["apply", res, movie, "--setpoint", "100", "-o", converted, "--overwrite", "-q"],
        4,
        apply_ok,
        rng,
    )
    exported = tmp_path / "exp"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "export",
            res,
            "--to",
            "pyme",
            "--setpoint",
            "100",
            "-o",
            exported,
            "-q",
        ],
        check=True,
    )
    files = {p.name: file_sha256(p) for p in exported.iterdir()}

    def export_ok():
        now = {p.name: file_sha256(p) for p in exported.iterdir() if not p.name.startswith(".")}
        assert now == files  # the same content: all old, or all (identical) new

    totals["export"] = kill_at_random(
        ["export", res, "--to", "pyme", "--setpoint", "100", "-o", exported, "--overwrite", "-q"],
        4,
        export_ok,
        rng,
    )
    print("kills (killed, finished first):", totals)
    # the next run cleans what the killed ones left
    subprocess.run(
        [
            sys.executable,
            "-m",
            "emccdcal",
            "apply",
            res,
            movie,
            "--setpoint",
            "100",
            "-o",
            converted,
            "-q",
            "--overwrite",
        ],
        check=True,
    )
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name or "partial" in p.name]


@pytest.mark.slow
def test_runs_at_once_into_one_output(tmp_path):
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path / "gs", setpoints=(1, 5), rows=8, cols=8, frames=600, dark_frames=300, seed=5
    )
    outcomes = []
    for trial in range(2):
        out = tmp_path / f"out{trial}"
        procs = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "emccdcal",
                    "calibrate",
                    str(sim.manifest),
                    "--method",
                    "gs",
                    "-o",
                    str(out),
                    "-q",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            for _ in range(2)
        ]
        codes = [(p.wait(), p.stderr.read()) for p in procs]
        outcomes.append(sorted(c for c, _ in codes))
        assert sorted(c for c, _ in codes) == [0, 2], codes
        loser = next(e for c, e in codes if c == 2)
        assert "another emccdcal run is writing it" in loser or "holds" in loser, loser
        assert loser.count("\n") == 1
        result.load(out)
        assert not (out / ".emccdcal-lock").exists()
    print("runs at once (exit codes per trial):", outcomes)


def test_byte_flips_of_a_database_are_refused_or_harmless(tmp_path):
    """A damaged calibration database gives its entries or one clear line (never SQLite's
    traceback), and reading it never changes it."""
    from emccdcal.errors import EmccdcalError
    from emccdcal.export import database

    db = tmp_path / "c.sqlite"
    res = true_result(tmp_path / "r")
    database.add(res, db=db, camera="SIM-1", date="2026-01-02")
    original = db.read_bytes()
    rng = np.random.default_rng(4)
    counts = {"refused": 0, "read": 0}
    for _ in range(150):
        data = bytearray(original)
        data[int(rng.integers(len(data)))] ^= int(rng.integers(1, 256))
        db.write_bytes(bytes(data))
        try:
            database.entries(db=db)
            database.compare("SIM-1", db=db)
        except EmccdcalError as exc:
            assert "\n" not in str(exc).strip(), exc
            counts["refused"] += 1
        else:
            counts["read"] += 1
        assert db.read_bytes() == bytes(data)  # reading never writes
    print("database byte flips (refused, read):", counts)
    assert counts["refused"] + counts["read"] == 150


@pytest.mark.slow
def test_sigkill_of_gain_check_plan_and_db_add_loses_nothing(tmp_path):
    """The newer verbs' outputs (gain-check's files, plan's plan, a database entry) are
    all old or all new after a SIGKILL at a random moment, never half-written."""
    from test_export import GAINS

    rng = np.random.default_rng(11)
    totals = {}
    darks = tmp_path / "darks.tif"
    tifffile.imwrite(
        darks,
        simulate_frames(
            np.full(SHAPE, 0.05),
            em_gain=GAINS[100.0],
            e_per_adu=PHI,
            offset=OFFSET,
            read_noise=SIGMA,
            frames=1500,
            seed=2,
        ),
    )
    checked = tmp_path / "check"
    argv = ["gain-check", darks, "--e-per-adu", PHI, "--setpoint", 100, "-q"]
    subprocess.run(
        [sys.executable, "-m", "emccdcal", *map(str, argv), "-o", checked],
        check=True,
        stdout=subprocess.DEVNULL,
    )

    def fingerprint():  # the figure's bytes vary from run to run (SVG ids): whole, though
        return {
            p.name: (
                p.read_bytes().rstrip().endswith(b"</svg>")
                if p.suffix == ".svg"
                else file_sha256(p)
            )
            for p in checked.iterdir()
            if not p.name.startswith(".")
        }

    files = fingerprint()

    def check_ok():
        assert fingerprint() == files  # old and new are alike; a torn file differs

    totals["gain-check"] = kill_at_random([*argv, "-o", checked, "--overwrite"], 3, check_ok, rng)
    planned = tmp_path / "plan.toml"
    argv = [
        "plan",
        "--e-per-adu",
        "3.859",
        "--read-noise",
        "15.5",
        "--offset",
        "588",
        "-q",
        "-o",
        planned,
    ]
    subprocess.run([sys.executable, "-m", "emccdcal", *argv], check=True)
    plan_bytes = planned.read_bytes()
    totals["plan"] = kill_at_random(
        [*argv, "--overwrite"], 3, lambda: planned.read_bytes() == plan_bytes or 1 / 0, rng
    )
    db = tmp_path / "c.sqlite"
    res = true_result(tmp_path / "r")
    from emccdcal.export import database

    def db_ok():
        found = database.entries(db=db) if db.exists() else []
        assert len(found) <= 1 and all(e.gains for e in found)  # the entry whole, or none
        if found:
            database.remove(found[0].id, db=db)

    totals["db add"] = kill_at_random(
        ["db", "add", res, "--camera", "SIM-1", "--db", db, "-q"], 3, db_ok, rng
    )
    print("kills (killed, finished first):", totals)
    # the next runs clean what the killed ones left
    for again in (
        [
            "gain-check",
            darks,
            "--e-per-adu",
            PHI,
            "--setpoint",
            100,
            "-q",
            "-o",
            checked,
            "--overwrite",
        ],
        [*argv, "--overwrite"],
    ):
        subprocess.run(
            [sys.executable, "-m", "emccdcal", *map(str, again)],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    assert not [p.name for p in tmp_path.rglob("*") if ".tmp" in p.name]
