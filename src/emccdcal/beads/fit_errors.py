"""The standard errors of a bead fit: the joint (arrowhead) information's inverse, the
shared parameters' error on each mean intensity, the width's effect, and the residual
against the mean over frame halves (:func:`frame_halves`)."""

from __future__ import annotations


import numpy as np

from ..errors import OptionError
from ..model import psf

#: How a residual image's frames and those that score it are told apart (:func:`frame_halves`).
RESIDUAL_SPLITS = ("alternate", "time")

_NP = len(psf.PARAMETERS)
#: Lower bound of a frame's intensity N (e⁻): a frame held there had no light to fit.
_MIN_INTENSITY = 1e-3


def _joint_errors(arrow, shared, frame):
    """Standard errors (B, F, 5) from each bead's joint information, reduced to its
    ``arrow`` (:func:`emccdcal._optimize.schur` of the (B, F, 5, 5) information), with
    what the error of the shared parameters does to each frame's intensity.

    A frame's own parameters: conditional on the shared ones (what scatters from frame to
    frame); the shared ones' error is common to the bead's frames. A frame at a bound
    keeps the error its curvature gives: the information is there, only the estimate is
    clipped. NaN where the information is not positive.

    Returns
    -------
    se : (B, F, 5)
    sensitivity : (B, F, k)
        ∂N̂_f/∂(shared) = −(H_ff⁻¹ H_fs)[intensity]: how a frame's intensity moves with
        the shared parameters' estimates (the joint covariance of two frames' N̂ is
        δ_ff' var_f + d_f S⁻¹ d_f'ᵀ).
    shared_cov : (B, k, k)
        S⁻¹, the shared parameters' covariance with every frame's own estimated.
    """
    S, Hff_inv, Hsf = arrow
    B, F = Hff_inv.shape[:2]
    se = np.full((B, F, _NP), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        var_f = np.einsum("bfii->bfi", Hff_inv)
        se[..., frame] = np.sqrt(np.where(var_f > 0, var_f, np.nan))
        try:
            shared_cov = np.linalg.inv(S)
        except np.linalg.LinAlgError:  # one singular bead: each alone
            shared_cov = np.stack([_inverse_or_nan(m) for m in S])
        var_s = np.einsum("bii->bi", shared_cov)
        se[..., shared] = np.sqrt(np.where(var_s > 0, var_s, np.nan))[:, None, :]
        intensity = frame.index(3)
        sensitivity = -np.einsum("bfj,bfkj->bfk", Hff_inv[:, :, intensity, :], Hsf)
    return se, sensitivity, shared_cov


def _inverse_or_nan(m):
    try:
        return np.linalg.inv(m)
    except np.linalg.LinAlgError:
        return np.full(m.shape, np.nan)


def _shared_error_of_mean(sensitivity, shared_cov, converged, width_var=0.0):
    """Each bead's SE of its mean intensity over its converged frames from its shared
    parameters' error: √(d̄ S⁻¹ d̄ᵀ + width_var), d̄ the frames' mean sensitivity (e⁻);
    ``width_var`` that of a held width's error (:func:`_width_effect`), e⁻²."""
    with np.errstate(invalid="ignore", divide="ignore"):
        n = converged.sum(axis=1)
        mean_d = np.einsum("bfk,bf->bk", np.nan_to_num(sensitivity), converged) / n[:, None]
        var = np.einsum("bk,bkl,bl->b", mean_d, shared_cov, mean_d) + width_var
    return np.where((n > 0) & (var >= 0), np.sqrt(np.maximum(var, 0.0)), np.nan)


def _width_effect(Hb, arrow, shared_cov, shared, frame, converged, width=2):
    """How a bead's mean intensity over its converged frames moves with a held width:
    d mean(N̂)/dw (e⁻ per pixel of width), from the joint information ``Hb`` (B, F, 5, 5)
    of all five parameters. The fitted ones follow w by dθ̂/dw = −H_θθ⁻¹ H_θw, solved on
    the ``arrow`` (:func:`emccdcal._optimize.schur`; the shared parameters by
    ``shared_cov`` = S⁻¹ first, then each frame's own)."""
    _, Hff_inv, Hsf = arrow
    with np.errstate(invalid="ignore", divide="ignore"):
        r_s = -Hb[..., shared, width].sum(axis=1)  # (B, k)
        r_f = -Hb[..., frame, width]  # (B, F, f)
        x_s = np.einsum(
            "bkl,bl->bk", shared_cov, r_s - np.einsum("bfkj,bfj->bk", Hsf @ Hff_inv, r_f)
        )
        x_f = np.einsum("bfij,bfj->bfi", Hff_inv, r_f - np.einsum("bfkj,bk->bfj", Hsf, x_s))
        d = x_f[..., frame.index(3)]  # dN̂_f/dw
        n = converged.sum(axis=1)
        return np.where(
            n > 0, np.sum(np.where(converged, d, 0.0), axis=1) / np.maximum(n, 1), np.nan
        )


def _mean_residual(box, p, E_all, info_all, converged, split, offset_var):
    """What the model misses: the mean of data − model over a bead's converged frames
    (but for frames whose intensity is held at its bound, a bead that was off: their
    residual is not centred on zero) and its variance, (B, npix) each; the same for
    each half of the frames (:func:`frame_halves`), (2, B, npix) each; and the mean
    information per pixel over the frames used. The variances are the frames' scatter
    over their number plus ``offset_var``, the offset map's own error (e⁻², (B, npix)):
    the same in every frame, it is in the mean residual whatever the frames."""
    B, F, npix = box.B, box.F, box.npix
    use = _residual_frames(converged, p[:, 3].reshape(B, F))[..., None] & (box.weight > 0)
    resid = (box.y_m - E_all).reshape(B, F, npix)

    def mean_var(sel):
        count = sel.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(sel, resid, 0.0)
            mean = r.sum(axis=1) / count
            var = (
                np.where(sel, (r - mean[:, None]) ** 2, 0.0).sum(axis=1) / (count - 1) / count
            ) + offset_var
        return np.where(count > 1, mean, np.nan), np.where(count > 1, var, np.nan)

    r_mean, r_var = mean_var(use)
    halves = [mean_var(use & (frame_halves(F, split) == k)[None, :, None]) for k in (0, 1)]
    with np.errstate(invalid="ignore", divide="ignore"):
        W = np.where(use, info_all.reshape(B, F, npix), 0.0).sum(axis=1) / use.sum(axis=1)
    return r_mean, r_var, np.stack([m for m, _ in halves]), np.stack([v for _, v in halves]), W


def frame_halves(n_frames, split="alternate"):
    """Which half (0 or 1) each frame of an acquisition belongs to, shape (n_frames,).

    ``"alternate"``: even and odd frames (both halves see the same bleaching and drift);
    ``"time"``: the first and the second half of the acquisition (the second also tests
    that the spot did not change its shape over time).
    """
    if split not in RESIDUAL_SPLITS:
        raise OptionError(f"split must be one of {', '.join(RESIDUAL_SPLITS)}, got {split!r}")
    idx = np.arange(n_frames)
    return idx % 2 if split == "alternate" else (idx >= (n_frames + 1) // 2).astype(int)


def _offset_error(box, pb, converged, fitted, W, s0_se):
    """Standard error of each bead's mean intensity from the offset map's error (e⁻).

    That error is the same in every frame. Its effect on the bead's mean intensity,
    linearised on the bead's mean frame: δN̄ = a·δy, with a the intensity row of
    (JᵀWJ)⁻¹JᵀW over the fitted parameters.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        p_mean = pb[:, 0].copy()
        p_mean[:, 3:] = np.nanmean(np.where(converged[..., None], pb[..., 3:], np.nan), axis=1)
        J = box.model(p_mean, np.arange(box.B))[1][..., fitted]  # (B, npix, k)
        JW = np.swapaxes(J, 1, 2) * W[:, None, :]
        A = np.nan_to_num(JW @ J) + 1e-12 * np.eye(len(fitted))
        coef = np.linalg.solve(A, np.nan_to_num(JW))[:, fitted.index(3)]
        return np.sqrt(np.sum((coef * s0_se / box.theta) ** 2, axis=1))


def _residual_frames(converged, intensity):
    """The frames a bead's mean residual is taken over: converged, and with the intensity
    off its bound (a frame held at N = 0 is not at a stationary point), shape (B, F)."""
    return converged & (intensity > 2 * _MIN_INTENSITY)
