"""The engine's per-acquisition terms against independent evaluations.

The log-likelihood against ``noise.logpmf`` (which picks its own, wider windows), the
gradient and the observed information against finite differences, the map cross terms
against finite differences of the pmf by offset and read noise, and the Parseval sum of
a window against weights against the window itself.
"""

from __future__ import annotations

import numpy as np
import pytest

from emccdcal import _optimize
from emccdcal.data import stats
from emccdcal.fit import engine
from emccdcal.model import noise
from emccdcal.simulate.camera import simulate_frames

# (photoelectrons, em_gain, e_per_adu, offset, read_noise): 1×, a low and a high gain,
# and few electrons at high gain (exponential right tail).
CASES = {
    "1x": (370.0, 1.0, 3.859, 587.0, 15.5),
    "5x": (370.0, 4.78, 3.859, 587.0, 15.5),
    "300x": (370.0, 261.6, 3.859, 587.0, 15.5),
    "few-electrons": (3.0, 300.0, 12.0, 1000.0, 40.0),
}


def _block(case, frames=3000, pixels=3, seed=7):
    E, g, phi, S0, sigma = CASES[case]
    data = simulate_frames(E, g, phi, S0, sigma, frames=frames, rows=1, cols=pixels, seed=seed)
    h = stats.histograms(data)
    P = h.n.size
    return engine.AcquisitionBlock(
        values=h.values,
        counts=h.counts,
        offset=np.full(P, S0),
        read_noise=np.full(P, sigma),
        poisson_normal=g == 1.0,
        mean=h.mean,
        var=h.var,
        n=h.n,
        offset_var=np.full(P, 1.0),
        read_noise_var=np.full(P, 0.5),
        em_model=noise.EMModel("gamma"),
    )


def _log_params(case, P, shift=(0.01, -0.02)):
    """(ln E, ln scale) near the truth, off the optimum so the gradient is not ~0."""
    E, g, phi, _, _ = CASES[case]
    scale = 1.0 / phi if g == 1.0 else g / phi
    return np.full(P, np.log(E) + shift[0]), np.full(P, np.log(scale) + shift[1])


@pytest.mark.parametrize("case", list(CASES))
def test_loglik_is_that_of_the_public_noise_model(case):
    acq = _block(case)
    log_e, log_scale = _log_params(case, acq.n.size)
    loglik = engine._acquisition_terms(acq, [log_e, log_scale], 0)[0]
    E, g, phi, S0, sigma = CASES[case]
    ref_g = 1.0 if g == 1.0 else np.exp(log_scale[0]) * phi
    ref_phi = 1.0 / np.exp(log_scale[0]) if g == 1.0 else phi
    ref = [
        np.sum(
            acq.counts[p]
            * noise.logpmf(
                acq.values[p], np.exp(log_e[p]), ref_g, ref_phi, S0, sigma, em_model="gamma"
            )
        )
        for p in range(acq.n.size)
    ]
    np.testing.assert_allclose(loglik, ref, rtol=1e-11)


@pytest.mark.parametrize("case", list(CASES))
def test_gradient_and_observed_information_are_the_derivatives(case):
    acq = _block(case)
    log_e, log_scale = _log_params(case, acq.n.size)
    _, grad, obs, *_ = engine._acquisition_terms(acq, [log_e, log_scale], 2)
    h = 1e-4

    def terms(de, ds):
        return engine._acquisition_terms(acq, [log_e + de, log_scale + ds], 1)

    steps = [(h, 0.0), (0.0, h)]
    for i, (de, ds) in enumerate(steps):
        ll_plus, ll_minus = (
            engine._acquisition_terms(acq, [log_e + s * de, log_scale + s * ds], 0)[0]
            for s in (1, -1)
        )
        np.testing.assert_allclose(grad[:, i], (ll_plus - ll_minus) / (2 * h), rtol=1e-5, atol=1e-4)
        g_plus, g_minus = terms(de, ds)[1], terms(-de, -ds)[1]
        hess_col = (g_plus - g_minus) / (2 * h)  # d grad / d u_i
        scale = np.abs(obs).max()
        np.testing.assert_allclose(-obs[:, :, i], hess_col, rtol=1e-4, atol=1e-6 * scale)


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("em_model", ["gamma", "cascade"])
def test_the_gradient_by_parseval_is_the_scores_sum(case, em_model):
    """A trial with the information kept gets its gradient from one forward FFT of the
    weights (Parseval): the same numbers as the sum of the scores' windows at the data,
    and no information."""
    acq = _block(case)
    acq = engine.AcquisitionBlock(**{**acq.__dict__, "em_model": noise.EMModel(em_model)})
    coords = engine._native_to_model(
        np.column_stack([np.log(np.full(acq.n.size, c)) for c in _native(case)]), acq
    )[0]
    windows = engine._acquisition_terms(acq, coords, 1)
    parseval = engine._acquisition_terms(acq, coords, 1, information=False)
    assert parseval.info is None and windows.info is not None
    np.testing.assert_array_equal(parseval.loglik, windows.loglik)
    scale = np.abs(windows.grad).max()
    np.testing.assert_allclose(parseval.grad, windows.grad, rtol=1e-9, atol=1e-11 * scale)


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("em_model", ["gamma", "cascade"])
def test_the_steps_information_in_single_precision_is_the_exact_one_to_1e_5(case, em_model):
    """The information that only steers the optimiser's steps comes from score windows
    in single precision: within 1e-5 of the exact one (a step's direction and length to
    as much), the objective and the gradient exactly the same."""
    acq = _block(case)
    acq = engine.AcquisitionBlock(**{**acq.__dict__, "em_model": noise.EMModel(em_model)})
    coords = engine._native_to_model(
        np.column_stack([np.log(np.full(acq.n.size, c)) for c in _native(case)]), acq
    )[0]
    for level in (1, 2):
        exact = engine._acquisition_terms(acq, coords, level)
        steps = engine._acquisition_terms(acq, coords, level, steps_only=True)
        np.testing.assert_array_equal(steps.loglik, exact.loglik)
        scale = np.abs(exact.grad).max()
        np.testing.assert_allclose(steps.grad, exact.grad, rtol=1e-9, atol=1e-11 * scale)
        for info_steps, info_exact in zip(steps.info, exact.info):
            live = np.abs(np.diag(info_exact)) > 0
            block = info_exact[np.ix_(live, live)]
            error = np.abs(info_steps[np.ix_(live, live)] - block)
            assert 0 < error.max() <= 1e-5 * np.abs(block).max()  # single, not double
            assert np.abs(info_steps[~live]).max(initial=0) == 0


