"""The calibration database: every calibration of a lab's cameras in one SQLite file.

Entries are keyed by the camera's serial number and its read-out mode (output amplifier,
read-out rate, pre-amplifier gain, ADC bits: a calibration holds for one mode only), taken
from what the result's stacks recorded or given when adding. Each entry keeps the
result's path (relative to the database's folder where the result lies inside it, so
that a project folder holding both can move), its SHA-256, its date, its method and
register model, its summary (``summary.json``'s content) and, per set-point, the
sensor's gain: the median over converged pixels with the standard error of that median
(``se_of_median``, 1.2533 × robust spread / √n). Beside them, gain checks from dark frames
(``emccdcal gain-check --record``: :func:`add_check`): the camera, read-out state,
set-point, date, register model, the gain and its standard error.

:func:`compare` follows a camera's gain at each set-point over time, calibrations and
gain checks alike. It flags the newest calibration when it is older than a given age,
when its gain differs from the one before by more than ``z`` combined standard errors,
when a gain check made after it differs from it so, and when the gains of a set-point
trend (a weighted straight line through three or more of them, in time, with a slope
beyond ``z`` of its standard errors): the EM register ages (its gain at a fixed
set-point drops over months of use), and a calibration that is not redone goes silently
wrong. Only calibrations under the same register model are compared: the
gamma model and the exact cascade read the same data ~0.2 % apart, which is not ageing.
:func:`calibration` gives the newest calibration at a set-point, or where none measured
it, the newest one with its gain curve's prediction there.

Several processes may add at once: each addition is one ``BEGIN IMMEDIATE`` transaction
in write-ahead-log mode, and a writer waits (up to 60 s) for another's lock instead of
failing. The default file is ``calibrations.sqlite`` in the user's data directory
(``$EMCCDCAL_DB`` overrides it; ``--db PATH`` to share one).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import sqlite3
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._output import file_sha256
from ..errors import OptionError
from ._sqlite import _opened, default_path
from ..result import format_setpoint, load, load_calibration, pixel_statistics, summarize

__all__ = [
    "default_path",
    "add",
    "add_check",
    "remove",
    "relocate",
    "entries",
    "entry",
    "checks",
    "find",
    "calibration",
    "compare",
    "readout_text",
    "past_date",
    "Entry",
    "CheckEntry",
    "Finding",
]


@dataclass(frozen=True)
class Entry:
    """One calibration in the database (gains: set-point → (median, se_of_median, n));
    ``path``: the result file(s), comma-joined, as found from here."""

    id: int
    camera: str
    readout: str
    date: str
    added: str
    method: str
    em_model: str
    path: str
    sha256: str
    note: str
    gains: dict

    @property
    def register(self) -> str:
        """The register model's name (``"gamma"``, ``"cascade"``), without its stages:
        a register's length moves its gains by far less than their errors."""
        return self.em_model.split(" (")[0]

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["gains"] = {
            format_setpoint(s): {"median": m, "se_of_median": se, "n": n}
            for s, (m, se, n) in sorted(self.gains.items())
        }
        return d


@dataclass(frozen=True)
class CheckEntry:
    """One gain check from dark frames (``emccdcal gain-check --record``): the gain
    ``em_gain`` with its standard error ``se`` at ``setpoint``, and the check's JSON
    record (:meth:`emccdcal.fit.darkgain.GainCheck.as_dict`)."""

    id: int
    camera: str
    readout: str
    date: str
    added: str
    setpoint: float
    em_gain: float
    se: float
    em_model: str
    events: float
    note: str
    record: dict

    @property
    def register(self) -> str:
        """The register model's name, as :attr:`Entry.register` (the check records the
        model's label, ``"cascade, 536 stages"``)."""
        return self.em_model.split(",")[0].split(" (")[0]

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def readout_text(camera: dict) -> str:
    """The read-out state a camera record names (amplifier, rate, analog gain, ADC bits),
    as the database keeps it: ``"EM, 10 MHz, analog gain 2, 16-bit"``."""
    parts = [str(camera["amplifier"])] if camera.get("amplifier") is not None else []
    if camera.get("readout_rate_mhz") is not None:
        parts.append(f"{camera['readout_rate_mhz']:g} MHz")
    if camera.get("analog_gain") is not None:
        parts.append(f"analog gain {camera['analog_gain']}")
    if camera.get("adc_bits") is not None:
        parts.append(f"{camera['adc_bits']}-bit")
    return ", ".join(parts)


def _parse(text: str) -> _dt.datetime:
    return _dt.datetime.fromisoformat(str(text).replace("Z", "+00:00"))


