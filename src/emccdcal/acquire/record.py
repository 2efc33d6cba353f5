"""``emccdcal acquire``: record a plan (:mod:`.plan`) through Micro-Manager.

A session folder receives one OME-Zarr stack per dark and per light acquisition, named
so that ``emccdcal scan`` needs nothing more (``25x-dark.ome.zarr``, ``25x-gain.ome.zarr``;
an intensity series ``dark.ome.zarr``, ``level-1.ome.zarr`` …), each recording the camera
settings the core reports; the plan it ran (``plan.toml``); and ``session.json``, what
has been recorded so far, which ``--resume`` continues from.

For each set-point (a gain series), in the plan's order:

1. the EM gain is set through the camera's property (:func:`gain_property`), the
   shutter closed (auto-shutter off) and the dark frames recorded;
2. the shutter is opened and the first :data:`CHECK_FRAMES` frames checked against the
   plan: at most :data:`SATURATED_LIMIT` of their values saturated, and the light they show, ``(mean − dark mean)·φ/g``, within
   ``light_tolerance`` of the plan's (a clear error and a stop otherwise, with the files
   so far kept);
3. the light frames are recorded; with ``stop_at_target``, a running fit of a fixed
   sample of pixels (:data:`SAMPLE_PIXELS`, with the 1× stack and the darks: the
   calibration's own likelihood) ends the stack as soon as the median per-pixel relative
   SE of its em_gain reaches the plan's target.

Frames are popped from the core's sequence buffer and appended to the stack in batches
of one chunk; an interruption (Ctrl-C, a camera error) ends the stack at the last batch
written, which is a valid, shorter stack, and ``session.json`` says where to resume.

Needs the ``acquire`` extra (pymmcore-plus, zarr ≥ 3).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import queue
import shutil
import signal
import threading
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import _files, defaults
from .._output import Output, OutputError, atomic_write, atomic_write_text, remove_leftovers
from .._util import check_number, one_line
from .._util import progress as progress_bar
from ..data import zarrs
from ..errors import InputError, OptionError
from .mm import (
    GAIN_PROPERTIES,
    AcquireError,
    Interrupted,
    camera_properties,
    config_core,
    gain_property,
    prepare,
    release,
    sequence,
    set_gain,
    simulated_core,
)
from .plan import Plan
from .plan_file import plan_text, read_plan
from .session import SESSION_FILE, Session, Stack, new_state, plan_sha

__all__ = [
    "acquire",
    "AcquireError",
    "Interrupted",
    "Session",
    "gain_property",
    "camera_properties",
    "simulated_core",
    "config_core",
    "GAIN_PROPERTIES",
    "CHECK_FRAMES",
    "LIGHT_TOLERANCE",
    "SAMPLE_PIXELS",
    "SESSION_FILE",
]

#: Frames at the start of each light stack checked against the plan before any is kept.
CHECK_FRAMES = 20
#: Largest fraction of the first frames' values at the ADC's limit. A light set too
#: bright saturates many; a hot pixel or an event in the tail of the multiplication
#: saturates a few, which calibrate drops (and counts) pixel by pixel, so they do not stop
#: the recording.
SATURATED_LIMIT = 1e-3
#: Largest relative difference between the light measured and the plan's. Wide: at a
#: multiplied set-point the measured light leans on the gain the plan assumed, and true
#: gains differ from their set-points by 10-20 % (the 1x stack measures it exactly).
LIGHT_TOLERANCE = 0.25
#: Pixels of the running fit of ``stop_at_target`` (evenly spread over the frame).
SAMPLE_PIXELS = 256
#: Frames between two running fits of ``stop_at_target`` (a quarter of the planned
#: frames, within these bounds).
CHECK_EVERY = 200
_FIRST_CHECK = 25
#: The attribute that marks a stack as written by acquire (with what it was planned as).
_MARKER = "emccdcal_acquisition"
#: Batches waiting for the disk, at most (then the recording waits: memory stays bounded).
_QUEUED_BATCHES = 4
#: Seconds between two updates of session.json while a stack records.
_STATE_EVERY_S = 1.0


# --------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------
@contextmanager
def _sigint_flag():
    """Ctrl-C sets a flag (checked between frames) instead of raising mid-write."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    previous = signal.signal(signal.SIGINT, lambda *_: flag.set())
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


