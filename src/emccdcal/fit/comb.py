"""φ where a photoelectron comb shows: a start in the likelihood's highest basin, and an
error as wide as the likelihood says.

Without multiplication a pixel's counts are a comb: peaks 1/φ ADU apart (one per
photoelectron), each as wide as the read noise. Where the read noise in electrons, σφ,
is small enough for the comb to show (an ORCA-Quest's 0.27 e⁻; an sCMOS's quieter
pixels), the likelihood over φ is not one hill:

- moving φ by a fraction 1/k moves the k-th peak onto the (k±1)-th, so near the
  fractions of the brightest level's photoelectrons it has local maxima; and counts
  rounded to integers cannot tell a comb of frequency φ from one of 1 − φ (an sCMOS's
  φ ≈ 0.46 e⁻/ADU has an alias at 0.54) except through the envelope. A start from the
  moments (a few per cent off with a few thousand frames) can sit in any basin, and
  Newton's method converges where it starts;
- where the comb barely shows (0.35–0.8 e⁻ on an sCMOS), those maxima are ripples a
  few hundredths to a few nats deep on a broad envelope: the maximum sits on one of
  them, and the observed information there is the ripple's curvature, up to 40 times
  what the data hold.

:func:`profile_start` finds the start in three steps (its docstring): the dimmest
level's best basins on a grid over φ (its ripples are the widest apart; the φ / 1 − φ
alias, which it cannot tell apart, stays among its candidates), the brighter levels
added one at a time from each, and every level on a grid at the ripples' spacing around
the best of them, each level's E following φ through its mean (``E = φ·(⟨S⟩ − S0)``:
along it the likelihood is the profile likelihood, checked against refits to 0.01 nats).
Where another ripple on that grid rivals the fit's (within :data:`RIVAL` nats), the
fit's own ripple does not decide φ and its curvature is not the error: the SE is that of
the parabola through the ripples' tops, the smooth likelihood they sit on
(:func:`ripple_covariance`), or the estimate's own errors' where that is larger (the
highest top among rivals is partly the data's noise: a parametric bootstrap,
:func:`bootstrap_errors`, :func:`wald_se`); where that likelihood is one hill the
ripples do not decide the estimate either, and the fit starts at the hill's top. Where
the rivals are a resolved comb's few basins, too few for an envelope, the SE reaches
every basin within the profile likelihood's 95 % set (:func:`_rival_reach`). Where a
level is so bright that no grid resolves its ripples (1/E apart: thousands of e⁻), they
are a tiny fraction of a nat deep yet their curvature is huge, and a fit ends on
whichever it meets: there the envelope itself is fitted (:func:`_envelope_fit`), its
vertex the start and its curvature the SE's floor. Where the comb is resolved (one
ripple stands alone) or absent, nothing changes. Where the ripples set the error,
profile-likelihood bounds are its Wald bounds (:func:`ripple_bounds`): the χ²₁ quantile
ends within one ripple.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..model import adc
from . import engine
from .engine import Layout

#: A comb whose revival at ω = 2πφ (relative to the transform at 0: exp(−2π²(σφ)²)
#: times the rounding's |sinc(πφ)|) is r ripples a level's log-likelihood by about
#: 2r·√n nats, 1/E apart in ln φ: a curvature up to 2r·√n·(2πE)², which a bright level
#: makes large from ripples a millionth of a nat deep. Where that can reach this share
#: of the moments' information of ln φ, the ripples are looked at (an EMCCD's 1× comb,
#: r ≈ 0, never is).
RIPPLES = 0.01
#: Grid points per ripple (1/E of a level's photoelectrons, relative), and at most.
PER_RIPPLE = 4
MAX_POINTS = 1025
#: Grid points over the envelope where a level is so bright that a grid of
#: :data:`MAX_POINTS` cannot resolve its ripples (they are then a fraction of a nat
#: deep, their curvature no error): the envelope's parabola needs no more.
ENVELOPE_POINTS = 33
#: Basins of the dimmest level followed through the brighter ones.
CANDIDATES = 3
#: The profile likelihood is checked where the observed information of ln φ claims at
#: most this fraction of the moments' SE (the comb's share of the information).
CHECK_BELOW = 0.8


def revival(phi, sigma, rounding):
    """|Φ(2πφ)| of a Poisson–normal count, relative to its value at 0: the comb's
    visibility (φ e⁻/ADU, σ ADU)."""
    sinc = np.where(rounding, np.abs(np.sinc(phi)), 1.0)  # np.sinc(x) = sin(πx)/(πx)
    return np.exp(-2.0 * np.pi**2 * (sigma * phi) ** 2) * sinc


def _revival(block, phi):
    return revival(phi, block.read_noise, adc.rounds(block.poisson_normal, block.read_noise))


@dataclass
class CombLayout(Layout):
    """An intensity series' layout (``x = [ln φ, ln E_1 … ln E_A]``) that carries the
    least SE of ln φ the comb's ripples allow (NaN where the observed information is the
    error)."""

    phi_profile_se: np.ndarray = None

    def subset(self, idx):
        return replace(self, constant=self.constant[idx], phi_profile_se=self.phi_profile_se[idx])


def profile_start(layout, blocks, x0, read_out_variance):
    """The layout as a :class:`CombLayout` and the start of each pixel whose comb can
    ripple the likelihood in its highest basin (module docstring); elsewhere ``x0``.

    1. The dimmest level alone (its aliases the widest apart, 1/E) on a grid over φ
       around the moment start: its best :data:`CANDIDATES` local maxima, each climbed
       to its basin's top (below one photoelectron the level's hill is narrower than
       the grid's step).
    2. From each, the brighter levels added one at a time by Newton's method (each φ by
       then far better known than the next level's aliases where the comb is
       resolved); the candidate of the highest likelihood of all levels is fitted, and
       from its alias k − φ (:func:`mirror`) too where that is near: the better kept.
    3. Where its observed information claims more than the moments' (by
       :data:`CHECK_BELOW`), every level on a grid around it at the ripples' spacing:
       where the grid's best ripple is another, the fit from there too (the better
       kept), and where rival ripples compete the envelope's SE, or the estimate's own
       errors' where larger (:func:`bootstrap_errors`, :func:`wald_se`), is the SE's
       floor (:func:`_envelope_se`), the start moved to the envelope's top where it is
       one hill; where rival basins are too few for an envelope (or the grid so coarse
       that tops hide between its points), each is climbed, the best is the start and
       the SE reaches the profile likelihood's 95 % set in the others
       (:func:`_rival_reach`); where no grid of :data:`MAX_POINTS` resolves the
       ripples, the envelope's fit (:func:`_envelope_fit`) gives the start and the
       floor.

    Parameters
    ----------
    layout : emccdcal.fit.engine.Layout
        An intensity series'.
    blocks : list of AcquisitionBlock
    x0 : ndarray, shape (P, F)
        Moment start.
    read_out_variance : callable
        The read-out's variance (ADU²) of a block (:func:`emccdcal.fit.layouts.read_out_variance`).
    """
    P = x0.shape[0]
    phi0 = np.exp(x0[:, 0])
    rel = moment_se(blocks, phi0, read_out_variance)
    live = np.flatnonzero(ripples(blocks, phi0, rel))
    # a block where some pixel's likelihood ripples is fitted by the outer product's
    # steps (Layout.smooth)
    smooth = live.size == 0
    out = CombLayout(**{**vars(layout), "smooth": smooth}, phi_profile_se=np.full(P, np.nan))
    if smooth:
        return out, x0
    part = [b.take(live) for b in blocks]
    sub = replace(layout.subset(live), smooth=False)
    signal = np.stack([np.maximum(b.mean - b.offset, 1e-6) for b in part], axis=1)
    rel = rel[live]
    x = x0[live].copy()
    se, objective = np.full(live.size, np.nan), np.full(live.size, np.nan)
    # Where no grid resolves the brightest level's ripples, a basin chosen among the
    # dimmer levels' would be left for the envelope's top anyway (below): go there.
    coarse = _unresolved(rel, signal.max(axis=1) * phi0[live])
    fine = np.flatnonzero(~coarse)
    if fine.size:
        fitted = _basin_fit(
            sub.subset(fine), [b.take(fine) for b in part], x[fine], signal[fine], rel[fine]
        )
        x[fine], objective[fine] = fitted.x, fitted.objective
        se[fine] = np.sqrt(np.abs(fitted.cov[:, 0, 0]))
    E_max = np.maximum(signal.max(axis=1) * np.exp(x[:, 0]), 1.0)
    # Where no grid resolves the brightest level's ripples (1/E apart), a fit ends on
    # whichever ripple it meets, on the envelope's flank as well as at its top: the
    # envelope itself is fitted there (:func:`_envelope_fit`).
    aliased = coarse | _unresolved(rel, E_max)
    smooth = np.flatnonzero(aliased)
    if smooth.size:
        x[smooth], out.phi_profile_se[live[smooth]] = _envelope_fit(
            sub.subset(smooth), [b.take(smooth) for b in part], x[smooth], signal[smooth],
            4.0 * rel[smooth],
        )  # fmt: skip
    check = np.flatnonzero(~(se >= CHECK_BELOW * rel) & ~aliased)  # NaN SEs checked too
    if check.size:
        E_max = E_max[check]
        ln_phi, v = _path_grid(
            sub.subset(check), [b.take(check) for b in part], x[check], signal[check],
            4.0 * rel[check], 1.0 / (PER_RIPPLE * E_max),
        )  # fmt: skip
        step = step_of(E_max, 4.0 * rel[check])
        top = np.argmax(v, axis=1)
        # The grid's best ripple not the fit's: the fit from there too, the better kept.
        # The estimate is then the likelihood's highest ripple, the one the bootstrap
        # (below) replays: a fit kept on a ripple up to a nat lower scattered more than
        # the bootstrap said.
        jump = np.flatnonzero(np.abs(ln_phi[np.arange(check.size), top] - x[check, 0]) > 1.5 * step)
        if jump.size:
            idx = check[jump]
            start = _on_path(x[idx], ln_phi[jump, top[jump]], signal[idx])
            refit = engine.fit(sub.subset(idx), [b.take(idx) for b in part], start)
            won = refit.objective > objective[idx]
            x[idx[won]], objective[idx[won]] = refit.x[won], refit.objective[won]
        envelope, vertex = _envelope_se(ln_phi, v, x[check, 0], objective[check], step)
        rival = _rivals(ln_phi, v, x[check, 0], objective[check], step)[2]
        # Basins too few for an envelope (a resolved comb's, each narrower than the
        # grid's step, whose tops can hide between its points): every point within reach
        # climbed, the best basin fitted, the SE reaching the near ones.
        coarse = np.sum(np.isfinite(v), axis=1) <= FEW_POINTS
        lone = np.flatnonzero((rival | coarse) & ~np.isfinite(envelope))
        if lone.size:
            idx = check[lone]
            envelope[lone], x[idx], objective[idx] = _rival_reach(
                sub.subset(idx), [b.take(idx) for b in part], x[idx], signal[idx],
                ln_phi[lone], v[lone], objective[idx], step[lone], coarse[lone],
            )  # fmt: skip
        hill = np.flatnonzero(np.isfinite(vertex))  # one hill: the fit starts at its top
        idx = check[hill]
        x[idx] = _on_path(x[idx], vertex[hill], signal[idx])
        # The estimate a ripple's top among rivals: its SE at least its own scatter, also
        # where too few tops make no envelope (a resolved comb's basins a few per cent
        # apart, as high as each other within a nat).
        tops = np.flatnonzero((np.isfinite(envelope) | rival) & ~np.isfinite(vertex))
        if tops.size:
            idx = check[tops]
            errors = bootstrap_errors(
                sub.subset(idx), [b.take(idx) for b in part], x[idx], signal[idx],
                4.0 * rel[idx], 1.0 / (PER_RIPPLE * E_max[tops]),
            )  # fmt: skip
            envelope[tops] = np.fmax(envelope[tops], wald_se(errors))
        out.phi_profile_se[live[check]] = envelope
    start = x0.copy()
    start[live] = x
    return out, start


def _unresolved(rel, E):
    """Pixels whose ripples (1/E apart in ln φ) no grid of :data:`MAX_POINTS` over ±4
    moments' SEs (``rel``) resolves."""
    return 2.0 * (4.0 * rel) / (MAX_POINTS - 1) > 1.0 / np.maximum(E, 1.0)