def _iso_date(text) -> str:
    try:
        when = _parse(text)
    except ValueError:
        raise OptionError(
            f"date must be ISO 8601 (2026-11-25 or 2026-11-25T12:00:00Z), got {text!r}"
        ) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.timezone.utc)
    return when.astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def past_date(text) -> str:
    """:func:`_iso_date` of a date that has been (a calibration cannot be of tomorrow)."""
    when = _iso_date(text)
    if _parse(when) > _dt.datetime.now(_dt.timezone.utc) + _dt.timedelta(days=1):
        raise OptionError(f"date {text!r} is in the future; give when the data were taken")
    return when


def add(result, *, db=None, camera=None, readout=None, date=None, note="") -> Entry:
    """Add a calibration result (or a comma-joined group) to the database.

    Parameters
    ----------
    result : str or Path
        A result for :func:`~emccdcal.result.load_calibration`.
    db : str or Path, optional
        The database file (default :func:`default_path`).
    camera : str, optional
        The camera's serial number; default: the one its stacks recorded.
    readout : str, optional
        Its read-out state (e.g. ``"10 MHz, analog gain 2, 16-bit"``); default: from the
        recorded read-out rate, analog gain and ADC bits ("" where none is recorded).
    date : str, optional
        When the calibration data were taken (ISO 8601); default: the result's creation
        time.
    note : str
        Free text kept with the entry.

    Returns
    -------
    Entry

    Raises
    ------
    OptionError
        No serial recorded and none given, a bad date, or a result already in the
        database (named by its entry).
    """
    cal = load_calibration(result)
    serial = camera or cal.camera.get("serial")
    if not serial:
        raise OptionError(
            f"{cal.label}: its files record no camera serial number; give --camera SERIAL"
        )
    readout = readout_text(cal.camera) if readout is None else str(readout)
    when = past_date(date or cal.created or _dt.datetime.now(_dt.timezone.utc).isoformat())
    digest = ",".join(cal.sha256)
    gains = {}
    for s in cal.setpoints:
        if s == 1.0:
            continue
        stats = pixel_statistics(cal.gain(s))
        if stats["median"] is not None:
            gains[s] = (stats["median"], stats["se_of_median"], stats["n"])
    summary = {str(f): summarize(load(f)) for f in cal.files}
    added = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    path = _stored_paths(cal.files, db)
    with _opened(db, write=True) as con:
        try:
            con.execute("BEGIN IMMEDIATE")
            old = con.execute("SELECT id FROM calibration WHERE sha256 = ?", (digest,)).fetchone()
            if old is not None:
                con.execute("ROLLBACK")
                raise OptionError(f"{cal.label}: already in the database as entry {old['id']}")
            cur = con.execute(
                "INSERT INTO calibration (camera, readout, date, added, method, em_model, path, "
                "sha256, note, summary) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    str(serial),
                    readout,
                    when,
                    added,
                    cal.method,
                    str(cal.em_model),
                    path,
                    digest,
                    note,
                    json.dumps(summary, allow_nan=False),
                ),
            )
            con.executemany(
                "INSERT INTO gain VALUES (?, ?, ?, ?, ?)",
                [(cur.lastrowid, s, m, se, n) for s, (m, se, n) in gains.items()],
            )
            con.execute("COMMIT")
            return entry(cur.lastrowid, db=db)
        except BaseException:
            if con.in_transaction:
                con.execute("ROLLBACK")
            raise


def add_check(check, *, camera, readout="", date=None, note="", db=None) -> CheckEntry:
    """Add a gain check from dark frames to the database.

    Parameters
    ----------
    check : emccdcal.fit.darkgain.GainCheck
        With its set-point.
    camera : str
        The camera's serial number (as its calibrations are keyed).
    readout : str
        Its read-out state, as :func:`add` writes it for the calibrations to compare with.
    date : str, optional
        When the dark frames were taken (ISO 8601; default now).
    note : str
        Free text kept with the check.
    db : str or Path, optional
        The database file.

    Returns
    -------
    CheckEntry
    """
    if not camera:
        raise OptionError(
            "a gain check is recorded under its camera's serial: give --camera "
            "SERIAL (the dark frames record none)"
        )
    if check.setpoint is None:
        raise OptionError("the gain check has no set-point: give it")
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    when = past_date(date or now)
    record = check.as_dict()
    with _opened(db, write=True) as con:
        cur = con.execute(
            "INSERT INTO gain_check (camera, readout, date, added, setpoint, em_gain, se, "
            "em_model, events, note, record) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                str(camera),
                str(readout),
                when,
                now,
                float(check.setpoint),
                float(check.em_gain),
                float(check.em_gain_se),
                str(check.em_model),
                float(check.events),
                str(note),
                json.dumps(record, allow_nan=False),
            ),
        )
        row = cur.lastrowid
    return checks(db=db, camera=camera, where_id=row)[0]