def test_a_pixel_the_single_precision_information_steers_badly_is_fitted_with_the_exact(
    tmp_path, monkeypatch
):
    """One frame of each pixel's 1× stack lifted 6–8.5 read-noise SDs above its median
    (a cosmic ray's hit, short of the floor that sets outliers aside): single-precision
    windows leave the derivatives noise that far out, and the steps' information came
    out hundreds of times too large: such pixels stopped short of the optimum (7e-6
    relative at 7.5 SDs, "converged") or did not converge (two at 8–8.2 SDs; one pixel
    of a 512 x 512 sensor). They are fitted again with the exact information: every
    pixel converges, and up to 7.5 SDs, where the likelihood itself is still smooth
    (beyond, its values at the lifted frame near double precision's floor), to the
    numbers of a fit steered by the exact information alone, within 1e-6; so do the
    profile-likelihood bounds, whose pinned refits take exact steps (steered by the
    single-precision information, one crawled 1.2 SEs off)."""
    import tifffile

    import emccdcal
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(tmp_path, rows=4, cols=4, frames=5000, seed=3, progress=False)
    stack = tmp_path / "gain-GS" / "1x-gain.tif"
    sigma = tifffile.imread(tmp_path / "gain-GS" / "1x-gain_no-signal_sigma.tif")
    frames = tifffile.imread(stack)
    lift = np.linspace(6.0, 8.5, 16).reshape(4, 4)
    frames[0] = np.median(frames, axis=0) + np.round(lift * sigma)
    tifffile.imwrite(stack, frames)

    redone = []
    fit = engine.fit

    def counted(*args, **kwargs):
        if kwargs.get("rough_steps") is False:
            redone.append(len(args[2]))
        return fit(*args, **kwargs)

    monkeypatch.setattr(engine, "fit", counted)
    ds = emccdcal.calibrate(sim.manifest, progress=False, intervals="profile")
    assert redone, "no pixel needed the exact steps: the test no longer tests them"
    assert ds["converged"].all()

    evaluate = engine._evaluate
    monkeypatch.setattr(engine, "_evaluate", lambda *a, steps_only=False, **k: evaluate(*a, **k))
    exact = emccdcal.calibrate(sim.manifest, progress=False, intervals="profile")
    smooth = lift <= 7.5
    for name in ("em_gain", "em_gain_se", "em_gain_lower", "em_gain_upper", "photoelectrons"):
        np.testing.assert_allclose(
            ds[name].values[..., smooth], exact[name].values[..., smooth], rtol=1e-6, err_msg=name
        )


def _native(case, shift=(0.01, -0.02, 0.0)):
    """(E, g, φ) of a case, E and g off the optimum so the gradient is not ~0."""
    E, g, phi, _, _ = CASES[case]
    return E * np.exp(shift[0]), g if g == 1.0 else g * np.exp(shift[1]), phi