def _basin_fit(layout, blocks, x0, signal, rel):
    """Steps 1 and 2 of :func:`profile_start`: the dimmest level's best basins, each
    followed through the brighter levels, the best of all levels' likelihood fitted."""
    order = np.argsort(np.median(signal, axis=0), kind="stable")  # dimmest first
    x, value = None, np.full(x0.shape[0], -np.inf)
    for candidate in _dim_level_candidates(layout, blocks, x0, signal, rel, order[0]):
        for a in range(2, len(blocks) + 1):
            use = order[:a]
            cols = np.r_[0, 1 + use]
            fitted = engine.fit(
                _levels(layout, use), [blocks[i] for i in use], candidate[:, cols],
                covariance=False,
            )  # fmt: skip
            candidate[:, cols] = fitted.x
        v = engine.objective(layout, blocks, candidate)
        better = v > value
        x = candidate if x is None else np.where(better[:, None], candidate, x)
        value = np.where(better, v, value)
    # The fit from the best, and from its alias where the moments do not rule that out:
    # only the envelope of every level tells the two apart, and a fit from either ends
    # at the one it starts nearer.
    first = engine.fit(layout, blocks, x, covariance=False)
    x = first.x
    alias = mirror(np.exp(x[:, 0]))
    with np.errstate(invalid="ignore", divide="ignore"):
        near = np.abs(np.log(alias) - x[:, 0]) < MIRROR_WITHIN * rel
    idx = np.flatnonzero(near)
    if idx.size:
        start = _on_path(x[idx], np.log(alias[idx]), signal[idx])
        other = engine.fit(
            layout.subset(idx), [b.take(idx) for b in blocks], start, covariance=False
        )
        won = other.objective > first.objective[idx]
        x[idx[won]] = other.x[won]
    return engine.fit(layout, blocks, x)


