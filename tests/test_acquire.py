"""``emccdcal acquire``: a plan recorded through Micro-Manager (pymmcore-plus), with the
simulated EMCCD and with Micro-Manager's own DemoCamera, then scanned and calibrated."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pymmcore_plus", reason="the 'acquire' extra is not installed")

from conftest import kill_at_random  # noqa: E402

from emccdcal import cli  # noqa: E402
from emccdcal.acquire.plan import plan  # noqa: E402
from emccdcal.acquire.plan_file import plan_text, read_plan  # noqa: E402
from emccdcal.acquire.record import AcquireError, Session, acquire  # noqa: E402
from emccdcal.data.scan import scan  # noqa: E402
from emccdcal.data.stacks import load_stack, stack_settings  # noqa: E402
from emccdcal.errors import InputError, OptionError  # noqa: E402

PROEM = dict(e_per_adu=3.859, read_noise=15.5, offset=587.7, adc_bits=16)
#: Micro-Manager's DemoCamera (from the mm-test-adapters package) with a shutter.
DEMO_CONFIG = """\
Device,Camera,DemoCamera,DCam
Device,Shutter,DemoCamera,DShutter
Property,Core,Initialize,1
Property,Camera,PixelType,16bit
Property,Camera,Mode,Noise
Property,Camera,Exposure,1
Property,Core,Camera,Camera
Property,Core,Shutter,Shutter
"""


def _plan_file(tmp_path, *, setpoints=(1, 5, 25), target=2.0, edit=None, name="plan.toml"):
    p = plan(method="gs", setpoints=list(setpoints), target_se=target, **PROEM)
    text = plan_text(p)
    for old, new in (edit or {}).items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text)
    return path


def _calibrated_gains(tmp_path, session_dir):
    """scan → calibrate on the session (the command line, as a user would)."""
    manifest = tmp_path / "manifest.toml"
    assert cli.main(["scan", str(session_dir), "-o", str(manifest), "-q"]) == 0
    out = tmp_path / "cal"
    assert (
        cli.main(
            [
                "calibrate",
                str(manifest),
                "--method",
                "gs",
                "--e-per-adu",
                str(PROEM["e_per_adu"]),
                "-o",
                str(out),
                "-q",
                "--no-checks",
            ]
        )
        == 0
    )
    from emccdcal.result import load

    return load(out)


@pytest.mark.slow
def test_plan_acquire_scan_calibrate_recovers_the_simulated_truth(tmp_path, capsys):
    """The whole loop on the simulated EMCCD: the gains the calibration finds agree with
    the camera's truth (truth.json) within their standard errors, pixel by pixel."""
    plan_path = _plan_file(tmp_path)
    session_dir = tmp_path / "session"
    assert (
        cli.main(
            [
                "acquire",
                str(plan_path),
                "-o",
                str(session_dir),
                "--simulated",
                "--seed",
                "4",
                "--roi",
                "8,8,32,24",
                "-q",
            ]
        )
        == 0
    )
    truth = json.loads((session_dir / "truth.json").read_text())
    assert truth["kind"] == "gain-series" and truth["roi"] == [8, 8, 32, 24]
    ds = _calibrated_gains(tmp_path, session_dir)
    assert ds.em_gain.shape[1:] == (24, 32)
    for t in truth["acquisitions"][1:]:
        g = ds.em_gain.sel(setpoint=t["em_gain_setpoint"]).values.ravel()
        se = ds.em_gain_se.sel(setpoint=t["em_gain_setpoint"]).values.ravel()
        z = (g - t["em_gain"]) / se
        z = z[np.isfinite(z)]
        assert z.size > 700
        assert abs(np.mean(z)) < 4 / np.sqrt(z.size) + 0.1  # unbiased
        assert 0.85 < np.std(z) < 1.15  # honest SEs
        assert np.mean(np.abs(z) < 1.96) > 0.92