@pytest.mark.parametrize("case", ["1x", "300x"])
def test_map_cross_terms_are_outer_products_of_the_scores(case):
    """cross[i, m] = Σ_k n_k (∂p/∂u_i)(∂p/∂m)/p², the ∂p/∂m by finite differences of p."""
    acq = _block(case)
    log_e, log_scale = _log_params(case, acq.n.size)
    cross = engine._acquisition_terms(acq, [log_e, log_scale], 2, map_cross=True)[4]
    E, scale = np.exp(log_e), np.exp(log_scale)
    rows = engine._register(acq).rows_at((E, scale), acq.poisson_normal)
    model = engine._ModelAtData(acq, rows, derivs=True)
    w = np.where(model.low, 0.0, acq.counts / model.pv**2)
    factor = np.stack([E, scale], axis=1)
    for m, field in enumerate(("offset", "read_noise")):
        h = 1e-3
        pv = []
        for sign in (1, -1):
            shifted = engine.AcquisitionBlock(
                **{**acq.__dict__, field: getattr(acq, field) + sign * h}
            )
            pv.append(engine._ModelAtData(shifted, rows).pv)
        dp = (pv[0] - pv[1]) / (2 * h)
        for i, name in enumerate(("photoelectrons", "scale")):
            ref = np.sum(w * model.scores[name] * dp, axis=1) * factor[:, i]
            np.testing.assert_allclose(
                cross[:, i, m], ref, rtol=1e-5, atol=1e-8 * np.abs(ref).max()
            )


@pytest.mark.parametrize("n,m", [(64, 20), (64, 33), (63, 32), (100, 7)])
def test_spectrum_dot_is_the_window_summed_against_weights(n, m):
    rng = np.random.default_rng(n + m)
    spectrum = rng.normal(size=(3, m)) + 1j * rng.normal(size=(3, m))
    weights = rng.normal(size=(3, n))
    weights[:, ::5] = 0.0  # a histogram's padding, at a position repeated below
    spec = noise.Spectrum(spectrum, n)
    direct = np.sum(weights * spec.window(), axis=1)
    index = np.arange(3 * n)
    index = np.concatenate([index, index[::5]])  # zero weights where values repeat
    flat = np.concatenate([weights.ravel(), np.zeros(index.size - 3 * n)])
    for _ in range(2):  # the second time on the grid the first one left behind
        hat = noise.Spectrum.weights_spectrum(index, flat, (3, n), m)
        np.testing.assert_allclose(spec.dot(hat), direct, rtol=1e-12, atol=1e-12)


def test_the_kept_fft_grids_leave_no_trace_from_call_to_call():
    """The inverse FFT writes each spectrum into a zero grid kept per thread: calls of
    any band, length and rows, one after another and on threads at once, give NumPy's
    transform of the zero-padded conjugate, as a fresh grid would."""
    from concurrent.futures import ThreadPoolExecutor

    from emccdcal import _xp

    rng = np.random.default_rng(5)
    calls = [(rows, n, m) for rows, n, m in rng.integers([1, 8, 2], [9, 400, 40], (40, 3))]

    def one(call):
        rows, n, m = (int(v) for v in call)
        m = min(m, n // 2 + 1)
        a = rng.normal(size=(rows, m)) + 1j * rng.normal(size=(rows, m))
        got = _xp.irfft(np, a, n, 1, conjugate=True)
        return np.abs(got - np.fft.irfft(np.conj(a), n=n)).max()

    assert max(map(one, calls)) < 1e-12
    with ThreadPoolExecutor(4) as pool:
        assert max(pool.map(one, calls * 3)) < 1e-12


def test_where_the_likelihood_ripples_or_has_a_prior_the_steps_are_the_outer_products():
    """Newton's steps with a kept information suit a smooth likelihood. Where the comb's
    aliases ripple it (the comb's layouts) a kept curvature or an unevaluated step can
    cross to another ripple: on a quiet sCMOS (0.3 e⁻ median) they made φ's RMS z 232
    (benchmarks/cmos_study.py); with a prior (the hierarchical norm's kink) a kept
    information took 43 trials a pixel. Both keep the outer product's steps."""
    from dataclasses import replace

    from emccdcal.fit import comb, layouts
    from emccdcal.fit.layouts import HierarchicalLayout

    intensity = layouts.layout_of("is-adu", [1, 1, 1], None, 4)
    assert intensity.newton_steps and layouts.layout_of("gs", [1, 5], np.ones(4), 4).newton_steps
    assert not comb._levels(intensity, np.array([0, 2])).newton_steps
    assert not replace(intensity, smooth=False).newton_steps
    assert not comb.CombLayout(**{**vars(intensity), "smooth": False}).newton_steps
    hierarchical = object.__new__(HierarchicalLayout)  # its data-built fields not needed
    hierarchical.smooth = True
    assert not hierarchical.newton_steps


def test_the_information_stack_is_inverted_at_once_as_each_matrix_alone():
    """The covariances of a block come from one batched inverse: each pixel's the same,
    bit for bit, as its matrix inverted alone; NaN where the information is not finite
    and positive definite."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 3, 3))
    H = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3)
    H[5] = -H[5]
    H[7, 0, 0] = np.nan
    cov, pos = _optimize.invert_information(H)
    assert pos.sum() == 198 and not pos[5] and not pos[7]
    assert np.isnan(cov[[5, 7]]).all()
    for i in np.flatnonzero(pos):
        assert np.array_equal(cov[i], np.linalg.inv(H[i]))