def checks(*, db=None, camera=None, readout=None, where_id=None) -> list[CheckEntry]:
    """The gain checks, oldest first, of one camera (and read-out state) or of all."""
    clauses, args = [], []
    for column, value in (("camera", camera), ("readout", readout), ("id", where_id)):
        if value is not None:
            clauses.append(f"{column} = ?")
            args.append(value)
    with _opened(db) as con:
        try:
            rows = con.execute(
                "SELECT * FROM gain_check "
                + ("WHERE " + " AND ".join(clauses) if clauses else "")
                + " ORDER BY date, id",
                args,
            ).fetchall()
        except sqlite3.OperationalError:  # a read-only database of a version without checks
            rows = []
        return [
            CheckEntry(
                **{k: r[k] for k in r.keys() if k != "record"}, record=json.loads(r["record"])
            )
            for r in rows
        ]


def remove(entry_id: int, *, db=None) -> Entry:
    """Remove one entry (the database's record only: the result files stay)."""
    with _opened(db, write=True) as con:
        found = _one(con, entry_id, db)
        con.execute("DELETE FROM calibration WHERE id = ?", (int(entry_id),))
        return found


def relocate(entry_id: int, result, *, db=None) -> Entry:
    """Point an entry at its result's new place (a moved project); the file must be the
    one added (same SHA-256)."""
    cal = load_calibration(result)
    digest = ",".join(cal.sha256)
    with _opened(db, write=True) as con:
        if _one(con, entry_id, db).sha256 != digest:
            raise OptionError(
                f"{cal.label}: not the result of entry {entry_id} (its content "
                "differs from the one added)"
            )
        path = _stored_paths(cal.files, db)
        con.execute("UPDATE calibration SET path = ? WHERE id = ?", (path, int(entry_id)))
    return entry(entry_id, db=db)


def _home(db) -> Path:
    return (Path(db) if db is not None else default_path()).resolve().parent


def _stored_paths(files, db) -> str:
    """The result paths to store: relative to the database's folder where inside it."""
    home, out = _home(db), []
    for f in files:
        f = Path(f).resolve()
        out.append(f.relative_to(home).as_posix() if f.is_relative_to(home) else str(f))
    return ",".join(out)


def _found_paths(stored: str, db) -> str:
    home = _home(db)
    return ",".join(str(home / p) if not Path(p).is_absolute() else p for p in stored.split(","))


def _one(con, entry_id, db) -> Entry:
    found = _entries(con, db, "WHERE id = ?", (int(entry_id),))
    if not found:
        raise OptionError(f"no entry {entry_id} in the calibration database {db or default_path()}")
    return found[0]


def _entries(con, db, where="", args=()) -> list[Entry]:
    rows = con.execute(f"SELECT * FROM calibration {where} ORDER BY date, id", args).fetchall()
    out = []
    for r in rows:
        gains = {
            g["setpoint"]: (g["median"], g["se"], g["n"])
            for g in con.execute(
                "SELECT * FROM gain WHERE calibration_id = ? ORDER BY setpoint", (r["id"],)
            )
        }
        fields = {k: r[k] for k in r.keys() if k != "summary"}
        out.append(Entry(**{**fields, "path": _found_paths(r["path"], db)}, gains=gains))
    return out


def entries(*, db=None, camera=None, readout=None) -> list[Entry]:
    """Entries, oldest first, of one camera (and read-out state) or of all."""
    clauses, args = [], []
    if camera is not None:
        clauses.append("camera = ?")
        args.append(str(camera))
    if readout is not None:
        clauses.append("readout = ?")
        args.append(str(readout))
    with _opened(db) as con:
        return _entries(con, db, ("WHERE " + " AND ".join(clauses)) if clauses else "", args)


def entry(entry_id: int, *, db=None, with_summary: bool = False):
    """One entry by its id (with its stored summary as a second value if asked)."""
    with _opened(db) as con:
        found = _one(con, entry_id, db)
        if with_summary:
            summary = con.execute(
                "SELECT summary FROM calibration WHERE id = ?", (int(entry_id),)
            ).fetchone()[0]
            return found, json.loads(summary)
        return found


