"""Step 2 of reading a manifest: its entries resolved (:func:`resolve_manifest`): the stacks' headers, the maps, the dark fits, everything a fit needs, checked; :func:`read_manifest` is both steps."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ... import defaults, identity
from ...errors import InputError, InputWarning, ReadNoiseGrowthWarning
from ..dark import check_read_noise_growth, read_out_maps
from ..telegraph import telegraph_pixels
from ..stacks import (
    check_counts,
    content_fingerprint,
    stack_settings,
    check_readable,
    default_adc_max,
    describe_first,
    describe_missing,
    load_stack,
    needs_scan,
    read_map,
    stack_header,
)
from .records import Acquisition, CAMERA_IDENTITY, Manifest, Source, _binning, _origin
from .parse import AcquisitionEntry, ManifestEntries, _MAP_RULES, _Reader, parse_manifest


# --------------------------------------------------------------------------------------
# Step 2: resolve (headers, maps, dark fits: everything a fit needs, checked)
# --------------------------------------------------------------------------------------
def read_manifest(path) -> Manifest:
    """Read and validate a calibration manifest.

    Everything is checked before any fitting: TOML syntax, keys (with a suggestion for a
    misspelt one), types and ranges of values (:func:`parse_manifest`), then
    (:func:`resolve_manifest`) that every file exists and is readable, that stacks are
    3-D and share (rows, cols), that maps have that shape and valid values, that stacks
    hold raw counts (non-negative integers, at most the ADC maximum), and that
    ``skip_frames`` leaves frames to use. Dark stacks are reduced to offset and
    read-noise maps here, each file once: at 1× their mean and SD
    (:func:`emccdcal.data.dark.maps_from_dark`), at a multiplied set-point by a fit of the
    read-out and its multiplied events (:func:`emccdcal.data.dark.fit_dark`), whose plain
    SD the events would inflate.

    Parameters
    ----------
    path : str or Path
        The TOML manifest; relative paths inside it are relative to its folder.

    Returns
    -------
    Manifest

    Raises
    ------
    ManifestError
        A ``ValueError`` whose one-line message names the manifest, the acquisition (1-based,
        in file order), the data file if any, and the problem.

    Warns
    -----
    ReadNoiseGrowthWarning
        When the read noise grows with the set-point by more than 5 %
        (:func:`emccdcal.data.dark.check_read_noise_growth`); also in ``Manifest.warnings``.

    Notes
    -----
    The format, with examples and every error message, is in ``docs/manifest.md``.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> manifest = emccdcal.read_manifest(sim.manifest)
    >>> manifest.shape, [a.em_gain_setpoint for a in manifest.acquisitions]
    ((4, 4), [1.0, 10.0])
    """
    return resolve_manifest(parse_manifest(path))


def resolve_manifest(entries: ManifestEntries) -> Manifest:
    """Open what a parsed manifest names and check it: see :func:`read_manifest`."""
    r = _Reader(entries.path)
    acqs = entries.acquisitions
    e_result = _require_files(r, entries)
    shape, headers = _stack_headers(r, acqs)
    _refuse_copies(r, acqs)
    dtypes = [dtype for _, dtype, _ in headers]
    if entries.adc_bits is not None:
        adc_max = 2**entries.adc_bits - 1
        hint = f" (adc_bits = {entries.adc_bits}); is adc_bits the camera's ADC resolution?"
    else:
        adc_max = max(default_adc_max(d) for d in dtypes)
        hint = (
            f" (default for {', '.join(sorted({str(d) for d in dtypes}))} data); set "
            "adc_bits in the manifest to the camera's ADC resolution"
        )
    e_per_adu, e_source = None, None
    if e_result is not None:  # read by the calibration, with its standard errors
        e_source = Source("result", Path(e_result))
    elif entries.e_per_adu is not None:
        e_per_adu, e_source = _map_from_value(r, None, "", "e_per_adu", entries.e_per_adu, shape)
    for a, (_, dtype, _) in zip(acqs, headers):
        if needs_scan(dtype, adc_max):
            try:
                check_counts(
                    load_stack(a.frames_path), a.frames_path, adc_max=adc_max, adc_bits_hint=hint
                )
            except InputError as exc:
                raise r.error(str(exc), a.index, a.label) from None
    # what the files' headers say, checked before the darks are read: an error costs
    # no reduction, and a kind the files record (not only the manifest's) is the kind
    found: list[str] = []
    origin, binning, camera, camera_kind = _recorded(r, entries, acqs, shape, found)
    telegraph = camera_kind in defaults.WITHOUT_EM_REGISTER
    maps = _read_out_maps(r, acqs, shape, adc_max, hint, telegraph)
    acquisitions = [
        Acquisition(
            name=a.name,
            frames_path=a.frames_path,
            em_gain_setpoint=a.em_gain_setpoint,
            level=a.level,
            skip_frames=a.skip_frames,
            offset=m["offset"],
            read_noise=m["read_noise"],
            offset_source=m["offset_source"],
            read_noise_source=m["read_noise_source"],
            n_frames_total=n_total,
            dark_frames=dark_frames,
            dark_event_rate=m["events"],
            dark_telegraph_states=m["telegraph_states"],
            dark_stuck=m["stuck"],
            exposure_s=a.exposure_s,
            dark_exposure_s=a.dark_exposure_s,
        )
        for a, m, (n_total, _, dark_frames) in zip(acqs, maps, headers)
    ]
    growth = [
        f"{entries.path}: {msg}"
        for msg in check_read_noise_growth(
            [a.em_gain_setpoint for a in acquisitions], [a.read_noise for a in acquisitions]
        )
    ]
    for msg in growth:
        warnings.warn(msg, ReadNoiseGrowthWarning, stacklevel=3)
    found = growth + found
    levels = tuple(dict.fromkeys(a.level for a in acquisitions if a.level is not None))
    return Manifest(
        path=entries.path,
        content_hash=entries.content_hash,
        e_per_adu=e_per_adu,
        e_per_adu_source=e_source,
        acquisitions=acquisitions,
        shape=(int(shape[0]), int(shape[1])),
        origin=origin,
        binning=binning,
        adc_max=int(adc_max),
        setpoints=tuple(sorted({a.em_gain_setpoint for a in acqs})),
        levels=levels,
        warnings=found,
        em_model=entries.em_model,
        register_stages=entries.register_stages,
        camera=camera,
        camera_kind=camera_kind,
        light=entries.light,
    )


def _require_files(r: _Reader, entries: ManifestEntries) -> Path | None:
    """Every file named exists and is readable; returns the result φ is chained from."""
    for a in entries.acquisitions:
        for key in ("frames", "dark", "offset", "read_noise"):
            if isinstance(getattr(a, key), str):
                _require_file(r, a.index, a.label, key, getattr(a, key))
    e_value = entries.e_per_adu
    if isinstance(e_value, str) and is_result_path(r.resolve(e_value)):
        e_result = r.resolve(e_value)
        if not e_result.exists():
            raise r.error(f"e_per_adu: {describe_missing(e_result, 'result')}")
        return e_result
    if isinstance(e_value, str):
        _require_file(r, None, "", "e_per_adu", e_value)
    return None


def _stack_headers(r: _Reader, acqs):
    """The stacks' shared (rows, cols) and, per acquisition, (frames in the file, dtype,
    dark frames behind its maps), from the headers only."""
    shape, first_label, headers = None, "", []
    for a in acqs:
        i, label = a.index, a.label
        stack_shape, dtype = _stack_header(r, i, label, a.frames_path, "frames")
        if shape is None:
            shape, first_label = stack_shape[1:], label
        elif stack_shape[1:] != shape:
            raise r.error(
                f"frames '{a.frames_path}' have (rows, cols) = {stack_shape[1:]}, "
                f"but acquisition 1 ({first_label}) has {shape}; all stacks must "
                "cover the same pixels",
                i,
                label,
            )
        n = stack_shape[0]
        if a.skip_frames >= n:
            raise r.error(
                f"skip_frames = {a.skip_frames} leaves no frames: '{a.frames_path}' has {n} frames",
                i,
                label,
            )
        if n - a.skip_frames < 2:
            raise r.error(
                f"'{a.frames_path}' has 1 frame"
                f"{' after skip_frames' * bool(a.skip_frames)}: a histogram of a "
                "pixel's counts needs at least 2 (a calibration, thousands)",
                i,
                label,
            )
        dark_frames = a.dark_frames
        if a.dark is not None:
            dark_shape, _ = _stack_header(r, i, label, a.dark_path, "dark")
            if dark_shape[1:] != shape:
                raise r.error(
                    f"dark stack '{a.dark_path}' has (rows, cols) = "
                    f"{dark_shape[1:]}, but the frames are {shape}",
                    i,
                    label,
                )
            if dark_shape[0] < 2:
                raise r.error(
                    f"dark stack '{a.dark_path}' has {dark_shape[0]} frame(s); at "
                    "least 2 are needed for a read noise",
                    i,
                    label,
                )
            dark_frames = dark_shape[0]
        headers.append((n, dtype, dark_frames))
    return shape, headers


def _read_out_maps(r: _Reader, acqs, shape, adc_max, hint, telegraph=False) -> list[dict]:
    """Each acquisition's offset and read-noise maps (ADU) with their sources, the
    multiplied events of its dark, its stuck pixels (dark counts that never change: read
    noise 0) and (with ``telegraph``: a camera without an EM register) its pixels'
    offset states: from the maps given, or each dark stack reduced once."""
    darks: dict[Path, tuple] = {}
    # the least multiplied dark first: its read noise is the others' reference
    for a in sorted((a for a in acqs if a.dark is not None), key=lambda a: a.em_gain_setpoint):
        key = a.dark_path.expanduser().resolve()
        if key not in darks:
            reference = float(np.median(next(iter(darks.values()))[1])) if darks else None
            darks[key] = _reduce_dark(r, a, adc_max, hint, reference, telegraph)
    out = []
    for a in acqs:
        if a.dark is None:
            m: dict = {"events": None, "telegraph_states": None, "stuck": None}
            for key in ("offset", "read_noise"):
                m[key], m[key + "_source"] = _map_from_value(
                    r, a.index, a.label, key, getattr(a, key), shape
                )
        else:
            offset, read_noise, events, states = darks[a.dark_path.expanduser().resolve()]
            source = Source("dark", a.dark_path)
            m = {
                "offset": offset.copy(),
                "read_noise": read_noise.copy(),
                "events": events,
                "telegraph_states": states,
                "stuck": read_noise <= 0,
                "offset_source": source,
                "read_noise_source": source,
            }
        for key, what in (("offset", "offset"), ("read_noise", "read noise")):
            if np.max(m[key]) >= adc_max:  # maps in other units, or a wrong adc_bits
                bad = describe_first(m[key], m[key] >= adc_max, 0)
                raise r.error(
                    f"{what} {bad} ({m[key + '_source']}) is at or above the ADC "
                    f"maximum {adc_max} ADU{hint}; maps must be in ADU of these "
                    "frames",
                    a.index,
                    a.label,
                )
        out.append(m)
    return out


def _reduce_dark(r: _Reader, a: AcquisitionEntry, adc_max, hint, reference=None, telegraph=False):
    """(offset, read noise, multiplied events or None, offset states or None) of an
    acquisition's dark stack; ``reference`` the read noise (ADU) of the calibration's
    least multiplied dark. With ``telegraph`` a 1× dark's pixels are tested for two or
    more offset states, and their states counted
    (:func:`emccdcal.data.telegraph.telegraph_pixels`)."""
    assert a.dark_path is not None  # only an acquisition with a dark stack comes here
    try:
        dark = load_stack(a.dark_path)
        check_counts(dark, a.dark_path, adc_max=adc_max, adc_bits_hint=hint)
    except InputError as exc:
        raise r.error(str(exc), a.index, a.label) from None
    try:
        offset, read_noise, events = read_out_maps(
            dark, a.em_gain_setpoint, adc_max=adc_max, reference_read_noise=reference
        )
    except InputError as exc:  # an implausible dark: named with its file
        raise r.error(f"dark '{a.dark_path}': {exc}", a.index, a.label) from None
    # A pixel whose dark counts never change (dead, or stuck at one value) has no read
    # noise to measure: it is left out of the fit and marked (``stuck``), as a pixel
    # whose light frames never change is; a dark constant at every pixel is no dark.
    if np.all(read_noise <= 0):
        raise r.error(
            f"'{a.dark_path}': dark stack's counts never change at any pixel (read noise "
            "0): not a dark stack of this camera",
            a.index,
            a.label,
        )
    states = None
    if telegraph and a.em_gain_setpoint == 1:
        states = telegraph_pixels(dark, adc_max=adc_max).states.reshape(offset.shape)
    return offset, read_noise, events, states


def _recorded(r: _Reader, entries, acquisitions, shape, found: list):
    """What the frames files record: the region's origin, the binning and the camera
    identity shared by all; a set-point differing from the manifest's is a warning."""
    origins, binnings, recorded_by = set(), set(), {}
    for i, a in enumerate(acquisitions, start=1):
        settings = stack_settings(a.frames_path)
        recorded_by[a.frames_path] = settings
        if settings.roi is not None:
            origins.add((settings.roi[1], settings.roi[0]))  # (row, col) = (y, x)
        if settings.binning is not None:
            binnings.add(tuple(settings.binning))
        recorded = settings.em_gain_setpoint
        if recorded is not None and recorded != a.em_gain_setpoint:
            msg = (
                f"{entries.path}: acquisition {i} ({a.name}): the manifest says EM gain "
                f"set-point {a.em_gain_setpoint:g}, but '{a.frames_path}' records "
                f"{recorded:g}"
            )
            found.append(msg)
            warnings.warn(msg, stacklevel=4, category=InputWarning)
    try:  # the stacks of one calibration are of one camera and read-out state
        joint = identity.of_frames(recorded_by, what="frames of a manifest", setpoints=False)
    except InputError as exc:
        raise r.error(str(exc)) from None
    camera = {
        k: getattr(next(iter(recorded_by.values())), k)
        for k in CAMERA_IDENTITY
        if k in joint and all(getattr(s, k) is not None for s in recorded_by.values())
    }
    kind = _camera_kind(r, entries, recorded_by)
    return (_origin(r, entries.origin, origins, shape), _binning(r, binnings), camera, kind)


