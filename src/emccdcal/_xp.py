"""The array namespace of the likelihood's hot path (the Python array API standard).

The engine's elementwise work is written against the standard
(https://data-apis.org/array-api/latest/), so that the same code runs on NumPy arrays
(the default), on CuPy's and PyTorch's (``array-api-compat`` gives each its standard
namespace), and on ``array-api-strict``'s, which the tests use to prove that no
NumPy-only call slipped in. Arrays keep their namespace and device: a function given
NumPy arrays returns NumPy arrays, bit for bit what it returned before.

What the standard lacks goes through here, once.
"""

from __future__ import annotations

import contextlib
import contextvars
import threading

import numpy as np
from array_api_compat import array_namespace, device, is_array_api_obj, is_numpy_namespace

from . import defaults
from .errors import OptionError

__all__ = [
    "namespace",
    "asarrays",
    "device",
    "is_complex",
    "DEVICES",
    "resolve",
    "computing_on",
    "engine",
    "free_bytes",
    "on",
    "like",
    "to_numpy",
    "bincount",
    "rfft",
    "scattered_rfft",
    "irfft",
]


def namespace(*arrays):
    """The standard namespace of ``arrays`` (array-api-compat's), ignoring anything that
    is not an array (Python numbers, None); NumPy's where there is none."""
    found = [a for a in arrays if is_array_api_obj(a)]
    return array_namespace(*found) if found else array_namespace(np.empty(0))


def asarrays(*values):
    """``(xp, arrays)``: the namespace of the arrays among ``values`` and every value
    as an array of it (lists and numbers converted; NumPy's namespace if none is an
    array)."""
    xp = namespace(*values)
    return xp, tuple(xp.asarray(v) for v in values)


def is_complex(xp, array) -> bool:
    """Whether ``array`` holds complex numbers."""
    return xp.isdtype(array.dtype, "complex floating")


# --------------------------------------------------------------------------------------
# Where a fit computes: the namespace of the likelihood's hot path
# --------------------------------------------------------------------------------------
#: What a user may ask for (``calibrate --device``; declared in :mod:`emccdcal.defaults`).
DEVICES = defaults.DEVICES

_ENGINE: contextvars.ContextVar = contextvars.ContextVar("engine_namespace", default=None)
#: Threads of each FFT (scipy.fft's ``workers``; -1: every CPU), in this context: a fit
#: on several threads, or in a process that runs one task per CPU (a Dask worker), asks
#: for fewer. A context variable, never module state: each thread's fit its own.
_FFT_WORKERS: contextvars.ContextVar = contextvars.ContextVar("fft_workers", default=-1)


def resolve(device: str | None):
    """``(xp, device)`` of a device name (:data:`DEVICES`), or one clear
    :class:`~emccdcal.errors.OptionError` saying what is missing."""
    if device in (None, "cpu"):
        return array_namespace(np.empty(0)), "cpu"
    if device == "array-api-strict":
        try:
            import array_api_strict
        except ImportError:
            raise OptionError(
                "device 'array-api-strict' needs the package array-api-strict "
                "(pip install array-api-strict)"
            ) from None
        # A device of its own that is not the CPU: its arrays refuse to become NumPy's,
        # as a GPU's do, so nothing outside the standard passes unnoticed.
        return array_api_strict, array_api_strict.Device("device1")
    if device == "cuda":
        return _cuda()
    if device == "jax":
        return _jax()
    raise OptionError(f"device {device!r}: expected one of {', '.join(DEVICES)}")


def _cuda():
    """CuPy's namespace on the current GPU, else PyTorch's; a clear line otherwise."""
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() > 0:
            import array_api_compat.cupy as xp

            return xp, cupy.cuda.Device()
    except Exception:  # noqa: BLE001 - no CuPy, or CuPy without a GPU: try PyTorch
        pass
    try:
        import torch

        if torch.cuda.is_available():
            import array_api_compat.torch as xp

            return xp, torch.device("cuda")
    except ImportError:
        pass
    raise OptionError(
        "device 'cuda': no GPU found through CuPy or PyTorch: install CuPy for the "
        "card's CUDA (pip install '.[gpu]' in emccdcal's source folder for CUDA 12, "
        "'.[gpu-cuda13]' for CUDA 13; 'nvidia-smi' shows the version) and check that "
        "the NVIDIA driver sees the card"
    )