@dataclass
class _Context:
    """What every stack of one recording shares."""

    core: object
    camera: str
    gain_prop: str
    plan: Plan
    session: Session
    stop: threading.Event
    light_tolerance: float | None
    stop_at_target: bool
    set_light: object
    progress: bool
    sample: np.ndarray | None = None
    light: float | None = None  # the light last set (set_light is called when it changes)
    darks: dict | None = None  # set-point -> (mean image, sample frames)
    unit_frames: np.ndarray | None = None  # the 1x stack's sample frames
    # Stacks whose last batches are still being written while the next one records.
    finishing: list = dataclasses.field(default_factory=list)


def _attrs(ctx: _Context, stack: Stack) -> dict:
    from ..data.micromanager import settings_of

    props = camera_properties(ctx.core, ctx.camera)
    settings = settings_of(props)
    if settings.camera_kind not in defaults.WITHOUT_EM_REGISTER:  # the set-point it recorded at
        settings = dataclasses.replace(settings, em_gain_setpoint=float(stack.setpoint))
    return {
        "emccdcal": settings.known(),
        "micromanager": props,
        _MARKER: {
            "dark": stack.dark,
            "planned_frames": stack.planned_frames,
            "photoelectrons": stack.photoelectrons,
        },
    }


class _Writing:
    """A stack's batches appended by a thread of its own, so that popping frames from the
    core never waits for the disk; the queue is bounded (and so is memory). An error of
    the writing is raised in the recording thread at the next batch or at the end."""

    def __init__(self, session: Session, stack: Stack, path: Path, shape, dtype, attrs):
        self.session, self.stack = session, stack
        self._args = (path, shape, dtype, attrs)
        if stack.frames == 0 and zarrs.begun_but_empty(path, _MARKER):
            shutil.rmtree(path)  # a store this stack began when the run was killed: redone
        try:  # a resume continues only a stack this session wrote
            self.writer = (
                zarrs.StackWriter(*self._args, owner=_MARKER, frames=stack.frames)
                if path.exists()
                else None
            )  # else made with the first frames kept
        except InputError as exc:
            raise AcquireError(str(exc)) from None
        self._queue: queue.Queue = queue.Queue(maxsize=_QUEUED_BATCHES)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"write {stack.name}", daemon=True)
        self._thread.start()

    def put(self, batch: zarrs.Batch) -> None:
        """Queue the batch's frames for writing; it is not touched meanwhile."""
        if self._error is not None:
            raise self._error
        self._queue.put((batch, batch.count))

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            if self._error is not None:
                continue
            try:
                self.writer = self.writer or zarrs.StackWriter(*self._args, owner=_MARKER)
                self.writer.append(*item)
                self.stack.frames = self.writer.frames
                self.session.save(every=_STATE_EVERY_S)
            except BaseException as exc:  # noqa: BLE001 - handed to the recording thread
                self._error = exc

    def close(self) -> None:
        """Wait for every batch to be written."""
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise AcquireError(
                f"'{self._args[0]}': writing failed: {one_line(self._error)}"
            ) from None


def _start_stack(ctx: _Context, stack: Stack):
    """Gain, light and shutter set for ``stack``; its frames' shape and dtype."""
    core = ctx.core
    set_gain(core, ctx.camera, ctx.gain_prop, stack.setpoint)
    if not stack.dark and ctx.set_light is not None and stack.photoelectrons != ctx.light:
        ctx.set_light(core, stack)
        ctx.light = stack.photoelectrons
    core.setShutterOpen(not stack.dark)
    shape = (core.getImageHeight(), core.getImageWidth())
    if ctx.sample is None:
        n_px = shape[0] * shape[1]
        ctx.sample = np.unique(np.linspace(0, n_px - 1, min(SAMPLE_PIXELS, n_px)).astype(int))
    return shape, (np.uint16 if core.getBytesPerPixel() == 2 else np.uint8)