def _camera_kind(r: _Reader, entries, recorded_by) -> str | None:
    """The camera's kind: the manifest's ``camera_kind``, else the one its frames files
    record; files that record different kinds, or another than the manifest's, and an
    intensified camera are errors."""
    kinds = {p: s.camera_kind for p, s in recorded_by.items() if s.camera_kind is not None}
    if len(set(kinds.values())) > 1:
        said = "; ".join(f"'{p}' a {k}" for p, k in kinds.items())
        raise r.error(f"the frames files record different kinds of camera ({said})")
    recorded = next(iter(kinds.values()), None)
    given = entries.camera_kind
    if given is not None and recorded is not None and given != recorded:
        path = next(iter(kinds))
        raise r.error(
            f"camera_kind = {given!r}, but '{path}' records a {recorded} camera (its model "
            f"{recorded_by[path].model}); correct camera_kind or the files"
        )
    kind = given or recorded
    if kind == "iccd":
        path = next(iter(kinds), entries.path)
        raise r.error(
            f"'{path}' is of an intensified camera (its model {recorded_by[path].model}): "
            "its gain is an image intensifier's, which no model here describes (emccdcal "
            "calibrates EM registers and cameras without gain)"
        )
    return kind


def _refuse_copies(r: _Reader, acqs) -> None:
    """Two acquisitions whose frames files hold the same data (one stack copied under two
    set-points or levels) would fit as two measurements of one: an error."""
    seen: dict[str, AcquisitionEntry] = {}
    for a in acqs:
        key = content_fingerprint(a.frames_path)
        if key in seen:
            b = seen[key]
            raise r.error(
                f"frames '{a.frames_path}' hold the same data as acquisition {b.index}'s "
                f"('{b.frames_path}'): the same stack under two "
                f"{'levels' if a.level is not None else 'set-points'}?",
                a.index,
                a.label,
            )
        seen[key] = a