def test_democamera_records_settings_and_frames_scan_reads_back(tmp_path):
    """Micro-Manager's DemoCamera, through a configuration file: the gain property named,
    a region set through the core; the files record the settings the core reports and
    hold the frames asked for, which scan reads with no hand editing."""
    config = tmp_path / "demo.cfg"
    config.write_text(DEMO_CONFIG)
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(
        plan_text(
            plan(
                method="gs",
                setpoints=[1, 2],
                target_se=5,
                e_per_adu=1.0,
                read_noise=2.5,
                offset=600,
                adc_bits=16,
            )
        )
    )
    session_dir = tmp_path / "session"
    code = cli.main(
        [
            "acquire",
            str(plan_path),
            "-o",
            str(session_dir),
            "--mm-config",
            str(config),
            "--gain-property",
            "Gain",
            "--no-light-check",
            "--roi",
            "16,32,128,64",
            "-q",
        ]
    )
    assert code == 0
    found = scan(session_dir)
    assert [f.setpoint for f in found.signal] == [1.0, 2.0]
    for f in found.signal:
        s = f.settings
        assert (s.em_gain_setpoint, s.model, s.exposure_ms, s.roi, s.adc_bits) == (
            f.setpoint,
            "DemoCamera-MultiMode",
            1.0,
            (16, 32, 128, 64),
            16,
        )
        frames = np.asarray(load_stack(f.path)[...])
        assert frames.shape == (50, 64, 128) and frames.dtype == np.uint16
        assert frames.std(axis=0).min() > 0 and 50 < frames.mean() < 1000  # Noise mode
    group = json.loads((session_dir / "2x-gain.ome.zarr" / "zarr.json").read_text())
    assert group["attributes"]["micromanager"]["Camera-Gain"] == "2"
    assert group["attributes"]["ome"]["version"] == "0.5"  # NGFF 0.5 on Zarr v3
    assert group["attributes"]["ome"]["multiscales"][0]["axes"][0]["name"] == "t"
    state = Session.load(session_dir).state
    assert state["status"] == "complete" and all(s["done"] for s in state["stacks"])


