"""Private helpers shared by the whole package: one of each, never a copy.

- (writing files has a module of its own: :mod:`emccdcal._output`);
- :func:`progress`: every progress bar;
- :func:`check_int`, :func:`check_number`, :func:`check_map`, :func:`e_per_adu_map`:
  argument validators whose errors are one-line :class:`~emccdcal.errors.OptionError`;
- :func:`parse_pixel`, :func:`finite_or_none`, :func:`one_line`: small conversions.

Nothing here imports more than NumPy (tqdm only when a bar is shown), so any module may
use it.
"""

from __future__ import annotations

import math
import operator
import sys
from collections.abc import Iterable

import numpy as np

from .defaults import BOUNDS
from .errors import InputError, OptionError

__all__ = [
    "progress",
    "check_int",
    "check_number",
    "check_map",
    "e_per_adu_map",
    "parse_pixel",
    "finite_or_none",
    "one_line",
    "format_setpoint",
]


# --------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------
def install_hint(extra: str) -> str:
    """How to install an extra, for a message: from the source folder, as the
    Installation page says (the package is not on an index).

    >>> install_hint("dask")
    "pip install '.[dask]' in emccdcal's source folder (the docs' Installation page)"
    """
    return f"pip install '.[{extra}]' in emccdcal's source folder (the docs' Installation page)"


def progress(
    iterable: Iterable | None = None,
    *,
    enabled,
    desc: str,
    unit: str = "it",
    total: int | None = None,
):
    """A progress bar, or a silent stand-in when ``enabled`` is false.

    The bar is tqdm's: a widget in Jupyter (``tqdm.auto``), a line on a terminal's
    stderr, nothing where stderr is not a terminal (a pipe, a log file). Use it as an
    iterable wrapper or, with ``iterable=None``, as a bar to ``update(n)`` and
    ``close()`` (also a context manager). The bar shows a rate and an ETA and is removed
    when done. ``enabled`` may also be a callable ``enabled(done, total)``, told of every
    update instead of a bar (a graphical front's progress bar; it may raise
    :class:`emccdcal.errors.Cancelled` to stop the run).
    """
    if callable(enabled):
        return _Callback(iterable, enabled, total)
    if not enabled:
        return _Silent(iterable)
    from tqdm.auto import tqdm

    return tqdm(
        iterable, desc=desc, unit=unit, total=total, file=sys.stderr, leave=False, disable=None
    )


def emcee_progress(enabled) -> dict:
    """emcee's ``run_mcmc`` arguments for the bar :func:`progress` would show."""
    if not enabled:
        return {"progress": False}
    from tqdm.auto import tqdm
    from tqdm.notebook import tqdm_notebook

    kind = "notebook" if issubclass(tqdm, tqdm_notebook) else True
    return {"progress": kind, "progress_kwargs": {"disable": None, "leave": False}}


class _Silent:
    """What :func:`progress` returns when disabled: iterates, and ignores bar calls."""

    def __init__(self, iterable):
        self._iterable = iterable

    def __iter__(self):
        return iter(self._iterable)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass

    def set_postfix_str(self, text):
        pass

    def close(self):
        pass


class _Callback(_Silent):
    """What :func:`progress` returns for a callable: tells it of every update."""

    def __init__(self, iterable, callback, total):
        super().__init__(iterable)
        self._callback, self._total, self._done = callback, total, 0

    def __iter__(self):
        for item in self._iterable:
            yield item
            self.update(1)

    def update(self, n=1):
        self._done += n
        self._callback(self._done, self._total)


