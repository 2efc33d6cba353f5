"""Tests of emccdcal.dark: offset / read-noise maps and the read-noise growth check."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from emccdcal.data.dark import check_read_noise_growth, maps_from_dark


def dark_stack(seed=0, n=200, shape=(5, 7), offset=588.0, sigma=15.5, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    return np.rint(rng.normal(offset, sigma, size=(n, *shape))).astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint16, np.int32, np.float32])
def test_maps_match_numpy(dtype):
    d = dark_stack(dtype=dtype)
    offset, read_noise = maps_from_dark(d)
    ref = d.astype(np.float64)
    assert offset.dtype == read_noise.dtype == np.float64
    assert offset.shape == read_noise.shape == (5, 7)
    np.testing.assert_allclose(offset, ref.mean(axis=0), rtol=1e-14)
    np.testing.assert_allclose(read_noise, ref.std(axis=0, ddof=1), rtol=1e-12)
    # and the numbers are those of the simulated camera
    assert abs(np.median(offset) - 588) < 3 and abs(np.median(read_noise) - 15.5) < 1.5


@pytest.mark.parametrize("chunk_frames", [1, 2, 7, 199, 200, 10_000])
def test_chunked_equals_unchunked(chunk_frames):
    d = dark_stack(seed=1)
    o_all, s_all = maps_from_dark(d, chunk_frames=10**9)
    o, s = maps_from_dark(d, chunk_frames=chunk_frames)
    np.testing.assert_allclose(o, o_all, rtol=1e-13)
    np.testing.assert_allclose(s, s_all, rtol=1e-11)


def test_accurate_with_a_large_offset_and_small_noise():
    # cancellation test: values near 60000 with SD ~ 0.5; the one-pass sum-of-squares
    # formula would lose most digits here
    rng = np.random.default_rng(2)
    d = (60000 + rng.integers(0, 2, size=(1001, 3, 3))).astype(np.uint16)
    offset, read_noise = maps_from_dark(d, chunk_frames=13)
    ref = d.astype(np.float64)
    np.testing.assert_allclose(offset, ref.mean(axis=0), rtol=1e-15)
    np.testing.assert_allclose(read_noise, ref.std(axis=0, ddof=1), rtol=1e-10)


def test_memmapped_big_endian_stack(tmp_path):
    d = dark_stack(seed=3)
    path = tmp_path / "dark.tif"
    tifffile.imwrite(path, d.astype(">u2"), photometric="minisblack")
    mm = tifffile.memmap(path, mode="r")
    assert isinstance(mm, np.memmap) and mm.dtype == np.dtype(">u2")
    offset, read_noise = maps_from_dark(mm, chunk_frames=16)
    np.testing.assert_allclose(offset, d.mean(axis=0), rtol=1e-14)
    np.testing.assert_allclose(read_noise, d.std(axis=0, ddof=1), rtol=1e-12)


def test_constant_pixel_has_zero_read_noise():
    d = dark_stack(seed=4)
    d[:, 2, 3] = 600
    offset, read_noise = maps_from_dark(d, chunk_frames=3)
    assert offset[2, 3] == 600 and read_noise[2, 3] == 0


@pytest.mark.parametrize(
    "stack, match",
    [
        (np.zeros((5, 4)), "3-D"),
        (np.zeros((1, 3, 3)), "at least 2 frames"),
        (np.array([[[np.nan]], [[1.0]]]), "NaN"),
        (np.array([[["a"]], [["b"]]]), "numbers"),
    ],
)
def test_bad_dark_stacks(stack, match):
    with pytest.raises(ValueError, match=match):
        maps_from_dark(stack)


def test_bad_chunk_size():
    with pytest.raises(ValueError, match="chunk_frames"):
        maps_from_dark(dark_stack(), chunk_frames=0)


# --------------------------------------------------------------------------------------
# Read noise growing with set-point
# --------------------------------------------------------------------------------------
def test_growth_warning_on_paper_numbers():
    maps = [np.full((3, 3), s) for s in (15.5, 15.5, 15.8, 16.6, 23.3)]
    msgs = check_read_noise_growth([1, 5, 25, 100, 300], maps)
    # 25x: +1.9 %, no warning; 100x: +7.1 %; 300x: +50 %
    assert len(msgs) == 2
    assert "set-point 100" in msgs[0] and "7 %" in msgs[0]
    assert "set-point 300" in msgs[1] and "23.3 ADU" in msgs[1] and "50 %" in msgs[1]
    assert all("clock-induced charge" in m and "15.5 ADU" in m for m in msgs)
    # what it does and what to do, at the user's numbers
    assert "take the amplifier's read noise from set-point 1, 15.5 ADU" in msgs[-1]
    assert all("\n" not in m for m in msgs)


def test_no_warning_when_flat_or_falling_or_single_setpoint():
    flat = [np.full((2, 2), 15.5), np.full((2, 2), 15.9), np.full((2, 2), 14.0)]
    assert check_read_noise_growth([1, 10, 100], flat) == []
    assert check_read_noise_growth([5, 5], [np.full((2, 2), 15), np.full((2, 2), 30)]) == []


def test_threshold_order_and_pooling():
    maps = [np.full((2, 2), 21.0), np.full((2, 2), 20.0)]
    # given out of order: the reference is the lowest set-point (20 ADU at 1x)
    assert len(check_read_noise_growth([300, 1], maps)) == 1
    assert check_read_noise_growth([300, 1], maps, threshold=0.06) == []
    # several maps at one set-point are pooled: median of 10, 10, 10, 30 values is 10
    pooled = [np.full((2, 2), 10.0)] * 3 + [np.full((2, 2), 30.0), np.full((2, 2), 10.2)]
    assert check_read_noise_growth([1, 1, 1, 1, 50], pooled) == []


def test_growth_check_bad_input():
    with pytest.raises(ValueError, match="2 set-points but 1 read-noise maps"):
        check_read_noise_growth([1, 5], [np.ones((2, 2))])
    with pytest.raises(ValueError, match="threshold"):
        check_read_noise_growth([1], [np.ones((2, 2))], threshold=-0.1)
    with pytest.raises(ValueError, match="positive"):
        check_read_noise_growth([1, 5], [np.zeros((2, 2)), np.ones((2, 2))])


def test_growth_on_the_real_sigma_maps(real_data):
    gs = real_data / "gain-GS"
    setpoints = [1, 5, 25, 100, 300]
    maps = [tifffile.imread(gs / f"{g}x-gain_no-signal_sigma.tif") for g in setpoints]
    msgs = check_read_noise_growth(setpoints, maps)
    assert any("set-point 300" in m for m in msgs)
    assert not any("set-point 5 " in m or "set-point 25 " in m for m in msgs)


class _Recording:
    """A stack that records how many frames each read asks for."""

    def __init__(self, data):
        self.data, self.dtype, self.shape, self.ndim = data, data.dtype, data.shape, data.ndim
        self.reads = []

    def __getitem__(self, item):
        out = self.data[item]
        self.reads.append(out.shape[0])
        return out


def test_default_streams_in_bounded_chunks(monkeypatch):
    import emccdcal.data.dark as dark

    monkeypatch.setattr(dark, "DEFAULT_CHUNK_ELEMENTS", 3 * 35)  # three (5, 7) frames
    d = dark_stack(seed=5, n=50)
    rec = _Recording(d)
    offset, read_noise = maps_from_dark(rec)
    assert max(rec.reads) == 3 and sum(rec.reads) == 50
    np.testing.assert_allclose(read_noise, d.std(axis=0, ddof=1), rtol=1e-12)


@pytest.mark.slow
def test_fit_dark_removes_the_multiplied_events_from_the_read_noise():
    """Darks at 400x with 0.02 clock-induced electrons per pixel per frame, an exact
    604-stage register: the plain SD is inflated by about 40 %, the fitted read noise is
    the read-out's within 1 % (here with the simulator's rounding, sqrt(σ² + 1/12))."""
    from emccdcal.data.dark import fit_dark
    from emccdcal.simulate.camera import simulate_frames

    dark = simulate_frames(
        0.0,
        400.0,
        5.2,
        500.0,
        15.4,
        frames=2000,
        rows=8,
        cols=8,
        cic=0.02,
        multiplication="cascade",
        stages=604,
        seed=11,
    )
    truth = np.sqrt(15.4**2 + 1 / 12)
    fit = fit_dark(dark)
    plain_offset, plain_sd = maps_from_dark(dark)
    assert fit.converged.all()
    assert abs(fit.read_noise.mean() / truth - 1) < 0.01
    assert plain_sd.mean() / truth - 1 > 0.2  # what the events do to it
    assert abs(fit.offset.mean() - 500.0) < 0.1 < plain_offset.mean() - 500.0
    assert abs(np.mean(fit.event_rate) / 0.02 - 1) < 0.15
    assert abs(fit.event_scale / (400.0 / 5.2) - 1) < 0.1  # g/φ, ADU per electron


def test_fit_dark_without_events_is_the_plain_mean_and_sd():
    from emccdcal.data.dark import fit_dark
    from emccdcal.simulate.camera import simulate_frames

    dark = simulate_frames(0.0, 5.0, 5.2, 500.0, 15.4, frames=500, rows=3, cols=3, seed=2)
    fit = fit_dark(dark)
    offset, sd = maps_from_dark(dark)
    np.testing.assert_allclose(fit.offset, offset, rtol=1e-12)
    np.testing.assert_allclose(fit.read_noise, sd, rtol=1e-12)
    assert fit.event_scale == 0.0 and np.isnan(fit.event_rate).all()


@pytest.mark.slow
def test_a_calibration_with_dark_stacks_at_gain_uses_the_fitted_maps(tmp_path):
    """The manifest's dark stack at 400x (0.02 events per pixel per frame) gives the
    read-out's read noise, not the inflated SD, and the result records the event rate."""
    import re
    import warnings

    from emccdcal import calibrate
    from emccdcal.simulate.series import simulate_gain_series

    sim = simulate_gain_series(
        tmp_path,
        setpoints=(1, 400),
        em_gain=(1, 380.0),
        rows=6,
        cols=6,
        frames=300,
        dark_frames=2000,
        seed=4,
        cic=0.02,
        e_per_adu=5.2,
        read_noise=15.4,
    )
    text = sim.manifest.read_text()
    text = re.sub(
        r'offset = ".*"\nread_noise = ".*"\ndark_frames = .*\n# dark = (".*")  .*',
        r"dark = \1",
        text,
    )
    manifest = sim.manifest.with_name("darks.toml")
    manifest.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = calibrate(manifest, "gs", checks=False)
    truth = np.sqrt(15.4**2 + 1 / 12)
    sigma = ds.read_noise.sel(setpoint=400.0).values
    assert abs(sigma.mean() / truth - 1) < 0.01
    rate = ds.dark_event_rate.sel(setpoint=400.0).values
    assert abs(rate.mean() / 0.02 - 1) < 0.3
    assert np.isnan(ds.dark_event_rate.sel(setpoint=1.0).values).all()