def find(camera, setpoint, *, db=None, readout=None) -> Entry:
    """The newest entry of a camera that has a gain at ``setpoint``, its file checked.

    Raises
    ------
    OptionError
        No such entry, one of several read-out states without ``readout`` given, or a
        result file that is missing or changed since it was added.
    """
    s = float(setpoint)
    found = [e for e in entries(db=db, camera=camera, readout=readout) if s == 1.0 or s in e.gains]
    if not found:
        raise OptionError(
            f"the calibration database has no calibration of camera {camera}"
            f"{'' if readout is None else f' ({readout})'} at set-point "
            f"{format_setpoint(s)}x"
        )
    return _checked(_one_state(found, camera)[-1])


def calibration(camera, setpoint, *, db=None, readout=None):
    """The calibration of a camera to use at a set-point: its newest calibration there,
    or, where none measured it, its newest calibration with two or more multiplied
    set-points, with the gain there predicted by their gain curve
    (:func:`~emccdcal.export.gain_curve.calibration_at`, which warns and records it).

    Returns
    -------
    emccdcal.result.Calibration

    Raises
    ------
    OptionError
        As :func:`find`, or no calibration to predict the set-point from.
    """
    from .gain_curve import calibration_at, fit_gain_curve

    s = float(setpoint)
    every = entries(db=db, camera=camera, readout=readout)
    if not every or any(s in e.gains for e in every) or s == 1.0:
        return load_calibration(find(camera, s, db=db, readout=readout).path)
    curved = [e for e in every if len(e.gains) >= 2]
    if not curved:
        raise OptionError(
            f"the calibration database has no calibration of camera {camera} "
            f"at set-point {format_setpoint(s)}x, and none with two or more "
            "multiplied set-points whose gain curve could predict it"
        )
    newest = _checked(_one_state(curved, camera)[-1])
    cal = load_calibration(newest.path)
    return calibration_at(
        cal, s, fit_gain_curve([cal]), source=f"of database entry {newest.id} ({newest.date[:10]})"
    )


def _one_state(found: list, camera) -> list:
    states = {e.readout for e in found}
    if len(states) > 1:
        raise OptionError(
            f"camera {camera} has calibrations in several read-out states "
            f"({'; '.join(sorted(states))}); give --readout"
        )
    return found


def _checked(newest: Entry) -> Entry:
    """The entry, its result files present and unchanged since added."""
    files = newest.path.split(",")
    digests = [file_sha256(f) if Path(f).is_file() else None for f in files]
    if ",".join(str(d) for d in digests) != newest.sha256:
        raise OptionError(
            f"entry {newest.id}: its result {newest.path} is missing or has "
            "changed since it was added to the database"
        )
    return newest


@dataclass(frozen=True)
class Finding:
    """What :func:`compare` flags: ``kind`` is ``"age"``, ``"change"`` (the newest
    calibration against the one before), ``"check"`` (a gain check against the
    calibration before it) or ``"trend"``."""

    kind: str
    setpoint: float | None
    message: str


def compare(camera, *, db=None, readout=None, max_age_days=None, z=3.0, now=None):
    """A camera's gains over time, and what is wrong with its newest calibration.

    Parameters
    ----------
    camera : str
        Its serial number.
    max_age_days : float, optional
        Flag the newest calibration when older than this.
    z : float
        Flag a gain that differs from the previous calibration's under the same register
        model by more than ``z`` combined standard errors (√(SE₁² + SE₂²)), a gain check
        that differs so from the calibration before it, and a trend whose slope is beyond
        ``z`` of its standard error (default 3).
    now : str, optional
        The date to measure age from (ISO 8601; default: now).

    Returns
    -------
    (list of Entry, list of Finding)
        The camera's entries (oldest first) and the findings; its gain checks are
        :func:`checks`'.
    """
    found = entries(db=db, camera=camera, readout=readout)
    if not found:
        raise OptionError(f"the calibration database has no calibration of camera {camera}")
    _one_state(found, camera)
    newest = found[-1]
    findings = _age(found, camera, max_age_days, now) + _changes(found, camera, z)
    checked = checks(db=db, camera=camera, readout=newest.readout)
    findings += _checks_against(found, checked, camera, z) + _trends(found, checked, camera, z)
    return found, findings


def _age(found, camera, max_age_days, now) -> list[Finding]:
    newest, findings = found[-1], []
    if max_age_days is not None:
        when = _parse(_iso_date(now or _dt.datetime.now(_dt.timezone.utc).isoformat()))
        age = (when - _parse(newest.date)).total_seconds() / 86400
        if age > max_age_days:
            findings.append(
                Finding(
                    "age",
                    None,
                    (
                        f"camera {camera}: the newest calibration (entry {newest.id}, {newest.date[:10]}) "
                        f"is {age:.0f} days old, more than {max_age_days:g}; recalibrate"
                    ),
                )
            )
    return findings


