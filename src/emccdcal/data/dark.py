"""Offset and read-noise maps from dark stacks.

A dark (shuttered) acquisition recorded at a gain set-point gives, per pixel, the offset
``offset`` = S0 (the mean dark count, ADU) and the read noise ``read_noise`` = σ (the
standard deviation of the dark counts, ADU). The paper records one dark stack right
after each set-point because the offset drifts with the set-point (Ryan et al. 2021, Methods).

At high EM gain the dark frames also contain clock-induced charge (spurious electrons
that the EM register multiplies), so the dark "σ" grows with the set-point and is then
not pure Gaussian read-out noise (docs/simulation.md): :func:`check_read_noise_growth` says so.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import InputError

__all__ = ["as_stack", "maps_from_dark", "check_read_noise_growth", "DEFAULT_CHUNK_ELEMENTS"]

#: Elements (frames × pixels) converted to float64 at a time when streaming a dark
#: stack: 2**23 elements = 64 MiB.
DEFAULT_CHUNK_ELEMENTS = 2**23


def as_stack(stack, what="stack"):
    """``stack`` as a (frames, rows, cols) array of numbers (memory maps stay as they are).

    Raises a ValueError naming ``what`` for another shape or a non-numeric dtype.
    """
    if not hasattr(stack, "shape") or not hasattr(stack, "dtype"):
        stack = np.asarray(stack)
    if stack.ndim != 3:
        raise InputError(f"{what} must be 3-D (frames, rows, cols), got shape {tuple(stack.shape)}")
    if stack.dtype.kind not in "uif":
        raise InputError(f"{what} must hold numbers, got dtype {stack.dtype}")
    return stack


def maps_from_dark(stack, *, chunk_frames: int | None = None):
    """Per-pixel offset and read-noise maps of a dark stack.

    The stack is streamed in chunks of frames; only one chunk at a time is converted to
    float64, so a memory-mapped dark larger than memory can be used. Chunks are combined
    with the exact pairwise update of count, mean and sum of squared deviations (Chan,
    Golub & LeVeque), which is as accurate as the two-pass formula.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw dark counts (ADU), integer or integer-valued float; a NumPy memmap is read
        chunk by chunk. At least 2 frames.
    chunk_frames : int, optional
        Frames per chunk. Default: as many as fit in :data:`DEFAULT_CHUNK_ELEMENTS`
        elements. The result does not depend on it (up to float64 round-off).

    Returns
    -------
    offset : ndarray of float64, shape (rows, cols)
        Per-pixel mean of the dark counts, ADU.
    read_noise : ndarray of float64, shape (rows, cols)
        Per-pixel standard deviation of the dark counts (ddof=1), ADU.

    Raises
    ------
    ValueError
        If the stack is not 3-D, has fewer than 2 frames, is not numeric, or contains
        NaN or infinite values.

    Examples
    --------
    >>> dark = np.array([[[100, 200]], [[102, 200]], [[104, 200]]], dtype=np.uint16)
    >>> offset, read_noise = maps_from_dark(dark)
    >>> offset.tolist(), read_noise.tolist()
    ([[102.0, 200.0]], [[2.0, 0.0]])
    """
    stack = as_stack(stack, "dark stack")
    n_frames, rows, cols = stack.shape
    if n_frames < 2:
        raise InputError(
            f"dark stack needs at least 2 frames for a standard deviation, got {n_frames}"
        )
    if chunk_frames is None:
        chunk_frames = max(1, DEFAULT_CHUNK_ELEMENTS // max(1, rows * cols))
    elif int(chunk_frames) < 1:
        raise InputError(f"chunk_frames must be >= 1, got {chunk_frames}")
    chunk_frames = int(chunk_frames)

    n = 0
    mean = np.zeros((rows, cols))
    m2 = np.zeros((rows, cols))  # sum of squared deviations from the mean
    for start in range(0, n_frames, chunk_frames):
        chunk = np.asarray(stack[start : start + chunk_frames], dtype=np.float64)
        nb = chunk.shape[0]
        mean_b = chunk.mean(axis=0)
        chunk -= mean_b
        m2_b = np.einsum("fij,fij->ij", chunk, chunk)
        delta = mean_b - mean
        total = n + nb
        mean += delta * (nb / total)
        m2 += m2_b + delta**2 * (n * nb / total)
        n = total
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(m2))):
        raise InputError("dark stack contains NaN or infinite values")
    return mean, np.sqrt(m2 / (n - 1))


def check_read_noise_growth(
    setpoints: Sequence[float], read_noise_maps: Sequence, *, threshold: float = 0.05
) -> list[str]:
    """Warn when the read noise of the darks grows with the EM gain set-point.

    Compares the median read noise at every set-point with the median at the lowest
    set-point. Where it is more than ``threshold`` (relative) higher, the dark frames
    most likely contain clock-induced charge that the EM register multiplies
    (docs/simulation.md): the dark "σ" is then not pure Gaussian read-out noise. On the shared ProEM data
    the median grows from about 15.5 ADU (1× to 25×) to about 23 ADU at 300×.

    Parameters
    ----------
    setpoints : sequence of float
        EM gain set-point (dimensionless) of each map.
    read_noise_maps : sequence of array_like
        Read-noise maps (ADU), one per set-point entry; several maps with the same
        set-point are pooled.
    threshold : float, optional
        Relative growth that triggers a warning (default 0.05, i.e. 5 %).

    Returns
    -------
    list of str
        One message per set-point whose median read noise exceeds the reference by more
        than ``threshold``, in increasing set-point order; empty when none does.

    Examples
    --------
    >>> maps = [np.full((2, 2), 15.5), np.full((2, 2), 15.6), np.full((2, 2), 23.3)]
    >>> msgs = check_read_noise_growth([1, 100, 300], maps)
    >>> len(msgs), msgs[0].startswith("read noise at EM gain set-point 300")
    (1, True)
    """
    setpoints = [float(s) for s in setpoints]
    read_noise_maps = list(read_noise_maps)
    if len(setpoints) != len(read_noise_maps):
        raise InputError(
            f"got {len(setpoints)} set-points but {len(read_noise_maps)} read-noise maps"
        )
    if not (np.isfinite(threshold) and threshold >= 0):
        raise InputError(f"threshold must be a non-negative number, got {threshold!r}")
    pooled: dict[float, list[np.ndarray]] = {}
    for g, m in zip(setpoints, read_noise_maps):
        pooled.setdefault(g, []).append(np.ravel(np.asarray(m, dtype=np.float64)))
    medians = {g: float(np.median(np.concatenate(ms))) for g, ms in pooled.items()}
    if not all(np.isfinite(m) and m > 0 for m in medians.values()):
        raise InputError(f"read-noise medians must be positive and finite, got {medians}")
    if len(medians) < 2:
        return []
    ordered = sorted(medians)
    g0 = ordered[0]
    ref = medians[g0]
    messages = []
    for g in ordered[1:]:
        growth = medians[g] / ref - 1.0
        if growth > threshold:
            messages.append(
                f"read noise at EM gain set-point {g:g} (median {medians[g]:.1f} ADU) is "
                f"{100 * growth:.0f} % above that at set-point {g0:g} ({ref:.1f} ADU): the "
                "dark frames probably contain clock-induced charge, which the EM register "
                "multiplies, so this read noise is not pure Gaussian read-out noise; it "
                "matters for faint pixels, hardly for bright calibration data"
            )
    return messages
