"""Per-frame scores and the Fisher information of the likelihood engine's model.

The hierarchical layout's sandwich covariance sums the scores at every histogram value
(:func:`value_scores`); the planner needs the information of one frame before there are
data (:func:`expected_information`, through
:meth:`emccdcal.fit.series.SeriesLikelihood.expected_information`). Both come from the
same windows the fit evaluates (:class:`emccdcal.fit.engine._ModelAtData`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .. import _xp
from .._util import weighted_gram
from ..model import noise
from .engine import _model_jacobian, _ModelAtData, _native_to_model, _register

__all__ = ["expected_information", "value_scores"]


def value_scores(layout, blocks, x):
    """Per-frame scores of each acquisition by ``x``, at every histogram value.

    Returns
    -------
    list of (scores (P, K, F), counts (P, K))
        One pair per acquisition: the derivative of ln p(value) by ``x`` (zero where the
        value is below the resolvable floor) and the frames at each value.
    """
    logs, jac = layout.native(x)
    out = []
    for a, acq in enumerate(blocks):
        coords, D = _native_to_model(logs[:, a], acq)
        values = [np.exp(c) for c in coords]
        rows = _register(acq).rows_at(values, acq.poisson_normal)
        names = rows.names
        model = _ModelAtData(acq, rows, derivs=True, names=names)
        d1, pv = model.scores, model.pv
        u = np.stack([d1[nm] * v[:, None] for nm, v in zip(names, values)], -1)
        u = np.where(model.low[..., None], 0.0, u / pv[..., None])  # (P, K, U) by coords
        j_u = _model_jacobian(jac, a, D)
        out.append((u @ j_u, acq.counts))
    return out


def expected_information(layout, blocks, x):
    """The Fisher information of one frame of each acquisition at ``x``, and its cross
    information with the offset and read-noise maps: what :func:`fit` reports at data
    that follow the model exactly.

    Each is the expectation under the model of the outer product of the per-frame scores,
    Σ_k p(k) s(k) s(k)ᵀ over every count k the model reaches (the window of the fit),
    from the same scores the fit uses; N frames carry N times as much. The blocks give
    the maps and the register; their histograms are not used.

    Returns
    -------
    info : ndarray, shape (P, A, F, F)
        Per frame, of the free parameters ``x``.
    cross : ndarray, shape (P, A, F, 2)
        Per frame, of ``x`` with (offset, read noise) in ADU: with ``N`` frames, the
        estimate moves by ``cov · N · cross`` per ADU of map error.
    """
    logs, jac = layout.native(x)
    P, F = x.shape
    info = np.zeros((P, len(blocks), F, F))
    cross = np.zeros((P, len(blocks), F, 2))
    for a, acq in enumerate(blocks):
        coords, D = _native_to_model(logs[:, a], acq)
        values = [np.exp(c) for c in coords]
        rows = _register(acq).rows_at(values, acq.poisson_normal)
        lo, hi = noise.window_extent(rows, acq.offset, acq.read_noise, width=8.0)
        start = np.floor(lo).astype(np.int64)
        support = start[:, None] + np.arange(int((np.ceil(hi) - start).max()) + 1)
        names = rows.names + ("offset", "read_noise")
        # The windows where the fit computes (_xp.computing_on); the sums here, on the host.
        model = _ModelAtData(
            replace(acq, values=support), rows, derivs=True, names=names, xp=_xp.engine()
        )
        pv, low = _xp.to_numpy(model.pv), _xp.to_numpy(model.low)
        scores = {nm: _xp.to_numpy(v) for nm, v in model.scores.items()}
        p = np.where(low, 0.0, pv)
        scale = np.where(low, 0.0, 1.0 / pv)
        u = np.stack([scores[nm] * v[:, None] for nm, v in zip(rows.names, values)], -1)
        s = (u * scale[..., None]) @ _model_jacobian(jac, a, D)
        m = np.stack([scores["offset"], scores["read_noise"]], -1) * scale[..., None]
        info[:, a] = weighted_gram(p, s)
        cross[:, a] = weighted_gram(p, s, m)
    return info, cross