def test_a_light_off_the_plan_stops_and_resume_completes(tmp_path):
    """A lamp 60 % brighter than the plan stops the first light stack before any of its
    frames is kept, with the measured light in the message; the dark before it is kept,
    and --resume (the lamp set right) records the rest."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    bright = lambda core, stack: core.setProperty("Camera", "Light", 1.6 * stack.photoelectrons)  # noqa: E731
    with pytest.raises(AcquireError, match=r"1x-gain .*the light is .*\(\+6\d %"):
        acquire(
            plan_path,
            out,
            simulated_seed=3,
            roi=(0, 0, 16, 16),
            set_light=bright,
            progress=False,
        )
    state = Session.load(out).state
    assert "the light is" in state["status"]
    assert [(s["name"], s["frames"], s["done"]) for s in state["stacks"][:2]] == [
        ("1x-dark", 50, True),
        ("1x-gain", 0, False),
    ]
    assert not (out / "1x-gain.ome.zarr").exists()
    assert load_stack(out / "1x-dark.ome.zarr").shape == (50, 16, 16)
    with pytest.raises(Exception, match="region"):  # the same camera and region only
        acquire(plan_path, out, simulated_seed=3, resume=True, progress=False)
    # an OME-Zarr someone put where the session's next stack goes is neither cut nor added to
    import zarr

    theirs = np.arange(3 * 16 * 16, dtype=np.uint16).reshape(3, 16, 16)
    group = zarr.open_group(str(out / "1x-gain.ome.zarr"), mode="w-")
    group.attrs["multiscales"] = [{"version": "0.4", "datasets": [{"path": "0"}]}]
    group.create_array("0", data=theirs)
    with pytest.raises(AcquireError, match="not the stack this session recorded"):
        acquire(plan_path, out, simulated_seed=3, roi=(0, 0, 16, 16), resume=True, progress=False)
    assert np.array_equal(np.asarray(load_stack(out / "1x-gain.ome.zarr")[...]), theirs)
    import shutil

    shutil.rmtree(out / "1x-gain.ome.zarr")
    session = acquire(
        plan_path, out, simulated_seed=3, roi=(0, 0, 16, 16), resume=True, progress=False
    )
    assert session.state["status"] == "complete" and session.state["runs"] == 3
    assert [s.frames for s in session.stacks] == [s.planned_frames for s in session.stacks]


def test_an_occupied_folder_and_another_plan_are_refused(tmp_path):
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "mine.txt").write_text("a user's file")
    with pytest.raises(Exception, match="not empty"):
        acquire(plan_path, tmp_path / "used", simulated_seed=1, progress=False)
    assert (tmp_path / "used" / "mine.txt").read_text() == "a user's file"
    out = tmp_path / "session"
    acquire(plan_path, out, simulated_seed=1, roi=(0, 0, 8, 8), progress=False)
    other = _plan_file(tmp_path, setpoints=(1, 25), name="other.toml")
    with pytest.raises(Exception, match="another plan"):
        acquire(other, out, simulated_seed=1, roi=(0, 0, 8, 8), resume=True, progress=False)
    with pytest.raises(OptionError, match="gain-series plan"):
        acquire(_plan_is(tmp_path), tmp_path / "is", simulated_seed=1, stop_at_target=True)


def _plan_is(tmp_path):
    path = tmp_path / "is-plan.toml"
    path.write_text(plan_text(plan(method="is-adu", target_se=2.0, **PROEM)))
    return path


@pytest.mark.slow
def test_ctrl_c_keeps_what_was_recorded_and_resume_goes_on(tmp_path):
    """Ctrl-C in the middle of a stack: exit 130 with what was kept; the stack is a valid,
    shorter one that scan and the readers take; --resume records the rest.

    The signal goes when the first dark's first chunk is on disk: the simulated camera
    records 6000 frames in about 0.4 s on a fast machine, sooner than session.json (saved
    once a second while a stack records) shows any, and the first dark is long enough
    (about 1.3 s there) for the signal to land in it on a busy machine too."""
    frames = 20000
    plan_path = _plan_file(
        tmp_path, setpoints=(1, 5), edit={"dark_frames = 50 ": f"dark_frames = {frames} "}
    )
    out = tmp_path / "session"
    cmd = [
        sys.executable,
        "-m",
        "emccdcal",
        "acquire",
        str(plan_path),
        "-o",
        str(out),
        "--simulated",
        "--seed",
        "8",
        "-q",
    ]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    first_chunk = out / "1x-dark.ome.zarr" / "0" / "c" / "0"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not first_chunk.exists() and proc.poll() is None:
        time.sleep(0.002)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted: 1x-dark holds" in err and "--resume" in err
    kept = Session.load(out).stacks[0]
    assert 0 < kept.frames < frames and not kept.done
    assert load_stack(out / "1x-dark.ome.zarr").shape[0] == kept.frames
    done = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    stacks = Session.load(out).stacks
    assert [s.frames for s in stacks] == [s.planned_frames for s in stacks]
    assert load_stack(out / "1x-dark.ome.zarr").shape[0] == frames


@pytest.mark.slow
def test_stop_at_target_ends_a_set_point_when_its_running_fit_is_precise(tmp_path):
    """A plan asking far more frames than its target needs: with --stop-at-target each
    multiplied set-point ends at the first running fit that reaches the target, and the
    calibration of what was recorded reports about the precision the running fit saw."""
    plan_path = _plan_file(
        tmp_path,
        setpoints=(1, 25),
        target=1.0,
        edit={"frames = 50\nassumed_em_gain = 25.0": "frames = 1000\nassumed_em_gain = 25.0"},
    )
    out = tmp_path / "session"
    session = acquire(
        plan_path,
        out,
        simulated_seed=6,
        roi=(0, 0, 16, 16),
        stop_at_target=True,
        progress=False,
    )
    light = session.stacks[-1]
    assert light.name == "25x-gain" and light.frames < 1000
    assert light.reached_se <= 1.0
    ds = _calibrated_gains(tmp_path, out)
    rel = (ds.em_gain_se / ds.em_gain).sel(setpoint=25.0).values
    assert np.nanmedian(rel) * 100 == pytest.approx(light.reached_se, rel=0.25)
    assert stack_settings(out / "25x-gain.ome.zarr").em_gain_setpoint == 25.0


def test_the_light_check_stops_a_saturating_light_not_a_few_hot_values():
    """More than 0.1 % of the first frames' values at the ADC's limit stop the stack
    (the light is too bright); a few (a hot pixel, an event in the register's tail) do
    not: calibrate drops them pixel by pixel."""
    from types import SimpleNamespace

    from emccdcal.acquire.record import _check_light
    from emccdcal.acquire.session import Stack

    ctx = SimpleNamespace(plan=SimpleNamespace(camera=dict(PROEM)), light_tolerance=None)
    stack = Stack("5x-gain", "5x-gain.ome.zarr", False, 5.0, 370.0, 100)
    frames = np.full((20, 32, 32), 1000, np.uint16)
    frames[0, :3, 0] = 65535  # 3 of 20480 values
    _check_light(ctx, stack, frames)
    frames[:, :8] = 65535
    with pytest.raises(
        AcquireError,
        match=r"25 % of the first 20 frames' pixels are at the "
        r"ADC's limit \(65535 ADU\)",
    ):
        _check_light(ctx, stack, frames)


def test_stacks_are_written_band_by_band_and_continued_at_any_frame(tmp_path):
    """Batches (frames kept as the chunks' bands of rows, the last band short) append
    exactly the frames added, whole chunks as their files; a resume continues a stack
    cut between two chunks."""
    from emccdcal.data.zarrs import Batch, StackWriter

    owner = "emccdcal_test"  # the writer's mark, which a resume needs
    ours = {}  # the writer marks its store itself
    shape = (100, 1200)  # bands of 64 and 36 rows; chunks of 27 frames
    frames = np.random.default_rng(0).integers(0, 4000, (90, *shape)).astype(np.uint16)
    path = tmp_path / "s.ome.zarr"

    def record(writer, todo):
        batch = Batch(writer.chunk_frames, shape, np.uint16)
        for frame in todo:  # batches end at a chunk's end, as acquire's do
            batch.add(frame)
            if (writer.frames + batch.count) % writer.chunk_frames == 0:
                writer.append(batch, batch.count)
                batch.count = 0
        if batch.count:
            writer.append(batch, batch.count)

    writer = StackWriter(path, shape, np.uint16, ours, owner=owner)
    chunk = writer.chunk_frames
    assert len(frames) > 3 * chunk > chunk > 1
    record(writer, frames[: chunk + 7])
    assert (path / "0" / "c" / "0" / "1" / "0").stat().st_size == chunk * 64 * 1200 * 2
    resumed = StackWriter(path, shape, np.uint16, ours, owner=owner, frames=chunk + 5)
    assert resumed.frames == chunk + 5
    record(resumed, frames[chunk + 5 :])
    assert np.array_equal(np.asarray(load_stack(path)[...]), frames)
    with pytest.raises(InputError, match="not the stack this session recorded"):
        StackWriter(path, shape, np.uint16, ours, owner="another writer", frames=chunk)


# --------------------------------------------------------------------------------------
# Hostile sessions, refused options, stores begun when killed
# --------------------------------------------------------------------------------------
def _stopped_at_the_first_light(plan_path, out, *, seed):
    """A session stopped by a lamp 60 % too bright: its first dark recorded, no light."""
    bright = lambda core, stack: core.setProperty("Camera", "Light", 1.6 * stack.photoelectrons)  # noqa: E731
    with pytest.raises(AcquireError):
        acquire(
            plan_path,
            out,
            simulated_seed=seed,
            roi=(0, 0, 8, 8),
            set_light=bright,
            progress=False,
        )


def test_a_session_record_never_supplies_a_path(tmp_path):
    """A stack's "file" in session.json once became a path outside the session; now the
    stacks are the plan's own and the record only says how far each got."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    _stopped_at_the_first_light(plan_path, out, seed=3)
    record = out / "session.json"
    good = record.read_text()
    for change, words in (
        (lambda s: s["stacks"][1].update(file="../escaped.ome.zarr"), "not a session"),
        (lambda s: s["stacks"][1].update(file=str(tmp_path / "abs.ome.zarr")), "not a session"),
        (lambda s: s.pop("stacks"), "not a session"),
        (lambda s: s["stacks"][0].update(frames="50"), "frames is '50'"),
        (lambda s: s["stacks"][0].update(done="yes"), "done is 'yes'"),
    ):
        state = json.loads(good)
        change(state)
        record.write_text(json.dumps(state))
        with pytest.raises(Exception, match=words):
            acquire(plan_path, out, simulated_seed=3, roi=(0, 0, 8, 8), resume=True, progress=False)
    assert not (tmp_path / "escaped.ome.zarr").exists()
    assert not (tmp_path / "abs.ome.zarr").exists()


def test_a_refused_option_leaves_nothing_and_a_killed_store_is_redone(tmp_path, capsys):
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    code = cli.main(
        [
            "acquire",
            str(plan_path),
            "-o",
            str(out),
            "--simulated",
            "--seed",
            "2",
            "--camera",
            "Nope",
            "-q",
        ]
    )
    assert code == 2 and "no camera 'Nope'" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())  # the corrected command may start
    assert (
        cli.main(["acquire", str(plan_path), "-o", str(out), "--simulated", "--seed", "-5", "-q"])
        == 2
    )
    capsys.readouterr()
    # a run killed while creating its first light stack's store: metadata, no frame
    _stopped_at_the_first_light(plan_path, out, seed=2)
    begun = out / "1x-gain.ome.zarr"
    begun.mkdir()  # the group's one metadata write, the session's marker in it
    (begun / "zarr.json").write_text(
        json.dumps(
            {
                "zarr_format": 3,
                "node_type": "group",
                "attributes": {"emccdcal_acquisition": {"dark": False, "planned_frames": 50}},
            }
        )
    )
    # resumed without saying which camera: the session says it was the simulated one
    assert (
        cli.main(["acquire", str(plan_path), "-o", str(out), "--resume", "--roi", "0,0,8,8", "-q"])
        == 0
    ), capsys.readouterr().err
    assert Session.load(out).state["status"] == "complete"
    assert load_stack(begun).shape[0] == Session.load(out).stacks[1].planned_frames


def test_saturation_is_judged_by_the_cameras_own_bit_depth(tmp_path):
    """A plan that says 20 bits once recorded a stack all at 65535 (the files: 16)."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5), edit={"adc_bits = 16": "adc_bits = 20"})
    bright = lambda core, stack: core.setProperty("Camera", "Light", 1e6)  # noqa: E731
    with pytest.raises(AcquireError, match="ADC's limit \\(65535 ADU\\)"):
        acquire(
            plan_path,
            tmp_path / "s",
            simulated_seed=4,
            roi=(0, 0, 8, 8),
            set_light=bright,
            light_tolerance=None,
            progress=False,
        )


def test_plan_check_refuses_light_past_the_adc(tmp_path, capsys):
    plan_path = _plan_file(tmp_path)
    text = plan_path.read_text()
    import re

    plan_path.write_text(re.sub(r"(?m)^photoelectrons = .*$", "photoelectrons = 1000000", text))
    code = cli.main(["plan", "--check", str(plan_path), "-q"])
    assert code == 2 and "past the ADC's 65535" in capsys.readouterr().err


def test_scan_refuses_an_unfinished_session(tmp_path, capsys):
    """An interrupted session once gave a one-set-point 'gain series' manifest, exit 0."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    _stopped_at_the_first_light(plan_path, out, seed=3)
    code = cli.main(["scan", str(out), "-o", str(tmp_path / "m.toml")])
    err = capsys.readouterr().err
    assert code == 2 and "has not finished" in err and "--resume" in err, err
    assert not (tmp_path / "m.toml").exists()


def test_plan_check_says_when_the_darks_limit_the_precision(tmp_path, capsys):
    """With 50 darks, plan --check once advised more light frames."""
    import re

    plan_path = _plan_file(tmp_path, target=0.1)
    text = re.sub(r"(?m)^dark_frames = .*$", "dark_frames = 50", plan_path.read_text())
    plan_path.write_text(text)
    assert cli.main(["plan", "--check", str(plan_path)]) == 0
    out = capsys.readouterr().out
    assert "the 50 dark frames limit it" in out and "more dark frames" in out, out


def test_an_empty_store_someone_else_made_is_never_removed(tmp_path):
    """Only a store this session began (metadata with its marker, or no file yet) is
    made again: a group with another's attributes, or with none, or of Zarr v2, is left
    as it is."""
    import json as _json

    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    _stopped_at_the_first_light(plan_path, out, seed=2)
    theirs = out / "1x-gain.ome.zarr"
    theirs.mkdir()
    for attributes in ({"owner": "a user"}, {}):
        meta = {"zarr_format": 3, "node_type": "group", "attributes": attributes}
        (theirs / "zarr.json").write_text(_json.dumps(meta))
        with pytest.raises(AcquireError, match="not the stack this session recorded"):
            acquire(plan_path, out, simulated_seed=2, roi=(0, 0, 8, 8), resume=True, progress=False)
        assert _json.loads((theirs / "zarr.json").read_text()) == meta
    # a Zarr v2 group (acquire writes v3 only): never this session's
    (theirs / "zarr.json").unlink()
    (theirs / ".zgroup").write_text('{"zarr_format": 2}')
    with pytest.raises(AcquireError, match="not the stack this session recorded"):
        acquire(plan_path, out, simulated_seed=2, roi=(0, 0, 8, 8), resume=True, progress=False)
    assert (theirs / ".zgroup").read_text() == '{"zarr_format": 2}'


def _flips(path, n, seed, load):
    """Flip one random byte of ``path`` ``n`` times (each from the original) and load it:
    counts of flips refused with emccdcal's one-line error and of flips loaded; any other
    exception (a traceback from deep inside a library) fails the test."""
    from emccdcal.errors import EmccdcalError

    original = path.read_bytes()
    rng = np.random.default_rng(seed)
    counts = {"refused": 0, "loaded": 0}
    for _ in range(n):
        data = bytearray(original)
        data[int(rng.integers(len(data)))] ^= int(rng.integers(1, 256))
        path.write_bytes(bytes(data))
        try:
            load()
        except EmccdcalError as exc:
            assert "\n" not in str(exc).strip(), exc
            counts["refused"] += 1
        else:
            counts["loaded"] += 1
    path.write_bytes(original)
    return counts


def test_byte_flips_of_a_session_and_its_plan_are_refused_or_harmless(tmp_path):
    """A damaged session.json or plan.toml gives a session or one clear line, never a
    traceback, and never a path outside the session (the stacks are the plan's)."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    out = tmp_path / "session"
    _stopped_at_the_first_light(plan_path, out, seed=3)
    own = out / "plan.toml"
    inside = {p.name for p in out.iterdir()}

    def load_session():
        session = Session.load(out, read_plan(own))
        assert all((out / s.file).resolve().parent == out.resolve() for s in session.stacks)

    totals = {
        "session.json": _flips(out / "session.json", 150, 1, load_session),
        "plan.toml": _flips(own, 150, 2, lambda: read_plan(own)),
    }
    print("byte flips (refused, loaded):", totals)
    assert all(sum(c.values()) == 150 for c in totals.values())
    assert {p.name for p in out.iterdir()} == inside and not list(tmp_path.glob("*.zarr"))


@pytest.mark.slow
def test_sigkill_of_acquire_at_random_moments_resumes_to_a_complete_session(tmp_path):
    """A real SIGKILL of `acquire` at random moments (while a store is created, a chunk
    written, the record saved): the next run (`--resume` where a session was recorded)
    always goes on, and the session ends complete with every stack its planned length."""
    plan_path = _plan_file(tmp_path, setpoints=(1, 5))
    base = [
        "acquire",
        str(plan_path),
        "--simulated",
        "--seed",
        "4",
        "--roi",
        "0,0,8,8",
        "-q",
        "-o",
    ]
    subprocess.run(
        [sys.executable, "-m", "emccdcal", *base, str(tmp_path / "whole")],
        check=True,
        capture_output=True,
    )
    out = tmp_path / "session"

    def command():
        resume = (out / "session.json").exists()
        return base + [str(out)] + (["--resume"] if resume else [])

    # six kills that landed (decided from the runs' ends, not a timing guess), each run
    # resuming what the killed ones left
    kills, finished = kill_at_random(command, 6, lambda: None, np.random.default_rng(5))
    done = subprocess.run(
        [sys.executable, "-m", "emccdcal", *command()], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    print(f"acquire: {kills} runs killed ({finished} finished first), then resumed to the end")
    stacks = Session.load(out).stacks
    assert all(s.done for s in stacks)
    for s in stacks:
        assert load_stack(out / s.file).shape[0] == s.planned_frames == s.frames
    assert sorted(p.name for p in out.iterdir()) == sorted(
        p.name for p in (tmp_path / "whole").iterdir()
    )


def test_a_store_killed_in_a_metadata_write_is_begun_but_empty(tmp_path):
    """zarr writes each metadata file as ``zarr.<id>.partial`` and renames it: a run killed
    in between leaves such files. A store holding metadata and those only, marked as the
    session's, is redone; one holding a chunk, or not marked, or whose only metadata is
    an unreadable fragment, is left as it is (the case a SIGKILL test met)."""
    from emccdcal.data.zarrs import begun_but_empty

    def store(name, files):
        path = tmp_path / name
        for rel, text in files.items():
            (path / rel).parent.mkdir(parents=True, exist_ok=True)
            (path / rel).write_text(text)
        return path

    ours = json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {"mine": {}}})
    theirs = json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {}})
    killed = store(
        "killed.zarr",
        {"zarr.json": ours, "zarr.ab12.partial": ours[:40], "0/zarr.cd34.partial": ""},
    )
    assert begun_but_empty(killed, "mine")
    assert begun_but_empty(store("first.zarr", {"zarr.ef56.partial": ours}), "mine")
    assert not begun_but_empty(store("cut.zarr", {"zarr.ef56.partial": ours[:30]}), "mine")
    assert not begun_but_empty(
        store("other.zarr", {"zarr.json": theirs, "0/zarr.x.partial": ""}), "mine"
    )
    assert not begun_but_empty(
        store("frames.zarr", {"zarr.json": ours, "0/zarr.json": "{}", "0/c/0/0/0": "data"}), "mine"
    )
    assert not begun_but_empty(
        store("chunk.zarr", {"zarr.json": ours, "0/c/0/0/0.a1.partial": "d"}), "mine"
    )


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="no FIFOs here")
def test_a_fifo_as_the_micro_manager_configuration_is_refused_at_once(tmp_path):
    """Micro-Manager would wait forever to read a FIFO: refused in one line before any
    core is made, through the installed command (bounded: it waited forever)."""
    import os

    from conftest import console_script

    plan_path = _plan_file(tmp_path)
    fifo = tmp_path / "MMConfig.cfg"
    os.mkfifo(fifo)
    done = subprocess.run(
        [
            console_script(),
            "acquire",
            str(plan_path),
            "-o",
            str(tmp_path / "s"),
            "--mm-config",
            str(fifo),
            "-q",
        ],
        capture_output=True,
        text=True,
        timeout=15,
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert f"'{fifo}': is a FIFO (named pipe), not a Micro-Manager configuration file" in lines[0]


@pytest.mark.slow
def test_plan_acquire_scan_calibrate_an_scmos_with_no_option(tmp_path):
    """An sCMOS from plan to calibration as a user runs it (installed command line): the
    plan says the kind, the simulated camera's files record it (its model's name), scan
    writes a manifest of a camera without an EM register, calibrate needs no method;
    φ per pixel agrees with the camera's truth within its SEs."""
    import tifffile

    from emccdcal.result import load

    def run(*argv):
        done = subprocess.run(
            [sys.executable, "-m", "emccdcal", *map(str, argv)], capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    plan_dir, session, out = tmp_path / "plan", tmp_path / "session", tmp_path / "out"
    run("plan", "--camera-kind", "scmos", "--e-per-adu", 0.46, "--read-noise", 3.0,
        "--offset", 100, "--target-se", 5, "--pixel-well", 30000, "-o", plan_dir, "-q")  # fmt: skip
    assert 'camera_kind = "scmos"' in (plan_dir / "plan.toml").read_text()
    run("acquire", plan_dir / "plan.toml", "-o", session, "--simulated", "--seed", 5,
        "--roi", "0,0,10,8", "-q")  # fmt: skip
    run("scan", session, "-o", tmp_path / "manifest.toml", "-q")
    assert 'camera_kind = "scmos"' in (tmp_path / "manifest.toml").read_text()
    run("calibrate", tmp_path / "manifest.toml", "-o", out, "-q", "--no-checks")
    ds = load(out)
    assert ds.attrs["method"] == "is-adu" and ds.attrs["camera_kind"] == "scmos"
    truth = tifffile.imread(session / "truth-e_per_adu.tif")[:8, :10]
    z = ((ds.e_per_adu.values - truth) / ds.e_per_adu_se.values)[ds.converged.values]
    assert z.size > 70 and abs(z.mean()) < 0.5 and 0.65 < np.sqrt(np.mean(z**2)) < 1.4