def _jax():
    """JAX's namespace (``jax.numpy``, which follows the array API standard) on its first
    device: a GPU where JAX has one, else the CPU. The likelihood needs float64, which
    JAX gives only once asked: this turns on its ``jax_enable_x64`` for the process."""
    try:
        import jax
    except ImportError:
        raise OptionError(
            "device 'jax' needs JAX: pip install jax (CPU), or 'jax[cuda12]' for an NVIDIA GPU"
        ) from None
    if not jax.config.jax_enable_x64:  # (setting it again would empty JAX's caches)
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as xp

    return xp, jax.devices()[0]


def compiles_shapes(xp) -> bool:
    """Whether ``xp`` compiles each operation for each array shape it meets (JAX): work
    for such a library is best kept to a few shapes."""
    return xp.__name__.startswith("jax")


@contextlib.contextmanager
def computing_on(device: str | None, *, fft_workers: int | None = None):
    """Within this block (this thread), the likelihood's hot path computes on ``device``
    (:data:`DEVICES`); arrays go there and their per-pixel sums come back to NumPy. With
    ``fft_workers``, each FFT of the block runs on that many threads (:func:`fft_workers`)."""
    token = _ENGINE.set(resolve(device))
    workers = None if fft_workers is None else _FFT_WORKERS.set(int(fft_workers))
    try:
        yield
    finally:
        if workers is not None:
            _FFT_WORKERS.reset(workers)
        _ENGINE.reset(token)


def fft_workers() -> int:
    """Threads of each FFT in this context (scipy.fft's ``workers``; -1: every CPU)."""
    return _FFT_WORKERS.get()


def engine():
    """``(xp, device)`` where the hot path computes now (NumPy on the CPU by default)."""
    chosen = _ENGINE.get()
    return chosen if chosen is not None else (array_namespace(np.empty(0)), "cpu")


def free_bytes(xp, dev) -> int | None:
    """Free memory of a GPU (bytes), as its library reports it; None elsewhere."""
    name = xp.__name__
    if "cupy" in name:
        import cupy

        return int(cupy.cuda.runtime.memGetInfo()[0])
    if "torch" in name:
        import torch

        return int(torch.cuda.mem_get_info(dev)[0])
    if name.startswith("jax") and dev.platform == "gpu":
        stats = dev.memory_stats() or {}
        return int(stats.get("bytes_limit", 0) - stats.get("bytes_in_use", 0)) or None
    return None


def on(xp, dev, *arrays):
    """``arrays`` (NumPy or of ``xp``) as arrays of ``xp`` on ``dev`` (no copy for NumPy
    into NumPy)."""
    if is_numpy_namespace(xp):
        return arrays[0] if len(arrays) == 1 else arrays
    out = tuple(xp.asarray(a, device=dev) for a in arrays)
    return out[0] if len(out) == 1 else out


def like(ref, *arrays):
    """``arrays`` as arrays of ``ref``'s namespace and device."""
    return on(namespace(ref), device(ref), *arrays)


#: Below this modulus e^z − 1 is taken by ``expm1`` (:func:`expm1`); above it, e^z − 1
#: loses at most a few units in the last place (|e^z − 1| ≥ 0.49 there on the imaginary
#: axis, where the transforms' arguments lie).
EXPM1_BELOW = 0.5


def expm1(xp, z, exp_z=None):
    """e^z − 1 of a complex array ``z`` (..., M) without cancellation where |z| is small.

    A complex ``expm1`` costs about 2.4 times an ``exp`` (NumPy 2.4: 6.7 against 2.8 ms
    for 128 × 1000), and only near z = 0 does ``exp(z) − 1`` lose digits. A transform's
    arguments z = s·c (s = t + iω, a column per frequency ω, rising along the last axis)
    are small only in a run of columns about ω = 0: there, and in every column between
    the first and last that holds one (so any z is right), ``expm1``; elsewhere ``exp``
    (``exp_z`` where the caller has it)."""
    e = (xp.exp(z) if exp_z is None else exp_z) - 1.0
    small = to_numpy(xp.any(abs(z) < EXPM1_BELOW, axis=tuple(range(z.ndim - 1))))
    cols = np.flatnonzero(small)
    if cols.size == 0:
        return e
    a, b = int(cols[0]), int(cols[-1]) + 1
    return xp.concat([e[..., :a], xp.expm1(z[..., a:b]), e[..., b:]], axis=-1)


def to_numpy(array) -> np.ndarray:
    """A NumPy array of ``array`` (on the host), whatever its namespace."""
    if isinstance(array, np.ndarray) or np.isscalar(array):
        return np.asarray(array)
    if hasattr(array, "get") and type(array).__module__.startswith("cupy"):
        return array.get()
    if type(array).__module__.startswith("torch"):
        return array.detach().cpu().numpy()
    if type(array).__module__.startswith("jax"):
        return np.asarray(array)
    if type(array).__module__.startswith("array_api_strict"):
        import array_api_strict

        array = array.to_device(array_api_strict.Device("CPU_DEVICE"))
    return np.from_dlpack(array)