def _record_stack(ctx: _Context, stack: Stack, bar) -> None:
    shape, dtype = _start_stack(ctx, stack)
    path = ctx.session.folder / stack.file
    target = ctx.stop_at_target and not stack.dark and stack.setpoint != 1
    most = (ctx.plan.max_frames or 2 * stack.planned_frames) if target else stack.planned_frames
    wanted = most - stack.frames
    sample_frames, kept = [], stack.frames
    checked = stack.dark or stack.frames > 0  # a resumed stack was checked when it began
    every = int(min(CHECK_EVERY, max(_FIRST_CHECK, stack.planned_frames // 4)))
    next_fit = stack.frames + every
    chunk = zarrs.StackWriter.chunk_frames_of(shape, dtype)
    # Frames are copied straight into batches, which the writer takes in turn: one
    # filling, the queued ones and one being written; no other copy of a frame is made.
    batches = [zarrs.Batch(chunk, shape, dtype) for _ in range(_QUEUED_BATCHES + 2)]
    writing = _Writing(ctx.session, stack, path, shape, dtype, _attrs(ctx, stack))
    finished = False
    try:
        with closing(sequence(ctx.core, wanted, ctx.stop, stack.name)) as frames:
            for frame in frames:
                batch = batches[0]
                batch.add(frame)
                n = batch.count
                bar.update(1)
                if target:
                    sample_frames.append(frame.reshape(-1)[ctx.sample])
                if not checked and n == min(CHECK_FRAMES, chunk, wanted):
                    _check_light(ctx, stack, batch.frames())
                    checked = True
                if checked and (kept + n) % chunk == 0:  # (a resume's first: to a chunk's end)
                    _finish(ctx)  # the stack before, written meanwhile
                    writing.put(batch)
                    batches.append(batches.pop(0))
                    batches[0].count, kept, n = 0, kept + n, 0
                if target and kept + n >= next_fit:
                    next_fit += every
                    stack.reached_se = _running_se(ctx, stack, sample_frames)
                    bar.set_postfix_str(
                        f"{stack.name}: SE {stack.reached_se:.2f} % "
                        f"(target {ctx.plan.target_se:g} %)"
                    )
                    if stack.reached_se <= ctx.plan.target_se:
                        break
        if batches[0].count and checked:
            writing.put(batches[0])
        # The last batches are written while the next stack records (_finish marks it
        # done); an interrupted or failed stack is written to the end here.
        finished = not ctx.stop.is_set()
    finally:
        if finished:
            ctx.finishing.append((stack, writing))
        else:
            writing.close()
    if ctx.stop.is_set():
        ctx.session.save()
        raise Interrupted(
            f"interrupted: {stack.name} holds {stack.frames} of "
            f"{stack.planned_frames} frames, kept in '{path}'; continue with "
            "--resume"
        )
    if target and (stack.reached_se is None or stack.reached_se > ctx.plan.target_se):
        stack.reached_se = _running_se(ctx, stack, sample_frames)


def _finish(ctx: _Context) -> None:
    """Wait for the stacks still being written and mark them done; the first error of
    their writing is raised once every one is seen to."""
    error = None
    while ctx.finishing:
        stack, writing = ctx.finishing.pop(0)
        try:
            writing.close()
        except AcquireError as exc:
            error = error or exc
            continue
        stack.done = True
        ctx.session.save()
    if error is not None:
        raise error


def _dark_of(ctx: _Context, setpoint: float):
    """The dark at a set-point (the series' one for an intensity series): its mean image
    and its sample pixels' frames, read back from its file."""
    _finish(ctx)  # the dark may be the stack just recorded
    if ctx.darks is None:
        ctx.darks = {}
    stack = next(
        s
        for s in ctx.session.stacks
        if s.dark and (s.setpoint == setpoint or ctx.plan.method != "gs")
    )
    if stack.name not in ctx.darks:
        total, n, sample = None, 0, []
        for block in zarrs.read_chunks(ctx.session.folder / stack.file):
            total = (
                block.sum(axis=0, dtype=np.float64)
                if total is None
                else total + block.sum(axis=0, dtype=np.float64)
            )
            n += block.shape[0]
            sample.append(block.reshape(block.shape[0], 1, -1)[:, :, ctx.sample])
        ctx.darks[stack.name] = (total / n, np.concatenate(sample))
    return ctx.darks[stack.name]


def _adc_max(ctx: _Context, dtype) -> int:
    """The largest count the frames can hold: the camera's bit depth as the core reports
    it, the plan's, and the frames' type, whichever is least (a plan may overstate it)."""
    bits = [int(ctx.plan.camera["adc_bits"])]
    try:
        bits.append(int(ctx.core.getImageBitDepth()))
    except Exception:  # noqa: BLE001 - a camera that does not say: the plan and the type
        pass
    return min(2 ** min(b for b in bits if b > 0) - 1, int(np.iinfo(dtype).max))


def _check_light(ctx: _Context, stack: Stack, frames: np.ndarray) -> None:
    """Stop when the first frames of a light stack saturate or their light is off the
    plan's by more than the tolerance."""
    cam = ctx.plan.camera
    adc_max = _adc_max(ctx, frames.dtype)
    saturated = float(np.mean(frames >= adc_max))
    where = f"{stack.name} (set-point {stack.setpoint:g})"
    if saturated > SATURATED_LIMIT:
        raise AcquireError(
            f"{where}: {100 * saturated:.2g} % of the first {len(frames)} "
            f"frames' pixels are at the ADC's limit ({adc_max} ADU): dim the "
            "light, then --resume"
        )
    if ctx.light_tolerance is None:
        return
    dark_mean, _ = _dark_of(ctx, stack.setpoint)
    gain = next((a.em_gain for a in ctx.plan.acquisitions if a.setpoint == stack.setpoint), 1.0)
    measured = float(np.mean(frames.mean(axis=0) - dark_mean)) * cam["e_per_adu"] / gain
    off = measured / stack.photoelectrons - 1.0
    if abs(off) > ctx.light_tolerance:
        raise AcquireError(
            f"{where}: the light is {measured:.4g} e- per pixel per frame (first "
            f"{len(frames)} frames, at the assumed gain {gain:g} and {cam['e_per_adu']:g} "
            f"e-/ADU), the plan's {stack.photoelectrons:.4g} ({100 * off:+.0f} %, more than "
            f"the {100 * ctx.light_tolerance:g} % allowed): set the light, then --resume"
        )


def _running_se(ctx: _Context, stack: Stack, sample_frames: list) -> float:
    """The median relative SE (percent) of the stack's em_gain over the sample pixels,
    from the calibration's own likelihood (gs: with the 1× stack and both darks)."""
    from ..data import stats
    from ..data.dark import read_out_maps
    from ..fit.series import acquisition_models, fit_series

    cam = ctx.plan.camera
    _finish(ctx)
    if ctx.unit_frames is None:
        unit = next(s for s in ctx.session.stacks if not s.dark and s.setpoint == 1)
        ctx.unit_frames = np.concatenate(
            list(zarrs.read_chunks(ctx.session.folder / unit.file, ctx.sample))
        )
    frames = [ctx.unit_frames, np.stack(sample_frames)[:, None, :]]
    adc_max = _adc_max(ctx, ctx.unit_frames.dtype)
    maps, dark_frames = [], []
    for sp in (1.0, stack.setpoint):
        dark = _dark_of(ctx, sp)[1]
        offset, read_noise, _ = read_out_maps(dark, sp, adc_max=adc_max)  # as calibrate's
        maps.append((offset.ravel(), read_noise.ravel()))
        dark_frames.append(dark.shape[0])
    models = acquisition_models(
        (1.0, stack.setpoint),
        [m[0] for m in maps],
        [m[1] for m in maps],
        ctx.plan.em_model,
        dark_frames,
    )
    hists = [stats.histograms(f, adc_max=adc_max) for f in frames]
    est = fit_series("gs", models, hists, e_per_adu=float(cam["e_per_adu"]), gof_test=False)
    rel = est["em_gain_se"][:, 1] / est["em_gain"][:, 1]
    rel = rel[np.isfinite(rel) & est["converged"]]
    return float(100.0 * np.median(rel)) if rel.size else math.inf


# --------------------------------------------------------------------------------------
# The verb
# --------------------------------------------------------------------------------------
def acquire(
    plan,
    out,
    *,
    core=None,
    camera: str | None = None,
    simulated_seed=None,
    roi=None,
    gain_prop: str | None = None,
    light_tolerance: float | None = LIGHT_TOLERANCE,
    stop_at_target: bool = False,
    resume: bool = False,
    set_light=None,
    progress: bool = True,
) -> Session:
    """Record ``plan`` into the session folder ``out``.

    Parameters
    ----------
    plan : path or Plan
        The plan (``plan.toml``, as :func:`emccdcal.acquire.plan_file.plan_text` writes it).
    out : path
        The session folder (new, or one to ``resume``).
    core : CMMCorePlus, optional
        A core with the camera loaded (and a shutter as its shutter device). Without it,
        ``simulated_seed`` must be given: the simulated EMCCD (:mod:`.devices`) is used,
        with the plan's camera, and its truth written as ``truth.json``.
    camera : str, optional
        The camera's device label (default: the core's camera).
    simulated_seed : int, optional
        Seed of the simulated camera.
    roi : (x, y, width, height), optional
        A region of the sensor, px, set through the core and recorded in the files.
    gain_prop : str, optional
        The EM-gain property (default: by adapter, :func:`gain_property`).
    light_tolerance : float or None
        Largest relative difference of the light from the plan's (None: not checked;
        saturation always is).
    stop_at_target : bool
        End each multiplied stack of a gain series when the running fit reaches the
        plan's target (up to the plan's ``max_frames``, else twice the planned frames).
    resume : bool
        Continue the session in ``out`` (the same plan) where it stopped.
    set_light : callable, optional
        ``set_light(core, stack)`` sets the light (:class:`Stack`'s ``photoelectrons``)
        before a light stack whose light differs from the last one set: needed for an
        intensity series' levels (a gain series' one light is set by hand before the
        recording, and checked). The simulated camera's lamp follows the plan by default.
    progress : bool
        A progress bar (default): in a notebook or on a terminal; none in a pipe.

    Returns
    -------
    Session

    Raises
    ------
    AcquireError
        The light is off the plan's or saturates, or the camera stops (what was recorded
        is kept; ``resume`` continues). :class:`Interrupted` on Ctrl-C.

    Examples
    --------
    A plan recorded by the simulated EMCCD (``simulated_seed``), then scanned and
    calibrated (a real camera: ``core=`` a Micro-Manager core with it loaded):

    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> p = emccdcal.plan(e_per_adu=3.9, read_noise=15.5, offset=590, target_se=5)
    >>> session = emccdcal.record(
    ...     p, f"{work}/session", simulated_seed=3, roi=(0, 0, 4, 4), progress=False
    ... )  # doctest: +SKIP
    >>> manifest = emccdcal.scan(f"{work}/session")  # doctest: +SKIP
    """
    if isinstance(plan, (str, Path)):
        plan_path = Path(plan)
        plan = read_plan(plan_path)
    text = plan_text(plan)
    if stop_at_target and plan.method != "gs":
        raise OptionError(
            "stop-at-target is for a gain-series plan (its target is per "
            "set-point); an intensity series records its planned frames"
        )
    if stop_at_target and not any(a.setpoint == 1 for a in plan.acquisitions):
        raise OptionError(
            "stop-at-target fits each set-point with the 1x acquisition, which this plan "
            "lacks: add a 1x [[acquisition]] or record without --stop-at-target"
        )
    if light_tolerance is not None:
        light_tolerance = check_number("light tolerance", light_tolerance, positive=True)
    out = Path(out)
    if core is None and simulated_seed is None:
        raise OptionError("give a core with a camera, or a seed for the simulated camera")
    # a session goes into a new (empty) folder or resumes its own: _open_session decides
    with Output(out, kind="folder", stage=False):
        session = _open_session(out, plan, text, resume, core, camera, roi, simulated_seed)
        for name in _SESSION_FILES:  # the temporary files of a killed run, ours to remove
            remove_leftovers(out / name)
        try:
            _record(
                session,
                out,
                plan,
                core,
                camera,
                roi,
                simulated_seed,
                gain_prop,
                set_light,
                light_tolerance,
                stop_at_target,
                progress,
            )
        except BaseException:
            if not resume and not any(s.frames or (out / s.file).exists() for s in session.stacks):
                _discard(out)  # refused before recording: what it wrote goes
            raise
    # The core made here is garbage now: collected in this thread, not by a daemon
    # thread at the interpreter's exit, where destroying Micro-Manager's C++ core aborts
    # the process (the command line collects after an error too: cli.main).
    gc.collect()
    return session


#: The files of a session folder besides its stacks: its record, its plan and the
#: simulated camera's truth.
_TRUTH_PATTERN = "truth-offset-pattern.tif"
_TRUTH_MAPS = tuple(f"truth-{m}.tif" for m in ("e_per_adu", "offset", "read_noise", "rts_step"))
_SESSION_FILES = (SESSION_FILE, "plan.toml", "truth.json", _TRUTH_PATTERN, *_TRUTH_MAPS)


def _discard(out: Path) -> None:
    """Remove the files a new session wrote before its first stack (its record, plan
    and the simulated camera's truth), so that the corrected command can start again."""
    for name in _SESSION_FILES:
        (out / name).unlink(missing_ok=True)


def _record(
    session,
    out,
    plan,
    core,
    camera,
    roi,
    simulated_seed,
    gain_prop,
    set_light,
    light_tolerance,
    stop_at_target,
    progress,
) -> None:
    """Record a session's stacks (:func:`acquire`, its parameters)."""
    run = session.state["runs"] - 1
    device = None
    if core is None:
        core, device = simulated_core(_simulated_camera(plan), seed=simulated_seed, run=run)
    camera = camera or core.getCameraDevice()
    if not camera:
        raise OptionError("the core has no camera: name it with --camera")
    try:
        prepare(core, camera, roi)
        prop = gain_property(core, camera, gain_prop)
        if device is not None:
            set_light = set_light or _simulated_light(camera)
            _write_truth(out, plan, device, session)
        elif plan.method != "gs" and set_light is None:
            raise OptionError(
                "an intensity-series plan changes the light between "
                "levels: give set_light (the command line asks at each)"
            )
        with _sigint_flag() as stop:
            ctx = _Context(
                core,
                camera,
                prop,
                plan,
                session,
                stop,
                light_tolerance,
                stop_at_target,
                set_light,
                progress,
            )
            _run(ctx)
    finally:
        release(core, unload=device is not None)
        if device is not None:
            device.wait_until_stopped()


def _open_session(out, plan, text, resume, core, camera, roi, seed) -> Session:
    if resume:
        if not (out / SESSION_FILE).exists():
            raise OutputError(f"{out}: no session to resume ({SESSION_FILE} is missing)")
        recorded = _files.load_json(out / SESSION_FILE, what="session record")
        if not isinstance(recorded, dict) or recorded.get("plan_sha256") != plan_sha(text):
            raise OutputError(
                f"{out}: its session recorded another plan; resume it with its own plan.toml"
            )
        session = Session.load(out, plan)
        sim = session.state.get("simulated")
        if (sim is None) != (seed is None) or (sim and sim.get("seed") != seed):
            raise OutputError(
                f"{out}: recorded with "
                + (f"the simulated camera (seed {sim['seed']})" if sim else "a real camera")
                + ": resume it with the same camera"
            )
        recorded_roi = session.state.get("roi")
        if (None if roi is None else list(roi)) != recorded_roi:
            raise OutputError(
                f"{out}: recorded with region {recorded_roi}: resume it with the same --roi"
            )
        session.state["runs"] = session.state.get("runs", 1) + 1
        session.state["status"] = "recording"
        session.save()
        return session
    taken = [p.name for p in out.iterdir() if not p.name.startswith(".")]
    if taken:
        raise OutputError(
            f"{out}: not empty ({', '.join(sorted(taken)[:3])}"
            f"{', …' if len(taken) > 3 else ''}): a session is recorded into a "
            "new folder (or --resume one)"
        )
    atomic_write_text(out / "plan.toml", text)
    state = new_state(
        plan,
        text,
        camera or (core.getCameraDevice() if core else "Camera"),
        roi,
        None if seed is None else {"seed": int(seed)},
    )
    session = Session(out, state)
    session.save()
    return session


def _run(ctx: _Context) -> None:
    todo = [s for s in ctx.session.stacks if not s.done]
    total = sum(s.planned_frames - s.frames for s in todo)
    bar = progress_bar(enabled=ctx.progress, desc="acquire", unit="frame", total=total)
    error = None
    try:
        for stack in todo:
            bar.set_postfix_str(stack.name)
            _record_stack(ctx, stack, bar)
    except AcquireError as exc:
        error = exc
    finally:
        bar.close()
        try:
            _finish(ctx)  # whatever stopped the recording, the stacks recorded are kept
        except AcquireError as exc:
            error = error or exc
    ctx.session.state["status"] = "complete" if error is None else one_line(error)
    ctx.session.save()
    if error is not None:
        raise error


# --------------------------------------------------------------------------------------
# The simulated camera's session
# --------------------------------------------------------------------------------------
def _simulated_camera(plan: Plan):
    """The simulated camera a plan describes: an sCMOS or qCMOS where its
    ``camera_kind`` says so (its per-pixel spreads the kind's preset's), else an EMCCD."""
    from ..simulate.camera import Camera
    from ..simulate.cmos import PRESETS, CMOSCamera
    from .devices import SENSOR_SHAPE

    cam, model = plan.camera, plan.em_model
    if cam.get("camera_kind") in PRESETS:
        return CMOSCamera(
            kind=cam["camera_kind"],
            rows=SENSOR_SHAPE[0],
            cols=SENSOR_SHAPE[1],
            frames=2,
            e_per_adu=cam["e_per_adu"],
            read_noise_e=cam["read_noise"] * cam["e_per_adu"],
            offset=cam["offset"],
            adc_bits=min(16, int(cam["adc_bits"])),
        )
    return Camera(
        rows=SENSOR_SHAPE[0],
        cols=SENSOR_SHAPE[1],
        frames=2,
        e_per_adu=cam["e_per_adu"],
        read_noise=cam["read_noise"],
        offset=cam["offset"],
        adc_bits=min(16, int(cam["adc_bits"])),
        multiplication=model.name,  # the simulator samples the named register
        stages=model.stages if model.register.uses_stages else Camera.stages,
    )


def _simulated_light(camera):
    def set_light(core, stack):
        core.setProperty(camera, "Light", float(stack.photoelectrons))

    return set_light


def _write_truth(out: Path, plan: Plan, device, session: Session) -> None:
    """``truth.json`` of the simulated camera, in the form of ``emccdcal simulate``'s
    (with its sensor-wide offset pattern, ``truth-offset-pattern.tif``; an sCMOS's or
    qCMOS's per-pixel maps, ``truth-<map>.tif``)."""
    import tifffile

    if hasattr(device, "maps"):
        _write_cmos_truth(out, device, session)
        return

    from ..simulate.series import truth_document

    dark = {s.setpoint: s for s in session.stacks if s.dark}
    acqs = []
    for s in session.stacks:
        if s.dark:
            continue
        d = dark.get(s.setpoint) or next(iter(dark.values()))
        acqs.append(
            {
                "label": s.name,
                "frames": s.file,
                "dark": d.file,
                "frames_n": s.planned_frames,
                "dark_frames_n": d.planned_frames,
                "setpoint": s.setpoint,
                "em_gain": device.true_em_gain(s.setpoint),
                "photoelectrons": s.photoelectrons,
                "offset": device.offset_of(s.setpoint),
            }
        )
    kind = "gain-series" if plan.method == "gs" else "intensity-series"
    opts = dataclasses.asdict(device.camera) | {"seed": device.seed}
    pattern_file = _TRUTH_PATTERN
    atomic_write(
        out / pattern_file,
        lambda tmp: tifffile.imwrite(tmp, device.offset_pattern.astype(np.float32)),
    )
    truth = truth_document(kind, device.camera, opts, acqs, pattern_file)
    truth["roi"] = session.state.get("roi")
    atomic_write_text(out / "truth.json", json.dumps(truth, indent=2) + "\n")


def _write_cmos_truth(out: Path, device, session: Session) -> None:
    """``truth.json`` and the per-pixel maps of a simulated sCMOS or qCMOS (the whole
    sensor's; the session's ``roi`` places the stacks on it)."""
    import tifffile

    for name in ("e_per_adu", "offset", "read_noise", "rts_step"):
        image = device.maps[name].astype(np.float32)
        atomic_write(out / f"truth-{name}.tif", lambda tmp, im=image: tifffile.imwrite(tmp, im))
    truth = {
        "kind": f"{device.camera.kind}-series",
        "camera": device.camera.kind,
        "seed": device.seed,
        "levels": {s.name: s.photoelectrons for s in session.stacks if not s.dark},
        "maps": {name: f"truth-{name}.tif" for name in ("e_per_adu", "offset", "read_noise")},
        "units": {"levels": "e-/px/frame", "e_per_adu": "e-/ADU", "offset": "ADU",
                  "read_noise": "ADU (rms, before the ADC's rounding)"},
        "options": dataclasses.asdict(device.camera),
        "roi": session.state.get("roi"),
    }  # fmt: skip
    atomic_write_text(out / "truth.json", json.dumps(truth, indent=2) + "\n")