def is_result_path(path: Path) -> bool:
    """Whether ``path`` names a calibration result: a ``.nc`` file or a directory."""
    return path.suffix.lower() == ".nc" or path.is_dir()


def _require_file(r: _Reader, i: int | None, label: str, key: str, written: str) -> None:
    p = r.resolve(written)
    if not p.exists():
        raise r.error(
            f"{key} file not found: '{written}' (resolved to '{p.expanduser().resolve()}')",
            i,
            label,
        )
    try:
        check_readable(p)
    except InputError as exc:
        raise r.error(f"{key}: {exc}", i, label) from None


def _stack_header(r: _Reader, i: int, label: str, p: Path, key: str):
    try:
        shape, dtype = stack_header(p)
    except InputError as exc:
        raise r.error(str(exc), i, label) from None
    if len(shape) == 2:
        raise r.error(
            f"{key} '{p}' holds one image of {shape[0]} × {shape[1]} pixels, not a "
            "stack of frames (a stack cut short to its first frame?)",
            i,
            label,
        )
    if len(shape) != 3:
        raise r.error(
            f"{key} '{p}' is not a 3-D (frames, rows, cols) stack: shape {shape}", i, label
        )
    if dtype.kind not in "uif":
        raise r.error(
            f"{key} '{p}' has unsupported data type {dtype}; expected integer counts", i, label
        )
    return shape, dtype


def _map_from_value(r: _Reader, i: int | None, label: str, key: str, value, shape):
    """A number expands to a (rows, cols) map (e_per_adu stays a number); a path is read."""
    positive, nonnegative = _MAP_RULES[key]
    if isinstance(value, str):
        p = r.resolve(value)
        try:
            m = read_map(p, shape, name=key, positive=positive, nonnegative=nonnegative)
        except InputError as exc:
            raise r.error(str(exc), i, label) from None
        return m, Source("map", Path(p))
    source = Source("value", value=value)
    if key == "e_per_adu":
        return float(value), source
    return np.full(shape, float(value)), source
