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

import numpy as np
from array_api_compat import array_namespace, device, is_array_api_obj

__all__ = ["namespace", "asarrays", "device", "from_numpy", "is_complex"]


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


def from_numpy(xp, array, like=None):
    """A small NumPy array (a table, a transform matrix) in namespace ``xp``, on the
    device of ``like``."""
    if like is None:
        return xp.asarray(array)
    return xp.asarray(array, device=device(like))


def is_complex(xp, array) -> bool:
    """Whether ``array`` holds complex numbers."""
    return xp.isdtype(array.dtype, "complex floating")