# --------------------------------------------------------------------------------------
# Validators
# --------------------------------------------------------------------------------------
def ordered_map(function, items, workers: int):
    """``map(function, items)`` on ``workers`` threads, in order, with at most
    ``workers + 1`` items taken from ``items`` and not yet returned: a generator of
    large items (bands of a stack read from disk) is consumed only as fast as its
    results are, so memory stays bounded."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    if workers <= 1:
        yield from map(function, items)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending = deque()
        for item in items:
            pending.append(pool.submit(function, item))
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def check_int(name: str, value, *, minimum: int | None = 1, maximum: int | None = None) -> int:
    """``value`` as an int within ``[minimum, maximum]``, or a one-line :class:`OptionError`.

    Integral floats (``3.0``) are accepted; booleans are not.

    Examples
    --------
    >>> check_int("frames", 3.0)
    3
    """
    if isinstance(value, (bool, np.bool_)):
        raise OptionError(f"{name} must be an integer, got {value!r}")
    try:
        out = operator.index(value)
    except TypeError:
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            out = int(value)
        else:
            raise OptionError(f"{name} must be an integer, got {value!r}") from None
    if (minimum is not None and out < minimum) or (maximum is not None and out > maximum):
        if maximum is None:
            rng = f">= {minimum}"
        elif minimum is None:
            rng = f"<= {maximum}"
        else:
            rng = f"from {minimum} to {maximum}"
        raise OptionError(f"{name} must be an integer {rng}, got {value!r}")
    within_bounds(name, np.asarray(out), value)
    return int(out)


def check_number(
    name: str,
    value,
    *,
    positive: bool = False,
    minimum: float | None = None,
    maximum: float | None = None,
    scalar: bool = True,
):
    """``value`` as a finite float (or float array) within its range, or an :class:`OptionError`.

    Parameters
    ----------
    name : str
        What the value is, for the message.
    value : number or array_like
        The value.
    positive : bool
        Require > 0.
    minimum, maximum : float, optional
        Inclusive bounds.
    scalar : bool
        Require a single number (returned as ``float``); else an array is returned.

    Examples
    --------
    >>> check_number("e_per_adu", "3.5", positive=True)
    3.5
    """
    if isinstance(value, (bool, np.bool_)):
        raise OptionError(f"{name} must be a number, got {value!r}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise OptionError(f"{name} must be a number, got {value!r}") from None
    if scalar and arr.ndim != 0:
        raise OptionError(f"{name} must be a single number, got an array of shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise OptionError(f"{name} must be finite, got {value!r}")
    if positive and np.any(arr <= 0):
        raise OptionError(f"{name} must be > 0, got {value!r}")
    if minimum is not None and np.any(arr < minimum):
        raise OptionError(f"{name} must be >= {minimum:g}, got {value!r}")
    if maximum is not None and np.any(arr > maximum):
        raise OptionError(f"{name} must be <= {maximum:g}, got {value!r}")
    within_bounds(name, arr, value)
    return float(arr) if scalar else arr


def within_bounds(name: str, arr, value, *, label: str | None = None) -> None:
    """Refuse a value (NaN included) outside the range its quantity ``name`` is taken as
    meant in (BOUNDS); the message names it ``label`` (default ``name``)."""
    if name not in BOUNDS:
        return
    low, high, unit = BOUNDS[name]
    if not np.all((arr >= low) & (arr <= high)):
        shown = (
            value if np.ndim(value) == 0 else f"a map spanning {np.min(arr):g} to {np.max(arr):g}"
        )
        raise OptionError(
            f"{label or name} {shown} is outside {low:g} to {high:g}"
            + (
                f" {unit}, the range it is taken as meant in (a value in another unit?)"
                if unit
                else ""
            )
        )


def weighted_gram(weights, a, b=None):
    """``Σ_k w[..., k] · a[..., k, i] · b[..., k, j]`` (..., I, J): stacked Gram matrices
    of the columns of ``a`` and ``b`` (default ``a``) weighted by ``w`` (an information
    from per-value scores and counts), as one batched matrix product: a three-operand
    ``einsum`` loops in C without BLAS, 3–8 times slower for a histogram's K values.

    Examples
    --------
    >>> a = np.arange(6.0).reshape(1, 3, 2)
    >>> weighted_gram(np.array([[1.0, 0.0, 2.0]]), a).tolist()
    [[[32.0, 40.0], [40.0, 51.0]]]
    """
    b = a if b is None else b
    return np.swapaxes(a * weights[..., None], -1, -2) @ b


def nanmedian(values, axis=None):
    """``np.nanmedian``, NaN where a slice holds no number, without NumPy's warning (a
    summary of pixels none of which converged is NaN, not a message about slices).

    Examples
    --------
    >>> float(nanmedian([np.nan, np.nan]))
    nan
    """
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(values, axis=axis)


def check_map(name: str, value, shape, **rules) -> np.ndarray:
    """A number or a (rows, cols) map as a read-only (rows, cols) float array, checked.

    ``rules`` are those of :func:`check_number` (``positive``, ``minimum``, ``maximum``).
    """
    arr = check_number(name, value, scalar=False, **rules)
    shape = tuple(int(d) for d in shape)
    if arr.ndim not in (0, 2):
        raise OptionError(f"{name} must be a number or a (rows, cols) map, got shape {arr.shape}")
    if arr.ndim == 2 and arr.shape != shape:
        raise OptionError(f"{name} map has shape {arr.shape}, expected (rows, cols) = {shape}")
    return np.broadcast_to(arr, shape)


def e_per_adu_map(value, shape) -> np.ndarray | None:
    """φ (e⁻/ADU) as a writable (rows, cols) float map, or None when ``value`` is None.

    ``value`` is a number or a (rows, cols) map; it must be positive and finite.
    """
    if value is None:
        return None
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), tuple(shape)).astype(float)
    except (TypeError, ValueError):
        raise OptionError(
            f"e_per_adu must be a number or a {tuple(shape)} map (e-/ADU), got {value!r}"
        ) from None
    if isinstance(value, (bool, np.bool_)) or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise OptionError("e_per_adu must be positive and finite (e-/ADU)")
    return arr


# --------------------------------------------------------------------------------------
# Conversions
# --------------------------------------------------------------------------------------
def parse_pixel(text) -> tuple[int, int]:
    """``"ROW,COL"`` → ``(row, col)``, or a one-line :class:`OptionError`.

    Examples
    --------
    >>> parse_pixel("1, 2")
    (1, 2)
    """
    parts = str(text).split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        row, col = (int(p.strip()) for p in parts)
    except ValueError:
        raise OptionError(
            f"malformed pixel {text!r}: expected ROW,COL (two integers), e.g. 1,1"
        ) from None
    return row, col


def parse_region(text) -> tuple[slice, slice]:
    """``"R0:R1,C0:C1"`` (either bound may be left out) → ``(rows, cols)`` slices, or a
    one-line :class:`OptionError`.

    Examples
    --------
    >>> parse_region("0:8,:")
    (slice(0, 8, None), slice(None, None, None))
    """
    parts = str(text).split(",")
    try:
        if len(parts) != 2 or any(part.count(":") != 1 for part in parts):
            raise ValueError
        rows, cols = (
            tuple(int(v) if v.strip() else None for v in part.split(":")) for part in parts
        )
    except ValueError:
        raise OptionError(
            f"malformed region {text!r}: expected rows and columns as "
            "R0:R1,C0:C1, e.g. 0:8,: for the first 8 rows"
        ) from None
    return slice(*rows), slice(*cols)


def finite_or_none(value) -> float | None:
    """A float for JSON, or None where it is not finite (JSON has no NaN).

    Examples
    --------
    >>> finite_or_none(2), finite_or_none(float("nan"))
    (2.0, None)
    """
    v = float(value)
    return v if math.isfinite(v) else None


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (its type's name where it has none)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def format_setpoint(value) -> str:
    """Canonical text of a set-point: integral values without a decimal point.

    Used for the keys of ``summary.json`` and in messages, so that ``5`` and ``5.0`` are
    the same key.

    Parameters
    ----------
    value : float
        A gain set-point (dimensionless), finite.

    Returns
    -------
    str
        ``"5"`` for 5.0, ``"1.5"`` for 1.5 (the shortest text that reads back as the
        same float).

    Examples
    --------
    >>> format_setpoint(5.0), format_setpoint(1.5), format_setpoint(300)
    ('5', '1.5', '300')
    """
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"set-point must be finite, got {value!r}")
    if v.is_integer():
        return str(int(v))
    return repr(v)
