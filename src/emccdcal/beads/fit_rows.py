"""The optimizer over many small problems at once: each frame's spot parameters within
their bounds, evaluated in batches of frames, and the joint fit of a bead's frames with
the parameters they share (an arrowhead system, :func:`emccdcal._optimize.schur`)."""

from __future__ import annotations

import numpy as np

from .._optimize import maximize
from .fit_errors import _MIN_INTENSITY, _NP

#: Frames fitted per batch: bounds the memory of the Jacobians (~1 kB per frame and pixel).
_BATCH_FRAMES = 4096
#: A fit that no step improves any more counts as converged if an undamped step would gain
#: less than this (nats): far below statistical noise, at the exact table's round-off.
_STUCK_DECREMENT = 1e-3


# --------------------------------------------------------------------------------------
# The optimizer over many small problems at once
# --------------------------------------------------------------------------------------
def _lower_upper(half_size):
    h = half_size + 0.5
    lower = np.array([-h, -h, 0.3, _MIN_INTENSITY, 0.0])
    upper = np.array([h, h, 3.0 * half_size, np.inf, np.inf])
    return lower, upper


def _evaluate_rows(objective, p_rows, rows):
    """``objective`` at parameters ``p_rows`` of the rows ``rows``, in batches of
    :data:`_BATCH_FRAMES`."""
    ll = np.empty(rows.size)
    grad = np.empty((rows.size, _NP))
    H = np.empty((rows.size, _NP, _NP))
    for a in range(0, rows.size, _BATCH_FRAMES):
        b = min(rows.size, a + _BATCH_FRAMES)
        ll[a:b], grad[a:b], H[a:b] = objective(p_rows[a:b], rows[a:b])
    return ll, grad, H


def _fit_rows(objective, p0, lower, upper, *, tol, max_iter):
    """Maximise ``objective`` for every row of ``p0`` (M, 5) on its own.

    ``objective(p, rows)`` returns ``ll (m,)``, ``grad (m, 5)`` and a positive
    semi-definite curvature ``H (m, 5, 5)``. Returns the parameters and the per-row
    iterations.
    """
    opt = maximize(
        lambda rows, p: _evaluate_rows(objective, p, rows),
        p0,
        lower=lower,
        upper=upper,
        tol=tol,
        max_iter=max_iter,
        max_step=np.inf,
        accept_rtol=1e-10,
        stuck_tol=_STUCK_DECREMENT,
    )
    return opt.x, opt.iterations


def _joint_fit(objective, p, layout, *, tol, max_iter, beads=None):
    """Maximise every bead's summed log-likelihood over its shared parameters and each
    frame's own (``layout``), Newton steps on each whole bead at once.

    ``p`` is (B·F, 5), bead-major; ``beads`` the beads to fit (default all). Returns the
    parameters, per-bead convergence and per-bead iterations.
    """
    F = layout.F
    B = len(p) // F
    beads = np.arange(B) if beads is None else np.flatnonzero(beads)
    rows_of = np.arange(B * F).reshape(B, F)
    template = p.copy()

    def evaluate(local, x):
        rows = rows_of[beads[local]].ravel()
        ll, grad, H = _evaluate_rows(objective, layout.unpack(x, template[rows]), rows)
        return (ll.reshape(-1, F).sum(axis=1), layout.gradient(grad), H.reshape(-1, F, _NP, _NP))

    opt = maximize(
        evaluate,
        layout.pack(p[rows_of[beads].ravel()]),
        lower=layout.lower,
        upper=layout.upper,
        tol=tol,
        max_iter=max_iter,
        max_step=np.inf,
        accept_rtol=1e-10,
        stuck_tol=_STUCK_DECREMENT,
        step=layout.step,
    )
    rows = rows_of[beads].ravel()
    p = p.copy()
    p[rows] = layout.unpack(opt.x, template[rows])
    converged, iterations = np.zeros(B, bool), np.zeros(B, int)
    converged[beads], iterations[beads] = opt.done, opt.iterations
    return p, converged, iterations