#: A fit's alias (:func:`mirror`) is fitted too where it lies within this many of the
#: moments' relative SEs of it: the dim level's grid spans ±5 of them about the moments'
#: start, so a fit that ended at the alias of the truth lies within about ten of it.
MIRROR_WITHIN = 12.0


def mirror(phi):
    """The nearest alias of a comb of φ e⁻/ADU (P,) sampled at the integers: the counts'
    frequency φ and k − φ give the same cos 2πφk for every integer count k (k = the
    nearest integer to 2φ); NaN where there is none (φ < ¼: k = 0)."""
    k = np.rint(2.0 * phi)
    with np.errstate(invalid="ignore"):
        return np.where(k >= 1.0, k - phi, np.nan)


#: Another ripple within this many nats of the best is a rival (Wilks's 99.9 % is 5.4):
#: the fit's own ripple is then not what decides φ, and its curvature not the error.
RIVAL = 10.0
#: Ripples within this many nats of the best shape the envelope's parabola.
ENVELOPE = 30.0
#: A likelihood whose grid a parabola misses nowhere by more than this (half the χ²₁ 95 %
#: quantile) is one hill: no ripple on it can hold a 95 % interval within itself.
ONE_HILL = 1.92
#: The hill's top is the estimate where its ripples lie at most this many of its SEs
#: apart: the nearest ripple's top (where a fit from it ends) then lies within a quarter
#: of an SE of it. Farther apart (a resolved comb, its aliases a few per cent apart on a
#: grid that sees only their envelope) each ripple is a basin of its own.
HILL_RIPPLES = 0.5


