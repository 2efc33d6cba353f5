"""Tests of emccdcal.stats: per-pixel histograms of counts."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from emccdcal.data.stats import PixelHistograms, histograms
from emccdcal.errors import InputError

ADC_MAX = 1023


def frames_with_saturation(seed=0, n=300, shape=(4, 5)):
    """Random counts with saturated frames, a constant pixel and special pixels."""
    rng = np.random.default_rng(seed)
    f = rng.poisson(40, size=(n, *shape)) + rng.integers(900, 1000, size=shape)
    f = np.minimum(f, ADC_MAX).astype(np.uint16)  # clipped at the ADC maximum
    f[rng.random(f.shape) < 0.05] = ADC_MAX  # extra saturated frames
    f[:, 0, 1] = 700  # constant pixel
    f[:, 3, 4] = ADC_MAX  # fully saturated pixel
    f[:, 2, 0] = ADC_MAX
    f[17, 2, 0] = 950  # a pixel with a single usable frame
    f[:, 1, 2] = rng.integers(0, 3, size=n)  # values at 0
    return f


def reference(frames, adc_max):
    """Per-pixel histograms with np.unique, one pixel at a time."""
    n_frames, rows, cols = frames.shape
    out = []
    for p in range(rows * cols):
        x = frames.reshape(n_frames, rows * cols)[:, p].astype(np.int64)
        used = x[x < adc_max] if adc_max is not None else x
        v, c = np.unique(used, return_counts=True)
        out.append((v, c, used, int(x.size - used.size)))
    return out


def check_against_reference(h: PixelHistograms, frames, adc_max):
    ref = reference(frames, adc_max)
    assert h.values.dtype == np.int64 and h.counts.dtype == np.float64
    assert h.values.shape == h.counts.shape == (len(ref), max(1, max(r[0].size for r in ref)))
    for p, (v, c, used, n_sat) in enumerate(ref):
        k = v.size
        np.testing.assert_array_equal(h.values[p, :k], v)
        np.testing.assert_array_equal(h.counts[p, :k], c)
        assert np.all(h.counts[p, k:] == 0)
        pad = v[-1] if k else 0
        assert np.all(h.values[p, k:] == pad)
        assert h.n[p] == used.size and h.n_saturated[p] == n_sat
        if used.size:
            assert h.min[p] == used.min() and h.max[p] == used.max()
            np.testing.assert_allclose(h.mean[p], used.mean(), rtol=1e-14)
        else:
            assert np.isnan(h.mean[p]) and h.min[p] == 0 and h.max[p] == 0
        if used.size >= 2:
            np.testing.assert_allclose(h.var[p], used.var(ddof=1), rtol=1e-12, atol=1e-12)
        else:
            assert np.isnan(h.var[p])


def test_against_np_unique_with_saturation():
    f = frames_with_saturation()
    h = histograms(f, adc_max=ADC_MAX)
    assert h.shape == (4, 5) and h.adc_max == ADC_MAX and h.n_pixels == 20
    check_against_reference(h, f, ADC_MAX)
    # the special pixels, in C order
    assert h.n_saturated[3 * 5 + 4] == 300 and h.n[3 * 5 + 4] == 0
    assert h.n[2 * 5 + 0] == 1 and h.mean[2 * 5 + 0] == 950 and np.isnan(h.var[2 * 5 + 0])
    const = 0 * 5 + 1
    assert h.n[const] == 300 and h.var[const] == 0 and h.mean[const] == 700
    assert h.values[const, 0] == 700 and h.counts[const, 0] == 300
    assert np.all(h.values[const] == 700) and h.counts[const, 1:].sum() == 0
    np.testing.assert_array_equal(h.counts.sum(axis=1), h.n)
    np.testing.assert_array_equal(h.n + h.n_saturated, 300)


def test_without_adc_max_nothing_is_excluded():
    f = frames_with_saturation(seed=1)
    h = histograms(f)
    check_against_reference(h, f, None)
    assert h.adc_max is None and np.all(h.n_saturated == 0) and np.all(h.n == 300)


def test_values_above_adc_max_are_saturated_too():
    f = frames_with_saturation(seed=2)
    h = histograms(f, adc_max=990)
    check_against_reference(h, f, 990)
    assert h.max.max() < 990


@pytest.mark.parametrize("chunk_pixels", [1, 3, 7, 20, 1000])
def test_chunked_equals_unchunked(chunk_pixels):
    f = frames_with_saturation(seed=3)
    a = histograms(f, adc_max=ADC_MAX)
    b = histograms(f, adc_max=ADC_MAX, chunk_pixels=chunk_pixels)
    for name in ("values", "counts", "n", "n_saturated", "min", "max"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-15)
    np.testing.assert_allclose(b.var, a.var, rtol=1e-15)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.int64, np.float32, np.float64, ">u2"])
def test_dtypes_give_the_same_histograms(dtype):
    f = frames_with_saturation(seed=4).astype(np.int64)
    adc_max = ADC_MAX
    if np.dtype(dtype).itemsize == 1:  # shift into 0..255, keeping saturated frames
        f, adc_max = np.clip(f - 800, 0, 255), ADC_MAX - 800
    h = histograms(f.astype(dtype), adc_max=adc_max)
    assert h.n_saturated.sum() > 300
    check_against_reference(h, f, adc_max)


def test_memmap_input(tmp_path):
    f = frames_with_saturation(seed=5)
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, f.astype(">u2"), photometric="minisblack")
    mm = tifffile.memmap(path, mode="r")
    h = histograms(mm[10:], adc_max=ADC_MAX, chunk_pixels=6)
    check_against_reference(h, f[10:], ADC_MAX)


def test_all_pixels_saturated_and_zero_frames():
    f = np.full((4, 2, 2), ADC_MAX, np.uint16)
    h = histograms(f, adc_max=ADC_MAX)
    assert h.values.shape == (4, 1) and np.all(h.counts == 0) and np.all(h.n == 0)
    assert np.all(np.isnan(h.mean)) and np.all(h.n_saturated == 4)
    h = histograms(np.zeros((0, 2, 3), np.uint16))
    assert h.values.shape == (6, 1) and np.all(h.n == 0) and np.all(np.isnan(h.var))


@pytest.mark.parametrize(
    "frames, match",
    [
        (np.zeros((3, 4)), "3-D"),
        (np.array([[[1.5]], [[2.0]]]), "not integers"),
        (np.array([[[np.nan]], [[2.0]]]), "NaN"),
        (np.array([[[3]], [[-1]]]), "negative"),
        (np.array([[[3.0]], [[-1.0]]]), "negative"),
        (np.array([[["a"]], [["b"]]]), "integer counts"),
    ],
)
def test_bad_frames(frames, match):
    with pytest.raises(ValueError, match=match):
        histograms(frames)


@pytest.mark.parametrize("adc_max", [0, -5, 2.5, True])
def test_bad_adc_max(adc_max):
    with pytest.raises(ValueError, match="adc_max"):
        histograms(np.ones((3, 1, 1), np.uint16), adc_max=adc_max)


@settings(max_examples=40, deadline=None)
@given(
    arrays(
        np.uint16,
        st.tuples(st.integers(0, 12), st.integers(1, 3), st.integers(1, 4)),
        elements=st.integers(0, 20),
    ),
    st.one_of(st.none(), st.integers(1, 21)),
    st.integers(1, 13),
)
def test_property_against_reference(frames, adc_max, chunk_pixels):
    h = histograms(frames, adc_max=adc_max, chunk_pixels=chunk_pixels)
    check_against_reference(h, frames, adc_max)


def test_real_data_histograms(real_data):
    path = real_data / "gain-GS/300x-gain.tif"
    f = tifffile.memmap(path, mode="r")
    h = histograms(f, adc_max=65535)
    assert h.shape == (3, 3) and np.all(h.n == 5000) and np.all(h.n_saturated == 0)
    np.testing.assert_allclose(h.mean, f.reshape(5000, 9).mean(axis=0), rtol=1e-13)
    ref = f.reshape(5000, 9).astype(np.float64)
    np.testing.assert_allclose(h.var, ref.var(axis=0, ddof=1), rtol=1e-11)


def test_default_block_size_bounds_memory(monkeypatch):
    import emccdcal.data.stats as stats

    sizes = []
    real = stats._block_histograms

    def recording(block, adc_max):
        sizes.append(block.size)
        return real(block, adc_max)

    monkeypatch.setattr(stats, "_block_histograms", recording)
    monkeypatch.setattr(stats, "DEFAULT_CHUNK_ELEMENTS", 4 * 300)  # four pixels of 300 frames
    f = frames_with_saturation(seed=6)
    h = stats.histograms(f, adc_max=ADC_MAX)
    assert max(sizes) == 4 * 300 and sum(sizes) == f.size
    check_against_reference(h, f, ADC_MAX)


def test_histograms_through_the_array_api_standard_are_numpys():
    """The sort and the runs computed on array-api-strict arrays (a pretend device that
    refuses NumPy) give NumPy's histograms: saturated counts, float-valued counts, a
    pixel with no usable frame; negative counts refused the same way."""
    pytest.importorskip("array_api_strict")
    from emccdcal import _xp

    rng = np.random.default_rng(4)
    frames = rng.poisson(30, size=(200, 3, 5)).astype(np.uint16)
    frames[::3, 0, 0] = 255
    frames[:, 2, 4] = 255  # every frame saturated
    floats = rng.poisson(5, size=(40, 2, 2)).astype(np.float64)
    for data, adc_max in ((frames, 255), (frames, None), (floats, None)):
        want = histograms(data, adc_max=adc_max)
        with _xp.computing_on("array-api-strict"):
            got = histograms(data, adc_max=adc_max)
        for name in ("values", "counts", "n", "n_saturated", "mean", "var", "min", "max"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)
    with _xp.computing_on("array-api-strict"), pytest.raises(InputError, match="negative"):
        histograms(-np.ones((3, 1, 1), dtype=np.int16))
