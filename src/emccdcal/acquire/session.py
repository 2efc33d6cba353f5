"""A session folder's record of what was recorded (``session.json``): its stacks, in the
plan's order (:func:`stacks_of`), and how far each got, which ``acquire --resume``
continues from. The record supplies only progress, checked; every name and file is the
plan's own, so no text in it is ever a path."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

from .. import _files, defaults
from .._output import atomic_write_text
from .._util import format_setpoint, one_line
from ..errors import InputError
from .plan import Plan
from .plan_file import read_plan

__all__ = ["Stack", "Session", "stacks_of", "plan_sha", "new_state", "SESSION_FILE"]

#: The session's record of what was recorded.
SESSION_FILE = defaults.SESSION_FILE


# --------------------------------------------------------------------------------------
# What a plan records
# --------------------------------------------------------------------------------------
@dataclass
class Stack:
    """One stack of a session, as ``session.json`` records it."""

    name: str
    file: str
    dark: bool
    setpoint: float
    photoelectrons: float
    planned_frames: int
    frames: int = 0
    done: bool = False
    reached_se: float | None = None


def stacks_of(plan: Plan) -> list[Stack]:
    """The plan's stacks in recording order: a gain series' dark then light at each
    set-point; an intensity series' one dark, then its levels."""
    out = []
    if plan.method == "gs":
        for a in plan.acquisitions:
            sp = format_setpoint(a.setpoint)
            out.append(
                Stack(
                    f"{sp}x-dark", f"{sp}x-dark.ome.zarr", True, a.setpoint, 0.0, plan.dark_frames
                )
            )
            out.append(
                Stack(
                    f"{sp}x-gain",
                    f"{sp}x-gain.ome.zarr",
                    False,
                    a.setpoint,
                    a.photoelectrons,
                    a.frames,
                )
            )
    else:
        sp = plan.acquisitions[0].setpoint
        out.append(Stack("dark", "dark.ome.zarr", True, sp, 0.0, plan.dark_frames))
        for i, a in enumerate(plan.acquisitions, start=1):
            out.append(
                Stack(f"level-{i}", f"level-{i}.ome.zarr", False, sp, a.photoelectrons, a.frames)
            )
    return out


def _progress_of(stack: Stack, rec) -> None:
    """Set ``stack``'s progress (frames, done, reached SE) from its record, checked; the
    record must name the same stack."""
    if not isinstance(rec, dict) or rec.get("name") != stack.name or rec.get("file") != stack.file:
        raise ValueError(
            f"stack {stack.name!r} is recorded as "
            f"{rec.get('name') if isinstance(rec, dict) else rec!r}"
        )
    frames, done, se = rec.get("frames", 0), rec.get("done", False), rec.get("reached_se")
    if isinstance(frames, bool) or not isinstance(frames, int) or not 0 <= frames <= 10**9:
        raise ValueError(f"{stack.name}: frames is {frames!r}")
    if not isinstance(done, bool):
        raise ValueError(f"{stack.name}: done is {done!r}")
    if se is not None and (isinstance(se, bool) or not isinstance(se, (int, float))):
        raise ValueError(f"{stack.name}: reached_se is {se!r}")
    stack.frames, stack.done, stack.reached_se = frames, done, se


class Session:
    """A session folder's record (``session.json``), written atomically."""

    def __init__(self, folder: Path, state: dict):
        self.folder, self.state = folder, state
        self.stacks = [Stack(**s) for s in state["stacks"]]
        self._saved = 0.0

    @classmethod
    def load(cls, folder: Path, plan: Plan | None = None) -> Session:
        """The session recorded in ``folder`` for ``plan`` (default: the session's own
        ``plan.toml``). The stacks, their files' names included, are the plan's own
        (:func:`stacks_of`): the record supplies only how far each got, checked, so that
        no text in it is ever a path."""
        folder = Path(folder)
        plan = read_plan(folder / "plan.toml") if plan is None else plan
        path = folder / SESSION_FILE
        state = _files.load_json(path, what="session record")
        try:
            if not isinstance(state, dict) or not isinstance(state.get("stacks"), list):
                raise ValueError("no list of stacks")
            expected = stacks_of(plan)
            if len(state["stacks"]) != len(expected):
                raise ValueError(f"{len(state['stacks'])} stacks, the plan has {len(expected)}")
            for stack, rec in zip(expected, state["stacks"]):
                _progress_of(stack, rec)
            runs = state.get("runs", 1)
            if isinstance(runs, bool) or not isinstance(runs, int) or not 0 <= runs < 10**6:
                raise ValueError(f"runs is {runs!r}")
        except (ValueError, TypeError, AttributeError) as exc:
            raise InputError(f"'{path}': not a session of this plan ({one_line(exc)})") from None
        session = cls.__new__(cls)
        session.folder, session.state, session.stacks, session._saved = folder, state, expected, 0.0
        return session

    def save(self, *, every: float = 0.0) -> None:
        """Write session.json (with ``every``, at most once per ``every`` seconds and not
        flushed to disk: a progress record, while the stacks' writing fills the disk)."""
        now = time.monotonic()
        if every and now - self._saved < every:
            return
        self.state["stacks"] = [dataclasses.asdict(s) for s in self.stacks]
        atomic_write_text(
            self.folder / SESSION_FILE, json.dumps(self.state, indent=2) + "\n", durable=not every
        )
        self._saved = now


def plan_sha(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def new_state(plan: Plan, text: str, camera: str, roi, simulated: dict | None) -> dict:
    from .. import __version__

    return {
        "emccdcal_version": __version__,
        "plan_sha256": plan_sha(text),
        "camera": camera,
        "roi": None if roi is None else list(roi),
        "simulated": simulated,
        "runs": 1,
        "status": "recording",
        "stacks": [dataclasses.asdict(s) for s in stacks_of(plan)],
    }