def step_of(E_max, half):
    """The grid step (ln φ) :func:`_path_grid` takes for ``E_max`` and ``half``."""
    return np.maximum(1.0 / (PER_RIPPLE * E_max), 2.0 * half / (MAX_POINTS - 1))


def _rivals(ln_phi, value, x_fit, fit_value, step):
    """The grid's tops (P, G), the best value (P,: the fit's or a top's) and whether a
    top away from the fit comes within :data:`RIVAL` nats of it (P,)."""
    P = value.shape[0]
    left = np.concatenate([np.full((P, 1), -np.inf), value[:, :-1]], axis=1)
    right = np.concatenate([value[:, 1:], np.full((P, 1), -np.inf)], axis=1)
    top = (value >= left) & (value >= right) & np.isfinite(value)
    best = np.maximum(fit_value, np.where(top, value, -np.inf).max(axis=1))
    away = np.abs(ln_phi - x_fit[:, None]) > 1.5 * step[:, None]
    return top, best, np.any(top & away & (best[:, None] - value < RIVAL), axis=1)


#: A grid of at most this many points (a comb whose basins lie far apart against the
#: moments' SE) is climbed from every point within reach: its basins' tops can hide
#: between its points.
FEW_POINTS = 33
#: Half the χ²₁ 95 % quantile: the profile likelihood's 95 % set holds the points within
#: this many nats of its best.
PROFILE_95 = 1.92


def _rival_reach(layout, blocks, x, signal, ln_phi, value, fit_value, step, every):
    """Where rival basins are too few to shape an envelope (a resolved comb: two or
    three basins a few per cent apart, each narrower than the grid's step, so that the
    grid's values fall short of their tops or miss a top between two points): each
    rival top, or with ``every`` (P,) each point of the grid within :data:`RIVAL` nats,
    and the fit itself climbed to its basin's top. Returns the SE of ln φ (P,) such that
    ±1.96 SEs reach the far edge of the profile likelihood's 95 % set (within
    :data:`PROFILE_95` nats of the best) in the farthest other basin that holds part of
    it (NaN where none does: the best basin's curvature is then the error), and ``x``
    and its objective (P,) at the best basin.

    A parametric bootstrap at the fit cannot see this: replicates drawn at one basin's
    top rarely prefer the other, however nearly the data tie them."""
    top, _, _ = _rivals(ln_phi, value, x[:, 0], fit_value, step)
    away = np.abs(ln_phi - x[:, :1]) > 1.5 * step[:, None]
    pixel, point = np.nonzero((top | every[:, None]) & away & (fit_value[:, None] - value < RIVAL))
    x, fit_value = x.copy(), fit_value.copy()
    reach = np.zeros(x.shape[0])
    if pixel.size:
        own = np.unique(pixel)
        rows = np.concatenate([own, pixel])
        start = _on_path(x[rows], np.r_[x[own, 0], ln_phi[pixel, point]], signal[rows])
        climbed = engine.fit(layout.subset(rows), [b.take(rows) for b in blocks], start)
        top_value = np.where(np.isfinite(climbed.objective), climbed.objective, -np.inf)
        order = np.lexsort((-top_value, rows))  # each pixel's best basin first
        best = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
        x[rows[best]], fit_value[rows[best]] = climbed.x[best], top_value[best]
        # each other basin's part of the 95 % set reaches as far as its top and beyond
        # it as far as its own curvature keeps the likelihood within the set
        room = PROFILE_95 - (fit_value[rows] - top_value)
        distance = np.abs(climbed.x[:, 0] - x[rows, 0])
        with np.errstate(invalid="ignore"):
            edge = distance + np.sqrt(np.abs(climbed.cov[:, 0, 0]) * 2.0 * np.maximum(room, 0.0))
        inside = (room >= 0) & np.isfinite(edge) & (distance > 0)
        np.maximum.at(reach, rows[inside], edge[inside])
    return np.where(reach > 0, reach / 1.96, np.nan), x, fit_value