def _changes(found, camera, z) -> list[Finding]:
    """The newest calibration against the one before it, set-point by set-point."""
    newest, findings = found[-1], []
    for s, (g_new, se_new, _) in sorted(newest.gains.items()):
        before = [e for e in found[:-1] if s in e.gains and e.register == newest.register]
        if not before:
            continue
        prev = before[-1]
        g_old, se_old, _ = prev.gains[s]
        se = math.hypot(se_new or 0.0, se_old or 0.0)
        change = g_new / g_old - 1
        if se > 0 and abs(g_new - g_old) > z * se:
            findings.append(
                Finding(
                    "change",
                    s,
                    (
                        f"camera {camera} at {format_setpoint(s)}x: gain {g_new:.4g} (entry "
                        f"{newest.id}, {newest.date[:10]}) against {g_old:.4g} (entry {prev.id}, "
                        f"{prev.date[:10]}): {change:+.2%}, {abs(g_new - g_old) / se:.1f} standard "
                        "errors; the register may have aged: use the newest calibration"
                    ),
                )
            )
    return findings


def _checks_against(found, checked, camera, z) -> list[Finding]:
    """The newest gain check of each set-point against the newest calibration before it
    under the same register model (its sensor gain's SE and the check's combined)."""
    findings = []
    for s in sorted({c.setpoint for c in checked}):
        check = [c for c in checked if c.setpoint == s][-1]
        before = [
            e
            for e in found
            if s in e.gains and e.register == check.register and e.date <= check.date
        ]
        if not before:
            continue
        cal = before[-1]
        g_cal, se_cal, _ = cal.gains[s]
        se = math.hypot(check.se, se_cal or 0.0)
        if se > 0 and abs(check.em_gain - g_cal) > z * se:
            side = "below" if check.em_gain < g_cal else "above"
            findings.append(
                Finding(
                    "check",
                    s,
                    (
                        f"camera {camera} at {format_setpoint(s)}x: the gain check of "
                        f"{check.date[:10]} (check {check.id}) finds the gain "
                        f"{abs(check.em_gain / g_cal - 1):.1%} {side} its calibration of "
                        f"{cal.date[:10]} (entry {cal.id}), {abs(check.em_gain - g_cal) / se:.1f} "
                        "standard errors: recalibrate"
                    ),
                )
            )
    return findings


def _trends(found, checked, camera, z, min_points=3) -> list[Finding]:
    """A straight line in time through each set-point's gains (calibrations and checks
    under the newest's register model), weighted by their standard errors: its slope
    beyond ``z`` of its standard error is a drift, even where no two neighbours differ
    by that much."""
    findings = []
    register = found[-1].register
    for s in sorted({s for e in found for s in e.gains} | {c.setpoint for c in checked}):
        points = [
            (e.date, e.gains[s][0], e.gains[s][1])
            for e in found
            if s in e.gains and e.register == register
        ]
        points += [
            (c.date, c.em_gain, c.se) for c in checked if c.setpoint == s and c.register == register
        ]
        points = [(when, g, se) for when, g, se in points if se and se > 0]
        if len(points) < min_points:
            continue
        years = np.array(
            [
                (_parse(when) - _parse(points[0][0])).total_seconds() / (365.25 * 86400)
                for when, _, _ in sorted(points)
            ]
        )
        if np.ptp(years) <= 0:
            continue
        y = np.log([g for _, g, _ in sorted(points)])
        w = np.array([(g / se) ** 2 for _, g, se in sorted(points)])  # 1/var(ln g)
        X = np.column_stack([np.ones_like(years), years])
        cov = np.linalg.inv(X.T @ (w[:, None] * X))
        slope = float((cov @ (X.T @ (w * y)))[1])
        slope_se = math.sqrt(cov[1, 1])
        if abs(slope) > z * slope_se:
            findings.append(
                Finding(
                    "trend",
                    s,
                    (
                        f"camera {camera} at {format_setpoint(s)}x: the gain drifts by "
                        f"{math.expm1(slope):+.1%} a year over {len(points)} calibrations and checks "
                        f"since {sorted(points)[0][0][:10]} ({abs(slope) / slope_se:.1f} standard "
                        "errors of the slope): recalibrate, and check more often"
                    ),
                )
            )
    return findings