def bincount(xp, index, weights, minlength: int):
    """Sums of ``weights`` (None: counts) at each integer of ``index`` (1-D), length
    ``minlength``: not in the standard; CuPy's and PyTorch's own, NumPy's for the
    others."""
    if is_numpy_namespace(xp):
        return np.bincount(index, weights=weights, minlength=minlength)
    name = xp.__name__
    if "cupy" in name:
        import cupy

        return cupy.bincount(index, weights=weights, minlength=minlength)
    if "torch" in name:
        import torch

        return torch.bincount(index, weights=weights, minlength=minlength)
    if name.startswith("jax"):
        return xp.bincount(index, weights=weights, minlength=minlength, length=minlength)
    out = np.bincount(
        to_numpy(index), weights=None if weights is None else to_numpy(weights), minlength=minlength
    )
    return xp.asarray(out, device=device(index))


def rfft(xp, a, workers):
    """The real FFT along the last axis (SciPy's, on ``workers`` threads, for NumPy)."""
    if is_numpy_namespace(xp):
        from scipy import fft

        return fft.rfft(a, axis=-1, workers=workers)
    return xp.fft.rfft(a, axis=-1)


def scattered_rfft(xp, index, weights, shape, m: int, workers):
    """The first ``m`` bins of the real FFT along the last axis of a grid of ``shape``
    (rows, n) that is zero but for ``weights`` at the flat positions ``index`` (1-D,
    the same length); positions of non-zero weights are distinct (a histogram's
    values; its padding, of weight zero, may repeat them)."""
    if not is_numpy_namespace(xp):
        grid = bincount(xp, index, weights, shape[0] * shape[1])
        return rfft(xp, xp.reshape(grid, shape), workers)[:, :m]
    from scipy import fft

    nonzero = weights != 0
    index, weights = index[nonzero], weights[nonzero]
    with _SCRATCH.zeros(shape, np.float64) as grid:
        flat = grid.reshape(-1)
        try:
            flat[index] = weights
            return fft.rfft(grid, axis=-1, workers=workers)[:, :m]
        finally:
            flat[index] = 0.0


def irfft(xp, a, n: int, workers, *, conjugate=False, single=False):
    """The inverse real FFT of length n along the last axis (SciPy's for NumPy), of ``a``
    or, with ``conjugate``, of its complex conjugate; bins beyond ``a``'s are zero. With
    ``single``, in single precision (about half the time; 1e-7 of the largest value)."""
    if single:
        a = xp.astype(a, xp.complex64)
    if is_numpy_namespace(xp):
        from scipy import fft

        if conjugate:
            # The conjugate written straight into a zero-padded spectrum kept from call
            # to call (SciPy's FFT only reads it): the few bins written, not all of them.
            m = a.shape[-1]
            with _SCRATCH.zeros(a.shape[:-1] + (n // 2 + 1,), a.dtype) as full:
                try:
                    np.conjugate(a, out=full[..., :m])
                    return fft.irfft(full, n=n, axis=-1, workers=workers)
                finally:
                    full[..., :m] = 0.0
        return fft.irfft(a, n=n, axis=-1, workers=workers)
    return xp.fft.irfft(xp.conj(a) if conjugate else a, n=n, axis=-1)


class _Scratch(threading.local):
    """Each thread's zero-filled arrays, one per dtype, kept from call to call.

    The engine's FFTs take grids of thousands of points per pixel of which a few dozen
    are non-zero (a spectrum's band, a histogram's values): made anew, each costs a pass
    over all of it, about half as much as the transform; kept, only the entries written
    are set back to zero (by the caller, before it leaves :meth:`zeros`). Grids above
    :data:`_SCRATCH_ELEMENTS`, and one asked for while the dtype's is in use, are made
    anew.
    """

    def __init__(self):
        self.arrays, self.busy = {}, set()

    @contextlib.contextmanager
    def zeros(self, shape, dtype):
        size = int(np.prod(shape))
        key = np.dtype(dtype)
        if size > _SCRATCH_ELEMENTS or key in self.busy:
            yield np.zeros(shape, dtype)
            return
        kept = self.arrays.get(key)
        if kept is None or kept.size < size:
            kept = self.arrays[key] = np.zeros(size, dtype)
        self.busy.add(key)
        try:
            yield kept[:size].reshape(shape)
        finally:
            self.busy.discard(key)


#: Largest grid (elements) a thread keeps: 64 MB of complex numbers.
_SCRATCH_ELEMENTS = 2**22
_SCRATCH = _Scratch()