def _envelope_se(ln_phi, value, x_fit, fit_value, step):
    """The SE of ln φ (P,) where the fit's ripple does not decide φ, from the curvature
    of the smooth likelihood the ripples sit on, and where that likelihood is one hill,
    its top: ``(se, vertex)``, each (P,). The SE is NaN where the fit's ripple stands
    alone (its observed information is then the error) or the points make no parabola;
    the vertex (ln φ) NaN where the likelihood is not one hill.

    Where a parabola through every point within :data:`ENVELOPE` nats of the best misses
    none by more than :data:`ONE_HILL` nats, the likelihood is one hill and that
    parabola's curvature is the error's floor: there the ripples may be too shallow to
    make tops between the grid's points, or too few, yet curved enough to be most of the
    observed information (a comb that barely shows, 0.5–0.8 e⁻ of read noise on an
    sCMOS). Its vertex is the estimate where the ripples are fine on it
    (:data:`HILL_RIPPLES`): which ripple on the hill is highest is then the data's
    noise, not φ's information, and a fit kept on the highest scatters more than the
    hill's top. Elsewhere, where rival ripples compete (:data:`RIVAL`), a parabola
    through the ripples' tops (within :data:`ENVELOPE` nats) gives the SE."""
    P = value.shape[0]
    top, best, rival = _rivals(ln_phi, value, x_fit, fit_value, step)
    near = np.isfinite(value) & (best[:, None] - value < ENVELOPE)
    out, vertex = np.full(P, np.nan), np.full(P, np.nan)
    for points, needs_fit in ((top & near, rival), (near, None)):  # the hill overrides
        # each row's points and the fit's own (at t = 0)
        t = np.concatenate([np.where(points, ln_phi - x_fit[:, None], 0.0), np.zeros((P, 1))], 1)
        v = np.concatenate([np.where(points, value, 0.0), fit_value[:, None]], axis=1)
        use = np.concatenate([points, np.ones((P, 1), dtype=bool)], axis=1)
        a, b, c = _parabolas(t, v, use)
        ok = (use.sum(axis=1) >= 4) & (a < 0)
        if needs_fit is None:  # one hill: no point farther than ONE_HILL from it
            fitted = a[:, None] * t**2 + b[:, None] * t + c[:, None]
            with np.errstate(invalid="ignore"):
                miss = np.max(np.where(use, np.abs(fitted - v), 0.0), axis=1)
                ok &= miss <= ONE_HILL
            span = np.max(np.where(use, np.abs(t), 0.0), axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                top_at = np.clip(-b / (2.0 * a), -span, span)
                # ripples at most PER_RIPPLE steps apart (the grid's), fine on the hill
                fine = PER_RIPPLE * step <= HILL_RIPPLES / np.sqrt(-2.0 * a)
            on_hill = ok & fine
            vertex[on_hill] = x_fit[on_hill] + top_at[on_hill]
        else:
            ok &= needs_fit
        out[ok] = 1.0 / np.sqrt(-2.0 * a[ok])
    return out, vertex


def _envelope_fit(layout, blocks, x, signal, half, rounds=4):
    """The top of the envelope and its SE of ln φ (P,), where the ripples are too fine
    for any grid: the likelihood of every level along E = φ·signal on
    :data:`ENVELOPE_POINTS` points within ±``half`` of the centre, a parabola through
    those within :data:`ENVELOPE` nats of the best, the centre moved to its vertex (at
    most ``half`` at a time) until it stays; ``x`` with ln φ at the vertex and every E
    along the path, and the SE from the parabola's curvature (NaN where it has none)."""
    x = x.copy()
    se = np.full(x.shape[0], np.nan)
    todo = np.arange(x.shape[0])
    step = 2.0 * half / (ENVELOPE_POINTS - 1)
    for _ in range(rounds):
        ln_phi, value = _path_grid(
            layout.subset(todo), [b.take(todo) for b in blocks], x[todo], signal[todo],
            half[todo], step[todo],
        )  # fmt: skip
        near = np.isfinite(value) & (value > value.max(axis=1, keepdims=True) - ENVELOPE)
        t = np.where(near, ln_phi - x[todo, :1], 0.0)
        a, b, _ = _parabolas(t, np.where(near, value, 0.0), near)
        top = (near.sum(axis=1) >= 4) & (a < 0)
        best = t[np.arange(todo.size), np.argmax(np.where(near, value, -np.inf), axis=1)]
        with np.errstate(divide="ignore", invalid="ignore"):
            vertex = np.where(top, -b / (2.0 * a), best)  # no top within reach: the best point
            se[todo[top]] = 1.0 / np.sqrt(-2.0 * a[top])
        vertex = np.clip(vertex, -half[todo], half[todo])
        x[todo] = _on_path(x[todo], x[todo, 0] + vertex, signal[todo])
        moved = (np.abs(vertex) > 0.25 * half[todo]) | ~top
        todo = todo[moved]
        if todo.size == 0:
            break
    return x, se


def _parabolas(t, v, use):
    """Least-squares parabolas ``v ≈ a·t² + b·t + c`` through each row's points ``use``
    (P, G): (a, b, c), each (P,); NaN where fewer than three distinct points."""
    w = use.astype(float)
    s = [np.sum(w * t**k, axis=1) for k in range(5)]
    r = [np.sum(w * t**k * v, axis=1) for k in range(3)]
    m = np.stack(
        [np.stack([s[4], s[3], s[2]], -1), np.stack([s[3], s[2], s[1]], -1),
         np.stack([s[2], s[1], s[0]], -1)], axis=-2,
    )  # fmt: skip
    ok = (use.sum(axis=1) >= 3) & (np.linalg.det(m) != 0)  # three distinct points
    coef = np.full((t.shape[0], 3), np.nan)
    if ok.any():
        coef[ok] = np.linalg.solve(m[ok], np.stack([r[2], r[1], r[0]], -1)[ok][..., None])[..., 0]
    return coef[:, 0], coef[:, 1], coef[:, 2]


def _on_path(x, ln_phi, signal):
    """``x`` (P, F) with ln φ at ``ln_phi`` (P,) and every level's E where the path takes
    it, ``E = φ·signal`` (``signal`` (P, A): the levels' mean counts above the offset)."""
    out = x.copy()
    out[:, 0] = ln_phi
    out[:, 1:] = np.log(signal * np.exp(ln_phi)[:, None])
    return out


def _path_points(x, signal, half, step):
    """The grid of :func:`_path_grid`: ln φ (P, G), which of its points each pixel has
    (P, G), the points as rows of ``x`` (P·G, F; E along the path) and each row's pixel."""
    step = np.maximum(step, 2.0 * half / (MAX_POINTS - 1))
    points = np.minimum(np.ceil(2.0 * half / step).astype(int) + 1, MAX_POINTS)
    P, G = x.shape[0], int(points.max())
    grid = np.arange(G)[None, :]
    ln_phi = x[:, :1] + (grid - (points[:, None] - 1) / 2.0) * step[:, None]
    inside = np.broadcast_to(grid < points[:, None], ln_phi.shape)
    trial = np.repeat(x, G, axis=0)
    trial[:, 0] = ln_phi.ravel()
    trial[:, 1:] = np.log(signal[:, None, :] * np.exp(ln_phi)[..., None]).reshape(P * G, -1)
    return ln_phi, inside, trial, np.repeat(np.arange(P), G)


def _in_chunks(todo):
    """Rows of a grid evaluated at a time (bounded memory)."""
    return np.array_split(todo, max(1, todo.size // 2048))


def _path_grid(layout, blocks, x, signal, half, step):
    """The likelihood of every level along E = φ·signal (the profile likelihood) on a
    grid of ln φ (P, G) within ±``half`` of ``x``'s at most ``step`` apart, and its values
    (−inf beyond each pixel's grid)."""
    ln_phi, inside, trial, rows = _path_points(x, signal, half, step)
    value = np.full(rows.size, -np.inf)
    for chunk in _in_chunks(np.flatnonzero(inside.ravel())):
        r = rows[chunk]
        value[chunk] = engine.objective(layout.subset(r), [b.take(r) for b in blocks], trial[chunk])
    return ln_phi, np.where(np.isfinite(value), value, -np.inf).reshape(ln_phi.shape)


#: Replicates of :func:`bootstrap_errors` (the SD's own relative SE, 1/√(2(B − 1)): 5 %).
BOOTSTRAP = 200
#: Each level's replicates range over its counts' span widened by this many of their SDs
#: on each side (data of 1000 frames or more reach about 3.2 SDs out: the support then
#: holds all but ~1e-9 of the model's mass).
SUPPORT_SDS = 3.0
#: The two paths beside the fit's that a replicate's ln p is interpolated between lie this
#: many SEs of each level's mean to either side (a replicate's mean is within 4 SEs of
#: the fit's at all but 6e-5 of the draws; beyond, the parabola extrapolates).
PATH_SPREAD = 4.0


def wald_se(errors):
    """The SE (P,) whose ±1.96 holds 95 % of the errors (P, B) or more: the larger of
    their SD and their 95th percentile of abs(error) over 1.96.

    Where rival ripples compete, a pixel's errors are a spike at the true ripple and
    wings out to tens of ripples: their SD is met, but ±1.96 SDs then hold some 91 % of
    them (the wings reach past it), and a Wald interval must hold 95 %."""
    sd = np.std(errors, axis=1, ddof=1)
    return np.fmax(sd, np.quantile(np.abs(errors), 0.95, axis=1) / 1.96)


def bootstrap_errors(layout, blocks, x, signal, half, step):
    """The errors of ln φ's estimate (P, :data:`BOOTSTRAP`) over replicates of each
    pixel's data drawn from its fit (a parametric bootstrap), each estimated as the pixel
    was: the replicate's estimate minus the fit's.

    Where rival ripples compete, the estimate is the highest of their tops: which one is
    highest is the data's noise as much as φ's information, so neither a ripple's
    curvature nor its envelope's is the estimate's scatter. The replicates' counts are
    drawn, level by level, from the model at ``x`` over each level's support (its
    counts' span widened by :data:`SUPPORT_SDS` SDs). A replicate's likelihood is taken
    on the fit's grid of ln φ along its own path, E = φ·(its mean − offset): the ripples
    lie 1/E apart, and its mean's noise, a fraction of a ripple, moves which one is
    highest. The model is evaluated once for all replicates, on the grid along the fit's
    path and along two paths :data:`PATH_SPREAD` SEs of the mean to either side, and a
    replicate's ln p at each count is the parabola through the three at its own mean
    (ln p is smooth in E). Its estimate is its grid's best point (refined by the parabola
    through its neighbours), or the hill's top where :func:`_envelope_se` finds one
    hill. The draws are seeded by the pixel's own data (:func:`_seed_of`): the same
    data give the same errors, in any tile or block.
    """
    # one pixel at a time: the model along three paths is (G, K) per level and path
    return np.stack(
        [
            _pixel_bootstrap(
                layout.subset([p]),
                [b.take([p]) for b in blocks],
                x[p : p + 1],
                signal[p : p + 1],
                half[p : p + 1],
                step[p : p + 1],
            )  # fmt: skip
            for p in range(x.shape[0])
        ]
    )


def _pixel_bootstrap(layout, blocks, x, signal, half, step):
    """:func:`bootstrap_errors` of one pixel (every array's first axis of length 1): (B,)."""
    support = []
    for b in blocks:  # each level's support: its counts' span, widened
        filled = b.values[0][b.counts[0] > 0]
        sd = np.sqrt(max(float(b.var[0]), 1.0))
        lo = int(np.floor(filled.min() - SUPPORT_SDS * sd))
        hi = int(np.ceil(filled.max() + SUPPORT_SDS * sd))
        values = np.arange(lo, hi + 1)[None, :]
        support.append(replace(b, values=values, counts=np.zeros(values.shape, dtype=np.int64)))
    fitted = [lp[0] for lp in engine.logpmf_at_values(layout, support, x)]
    # each level's signal moved by ±h (relative): PATH_SPREAD SEs of its mean
    h = np.array(
        [
            PATH_SPREAD * np.sqrt(b.var[0] / max(b.n[0], 1)) / signal[0, a]
            for a, b in enumerate(blocks)
        ]
    )
    ln_phi, inside, trial, rows = _path_points(x, signal, half, step)
    ln_phi, inside = ln_phi[0], inside[0]
    live = np.flatnonzero(inside)
    paths = []  # per shift (−h, 0, +h): per level, ln p (G live points, K counts)
    for shift in (-1.0, 0.0, 1.0):
        moved = trial[live].copy()
        moved[:, 1:] += np.log1p(shift * h)
        r = rows[live]
        paths.append(engine.logpmf_at_values(layout.subset(r), [s.take(r) for s in support], moved))
    rng = np.random.default_rng(_seed_of(blocks))
    value = np.zeros((BOOTSTRAP, live.size))
    for a, b in enumerate(blocks):
        prob = np.exp(fitted[a])
        draws = rng.multinomial(int(b.n[0]), prob / prob.sum(), size=BOOTSTRAP)
        mean = draws @ support[a].values[0] / b.n[0]
        t = ((mean - b.offset[0]) / signal[0, a] - 1.0) / h[a]
        weights = (0.5 * t * (t - 1.0), 1.0 - t**2, 0.5 * t * (t + 1.0))
        for w, path in zip(weights, paths):
            value += w[:, None] * (draws @ path[a].T)
    grid = np.broadcast_to(ln_phi[live], value.shape)
    best = np.argmax(value, axis=1)
    at = np.arange(BOOTSTRAP)
    left = value[at, np.maximum(best - 1, 0)]
    right = value[at, np.minimum(best + 1, live.size - 1)]
    top = value[at, best]
    curve = left - 2.0 * top + right
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curve < 0, np.clip(0.5 * (left - right) / curve, -0.5, 0.5), 0.0)
    point_step = np.full(BOOTSTRAP, ln_phi[1] - ln_phi[0] if live.size > 1 else 0.0)
    estimate = grid[at, best] + shift * point_step
    _, vertex = _envelope_se(grid, value, estimate, top, point_step)
    return np.where(np.isfinite(vertex), vertex, estimate) - x[0, 0]


def _seed_of(blocks):
    """A seed from one pixel's data (every block's first axis of length 1): its values
    held and their counts, level by level, not the rows' padding (as wide as the widest
    pixel's in the block), so that the same data give the same draws in any block."""
    held = [b.counts[0] > 0 for b in blocks]
    parts = [np.r_[b.counts[0][h], b.values[0][h]] for b, h in zip(blocks, held)]
    return np.concatenate(parts).astype(np.int64) % 2**32  # a seed's words: non-negative


def _levels(layout, use):
    """The intensity layout of the levels ``use`` alone (their columns of E and φ)."""
    cols = np.r_[0, 1 + use]
    return Layout(
        parameters=[layout.parameters[c] for c in cols],
        lower=layout.lower[cols],
        upper=layout.upper[cols],
        matrix=layout.matrix[np.ix_(use, np.arange(layout.matrix.shape[1]), cols)],
        constant=layout.constant[:, use],
        smooth=False,
    )


def _dim_level_candidates(layout, blocks, x0, signal, rel, level):
    """The best :data:`CANDIDATES` local maxima of ``level``'s likelihood alone on a
    grid over ln φ (E = φ·signal), best first: a list of (P, F) starts.

    More than one, because counts rounded to integers cannot tell a comb of frequency φ
    from one of 1 − φ (or m ± φ) apart: only the envelope does, which one dim level
    hardly sees."""
    one = _levels(layout, np.array([level]))
    E = np.maximum(signal[:, level] * np.exp(x0[:, 0]), 1.0)
    half = np.clip(5.0 * rel, 0.02, 0.5)
    ln_phi, value = _path_grid(
        one, [blocks[level]], x0[:, [0, 1 + level]], signal[:, [level]], half,
        1.0 / (PER_RIPPLE * E),
    )  # fmt: skip
    P, G = value.shape
    left = np.concatenate([np.full((P, 1), -np.inf), value[:, :-1]], axis=1)
    right = np.concatenate([value[:, 1:], np.full((P, 1), -np.inf)], axis=1)
    peaks = np.where((value >= left) & (value >= right), value, -np.inf)
    ranked = np.argsort(-peaks, axis=1, kind="stable")[:, :CANDIDATES]
    cols = np.r_[0, 1 + level]
    out = []
    for c in range(ranked.shape[1]):
        pick = np.where(np.isfinite(peaks[np.arange(P), ranked[:, c]]), ranked[:, c], ranked[:, 0])
        start = _on_path(x0, ln_phi[np.arange(P), pick], signal)
        # The grid's point climbed to its basin's top: below one photoelectron a level's
        # hill in ln φ can be a few per cent wide, the grid's step a quarter, and its top
        # far from every point: farther than the next level's basins are wide.
        climbed = engine.fit(one, [blocks[level]], start[:, cols], covariance=False).x
        kept = np.all(np.isfinite(climbed), axis=1)  # else the grid's point
        start[np.ix_(kept, cols)] = climbed[kept]
        out.append(start)
    return out


def ripples(blocks, phi, rel):
    """Pixels (P,) where the levels' combs can ripple the likelihood at φ (e⁻/ADU) into
    curvature of ln φ beyond :data:`RIPPLES` of the moments' information (``rel``: the
    moments' relative SE of φ)."""
    curvature = np.zeros(phi.shape)
    for b in blocks:
        E = phi * np.maximum(b.mean - b.offset, 0.0)
        bound = 2.0 * _revival(b, phi) * np.sqrt(np.maximum(b.n, 1)) * (2.0 * np.pi * E) ** 2
        curvature += np.where(b.poisson_normal, bound, 0.0)
    return curvature > RIPPLES / rel**2


def moment_se(blocks, phi, read_out_variance):
    """The relative SE of φ (P,) from the moments alone: the photon transfer through the
    origin, whose excess variances each have the variance 2·Var²/(n − 1)."""
    excess = np.stack([np.maximum(b.var - read_out_variance(b), 1e-6) for b in blocks], 1)
    n = np.stack([np.maximum(b.n, 2) for b in blocks], 1)
    var = np.stack([b.var for b in blocks], 1)
    return np.sqrt(np.sum(2.0 * var**2 / (n - 1), axis=1)) / excess.sum(axis=1)


def _widened(layout, cov):
    """Pixels (P,) whose SE of ln φ the ripples' envelope or the estimate's bootstrap
    sets (:class:`CombLayout`): larger than the observed information's, ``cov`` (P, F, F)."""
    profile_se = getattr(layout, "phi_profile_se", None)
    if profile_se is None:
        return np.zeros(cov.shape[0], dtype=bool)
    with np.errstate(invalid="ignore"):
        return np.isfinite(profile_se) & (profile_se**2 > cov[:, 0, 0])


def ripple_covariance(layout, cov):
    """The covariance of an intensity series' ``x`` (P, F, F) with ln φ's variance at
    least the ripples' envelope's (:class:`CombLayout`), grown along
    the direction in which the other parameters move with φ (each E with it), as a
    given φ's error would; unchanged where the observed information says more."""
    idx = np.flatnonzero(_widened(layout, cov))
    if idx.size == 0:
        return cov
    grow = layout.phi_profile_se[idx] ** 2 - cov[idx, 0, 0]
    b = cov[idx, :, 0] / cov[idx, 0, 0][:, None]  # how x moves with ln φ
    out = cov.copy()
    out[idx] += grow[:, None, None] * b[:, :, None] * b[:, None, :]
    return out


def ripple_bounds(layout, cov, estimates, bounds, level=0.95):
    """Profile-likelihood ``bounds`` (``<name>_lower``/``_upper``, each (P, A)) with,
    where the ripples widened φ's error (``cov``: the fit's own, (P, F, F)), the Wald
    bounds on the log scale of the widened ``estimates`` (``<name>`` and ``<name>_se``)
    instead.

    There the likelihood over φ is a comb of rival ripples: the χ²₁ quantile of its
    deviance ends within the estimate's own ripple (an interval of a few hundredths of
    its SE, covering some 58 % of the truths at 0.35–0.5 e⁻ of read noise on an sCMOS),
    and the deviance does not follow χ²₁ over the rivals either."""
    idx = np.flatnonzero(_widened(layout, cov))
    if idx.size == 0:
        return bounds
    from scipy import special

    z = special.ndtri(0.5 + level / 2)
    out = dict(bounds)
    for name in {key.rsplit("_", 1)[0] for key in bounds}:
        value, se = estimates[name][idx], estimates[f"{name}_se"][idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            spread = np.exp(z * se / value)
        lower, upper = out[f"{name}_lower"].copy(), out[f"{name}_upper"].copy()
        free = se > 0  # a quantity the layout fixes has no bounds
        lower[idx] = np.where(free, value / spread, lower[idx])
        upper[idx] = np.where(free, value * spread, upper[idx])
        out[f"{name}_lower"], out[f"{name}_upper"] = lower, upper
    return out
