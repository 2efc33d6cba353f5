"""Counts of many pixels that share one register's output, each with its own read-out.

In a shutter-closed stack the count of pixel i is ``S = S0_i + X + ε_i``: its own offset
S0_i and Gaussian read-out ε_i ~ N(0, σ_i²) (ADU), and the register's output X (ADU) of the
electrons made before it (clock-induced charge and dark current, E per pixel per frame)
and inside it (the register's own clock-induced charge c, which only the exact register
has), whose distribution the pixels share:

    p_i(k) = P0·φ(k − S0_i; σ_i) + B(k − S0_i; σ_i),    P0 = e^(−E − c),

φ the Gaussian density and B = b ∗ φ_σ the events' part, b the density of X where X > 0.
The window engine (:mod:`._engine`) would take one FFT of thousands of points per pixel
and evaluation; a sensor has hundreds of thousands of pixels. Here the Gaussian part is
computed exactly and B is tabulated once for all pixels: by an inverse FFT of the
register's transform on a grid of spacing h = σ/12 at reference read noises σ_c a factor
1.004 apart, and evaluated at each count by cubic Hermite interpolation in
u = k − S0_i and a Taylor series in Δ = (σ_i² − σ_c²)/2: the Gaussian's heat equation,
∂B/∂Δ = ∂²B/∂u², makes the series' terms the tables of B's even derivatives, whose
transforms are the register's times (−ω²)^r. Derivatives by the shared parameters are
tables of their own, by the pixels' S0 and σ those of the interpolant and the series.
Only the reference read noises that some pixel is near are tabulated.

With a rate E_i of its own per pixel, e^(E_i·v) (v the transform of one electron's output
minus one) is expanded in powers of E_i, one table per power, until they no longer count.

Accuracy (tests/test_gain_check.py compares with :func:`emccdcal.model.noise.logpmf`):
|Δ ln p| below 1e-6 wherever p is above 1e-6 of its peak and 1e-5 above 1e-10, the
scores within 2e-6 (the gain's) to 5e-5 (the read noise's) of their differences: far
below what moves an estimate (a systematic relative error ε of the scores biases a fit of
N counts by at most ε·√N of its standard error: 0.01 at 5e7 counts). The read noise must be at least
1.5 ADU (below, the density at the integers no longer sums to one).
"""

from __future__ import annotations

import math
import numpy as np

from .. import _xp
from ..errors import InputError, OptionError
from ._engine import fast_len

__all__ = ["SharedRegister", "MIN_READ_NOISE"]

#: Smallest read noise the tables serve, ADU.
MIN_READ_NOISE = 1.5
#: Grid points per read-noise width of the smallest reference read noise.
_POINTS_PER_SIGMA = 12
#: Reference read noises are a factor e^(2·_CLASS) apart; a pixel's is within e^±_CLASS of one.
_CLASS = 0.002
#: Terms of the Taylor series in Δ (Δ^0 … Δ^2; its Δ-derivative, the read noise's score,
#: has one fewer).
_TERMS = 3
#: Read-noise widths on the left of the offset, and single-electron outputs on the right
#: of it, that the tables cover (the events' density at 45 outputs is e^-45 of its peak).
_LEFT_SIGMAS, _RIGHT_OUTPUTS, _RIGHT_SIGMAS = 14.0, 45.0, 14.0

#: Largest memory the tables may take while they are built, bytes; and what they take a
#: point (a reference read noise's grid point) and column, measured with tracemalloc.
MAX_TABLE_BYTES = 2**30
_BYTES_PER_POINT = 40
#: The Gaussian's transform is below e^-40 beyond ω = √80 / σ: no bin beyond is needed.
_BAND = math.sqrt(80.0)
#: The expected information is summed over every 4th grid point, at every 4th
#: reference read noise.
_INFO_STRIDE = 4
#: Powers of a per-pixel rate are summed until (2E)^m/m! is below this.
_SERIES_TOL = 1e-12
#: Probabilities below this fraction of the pixel's Gaussian peak are floored (outliers:
#: a cosmic ray beyond the tables); their scores are zero.
_FLOOR = 1e-14


class SharedRegister:
    """The pmf of dark counts, and its derivatives, for pixels sharing a register.

    Parameters
    ----------
    register
        The register model (``EMModel(...).register``).
    em_gain : float
        g, the register's mean gain (> 1).
    e_per_adu : float
        φ, e⁻/ADU.
    read_noise : array_like
        The pixels' read noises σ_i (ADU): where the reference read noises are placed.
        Any σ within them may be evaluated (:meth:`covers`).
    rate : float
        E, electrons per pixel per frame entering the register (pooled); with
        ``per_pixel_rate`` the largest rate any pixel will be evaluated at.
    register_cic : float
        c, electrons per pixel per frame made inside the register (exact register only).
    per_pixel_rate : bool
        Each pixel its own rate (passed to :meth:`evaluate`).
    shared : sequence of str
        Shared parameters to differentiate by: ``"ln_gain"``, ``"register_cic"`` and (the
        pooled rate) ``"ln_rate"``.
    """

    def __init__(
        self,
        register,
        em_gain,
        e_per_adu,
        read_noise,
        *,
        rate,
        register_cic=0.0,
        per_pixel_rate=False,
        shared=("ln_gain",),
    ):
        sigma = np.asarray(read_noise, dtype=float)
        if not np.all(sigma >= MIN_READ_NOISE):
            raise OptionError(
                f"a read noise below {MIN_READ_NOISE} ADU "
                f"({float(np.min(sigma)):.3g}) is outside the tables' range"
            )
        if register_cic and "register_cic" not in register.parameters:
            raise OptionError("register_cic is a parameter of the exact register only")
        self.register, self.g, self.phi = register, float(em_gain), float(e_per_adu)
        self.E, self.c = float(rate), float(register_cic)
        self.per_pixel = bool(per_pixel_rate)
        self.shared = tuple(shared)
        unknown = set(self.shared) - {"ln_gain", "register_cic", "ln_rate"}
        if unknown or (self.per_pixel and "ln_rate" in self.shared):
            raise OptionError(f"cannot differentiate by {sorted(unknown) or ['ln_rate']}")
        # reference read noises: those of a log grid, step 2·_CLASS from the smallest
        # pixel's, that some pixel is near (an outlier adds one, not a range)
        self._lo = float(sigma.min())
        self._grid = np.unique(self._grid_index(sigma))
        self.class_sigma = self._lo * np.exp(_CLASS + 2 * _CLASS * self._grid)
        self.h = self._lo / _POINTS_PER_SIGMA
        theta = self.g / self.phi  # one electron's mean output, ADU
        self.u0 = float(-_LEFT_SIGMAS * self.class_sigma[-1] * math.exp(_CLASS))
        u_end = _RIGHT_SIGMAS * self.class_sigma[-1] * math.exp(_CLASS) + _RIGHT_OUTPUTS * theta
        self.n = fast_len(int(math.ceil((u_end - self.u0) / self.h)) + 2)
        self._build()

    # ------------------------------------------------------------------ the tables
    def _grid_index(self, sigma):
        return np.rint(
            (np.log(np.asarray(sigma, dtype=float) / self._lo) - _CLASS) / (2 * _CLASS)
        ).astype(np.intp)

    def covers(self, read_noise) -> bool:
        """Whether these read noises lie within the reference read noises' reach."""
        j = self._grid_index(read_noise)
        at = np.clip(np.searchsorted(self._grid, j), 0, self._grid.size - 1)
        return bool(np.all(self._grid[at] == j))

    def _transforms(self, omega):
        """v and v̄ (one electron's, one register electron's transform minus one) at
        s = iω, and their derivatives by ln g."""
        s = 1j * omega[None, :]
        g, phi = np.array([self.g, self.g]), np.array([self.phi, self.phi])
        if "register_cic" in self.register.parameters:
            rows = self.register.rows(np.array([1.0, 0.0]), g, phi, np.array([0.0, 1.0]))
        else:  # a model without register charge: v̄ is not used (c = 0)
            rows = self.register.rows(np.array([1.0, 1.0]), g, phi)
        K, first, _ = rows.cgf(s, order=1, names=rows.names)
        dg = self.register.public_gradients(first, g[:, None], phi[:, None])["em_gain"]
        return K[0], K[1], self.g * dg[0], self.g * dg[1]

    def _build(self):
        n, h = self.n, self.h
        band = min(
            n // 2 + 1, int(math.ceil(_BAND / self.class_sigma[0] * n * h / (2 * math.pi))) + 2
        )
        omega = 2.0 * math.pi * np.arange(band) / (n * h)
        v, vbar, v_g, vbar_g = self._transforms(omega)
        E, c = self.E, self.c
        P0 = math.exp(-E - c)
        spectra = {}  # name -> list of (transform, per-pixel power of E or None)
        if not self.per_pixel:
            phi_x = np.exp(E * v + c * vbar)
            spectra["value"] = [phi_x - P0]
            if "ln_gain" in self.shared:
                spectra["ln_gain"] = [phi_x * (E * v_g + c * vbar_g)]
            if "ln_rate" in self.shared:
                spectra["ln_rate"] = [E * (v * phi_x + P0)]
            if "register_cic" in self.shared:
                spectra["register_cic"] = [vbar * phi_x + P0]
        else:
            # e^(E v + c v̄) − e^(−E − c) = Σ_m E^m/m! [v^m e^(c v̄) − (−1)^m e^(−c)]
            m_max = 1
            while (2 * E) ** (m_max + 1) / math.factorial(m_max + 1) > _SERIES_TOL:
                m_max += 1
            e_cv = np.exp(c * vbar)
            powers = [np.ones_like(v)]
            for _ in range(m_max):
                powers.append(powers[-1] * v)
            spectra["value"] = [
                powers[m] * e_cv - (-1) ** m * math.exp(-c) for m in range(m_max + 1)
            ]
            if "ln_gain" in self.shared:
                spectra["ln_gain"] = [
                    (m * powers[m - 1] * v_g if m else 0.0) * e_cv + powers[m] * e_cv * c * vbar_g
                    for m in range(m_max + 1)
                ]
            if "register_cic" in self.shared:
                spectra["register_cic"] = [
                    powers[m] * vbar * e_cv + (-1) ** m * math.exp(-c) for m in range(m_max + 1)
                ]
        self._check_size(sum(len(specs) for specs in spectra.values()) * _TERMS)
        # One table of all: a row per (reference read noise, grid point), a column per
        # series term of every part (its value, then h·∂/∂u), so that each count's
        # interpolation gathers two rows
        self.parts = {}  # name -> [(first column, terms)] per power of E
        columns = []
        for name, specs in spectra.items():
            self.parts[name] = []
            for spec in specs:
                self.parts[name].append((sum(c[0].shape[0] for c in columns), _TERMS))
                columns.append(self._tabulate(spec, omega, _TERMS))
        self.Q = sum(c[0].shape[0] for c in columns)
        table = np.concatenate([c[0] for c in columns] + [c[1] for c in columns])
        # single precision: its 1e-7 relative round-off moves an estimate from 5e7
        # counts by 0.001 of its standard error (module docstring), at half the memory
        self.table = table.reshape(2 * self.Q, -1).astype(np.float32)  # (2Q, classes·N)
        self._on_device = {}  # the table where evaluations compute, copied once

    def _check_size(self, columns: int) -> None:
        """Refuse tables of more than :data:`MAX_TABLE_BYTES` while they are built (about
        40 bytes a point and column, measured: the transforms, both inverse FFTs and the
        joined table) before any is: pixels whose read noises span a wide range (light
        on some of them) need thousands of reference read noises."""
        points = self._grid.size * self.n
        need = _BYTES_PER_POINT * columns * points
        if need > MAX_TABLE_BYTES:
            raise InputError(
                f"the pixels' read noises span {self._lo:.4g} to "
                f"{float(self.class_sigma[-1]):.4g} ADU: the noise model's tables of "
                f"{self._grid.size} of them would take {need / 2**30:.1f} GiB (at most "
                f"{MAX_TABLE_BYTES / 2**30:.0f} GiB); fit dark pixels of one read-out "
                "(a region without light)"
            )

    def _table_in(self, xp, dev):
        """The table as an array of ``xp`` on ``dev`` (copied there once)."""
        key = (xp.__name__, str(dev))
        if key not in self._on_device:
            self._on_device[key] = _xp.on(xp, dev, self.table)
        return self._on_device[key]

    def _tabulate(self, spectrum, omega, terms):
        """The tables of the density whose transform is ``spectrum`` (ω ≥ 0): for every
        reference read noise, the Gaussian's factor and the series' (−ω²)^r, shifted to
        the grid's start; values and h·∂/∂u by inverse FFT, each (terms, classes, N)."""
        from scipy import fft

        gauss = np.exp(-0.5 * (self.class_sigma[:, None] * omega[None, :]) ** 2)
        powers = (-(omega**2))[None, :] ** np.arange(terms)[:, None]
        spec = np.broadcast_to(spectrum, omega.shape) * np.exp(-1j * omega * self.u0)
        full = powers[:, None, :] * gauss[None, :, :] * spec[None, None, :]
        f = fft.irfft(np.conj(full), n=self.n, axis=-1) / self.h
        d = fft.irfft(np.conj(full * (-1j * omega)), n=self.n, axis=-1)
        return f, d

    # ------------------------------------------------------------------ evaluation
    def coordinates(self) -> tuple[str, ...]:
        """The columns of :meth:`evaluate`'s scores: each pixel's own (offset, ln read
        noise[, ln rate]), then the shared parameters in the order given."""
        return ("offset", "ln_read_noise") + (("ln_rate",) if self.per_pixel else ()) + self.shared

    def evaluate(self, values, counts, offset, read_noise, rate=None, *, outer=False, xp=None):
        """Log-likelihood and scores of a block of pixels.

        Parameters
        ----------
        values, counts : ndarray, shape (P, K)
            Each pixel's distinct counts (ADU) and how often each occurred (0: padding).
        offset, read_noise : ndarray, shape (P,)
            S0_i and σ_i, ADU.
        rate : ndarray, shape (P,), optional
            E_i with ``per_pixel_rate`` (e⁻ per pixel per frame).
        outer : bool
            Also the outer products of the per-count scores.
        xp : (namespace, device), optional
            Where the interpolation and the sums compute (default: where this thread's
            fit computes, :func:`emccdcal._xp.engine`); the results are NumPy arrays.

        Returns
        -------
        loglik : ndarray, shape (P,)
            Σ counts · ln p, nats.
        grad : ndarray, shape (P, D)
            Its derivatives by :meth:`coordinates`.
        outer : ndarray, shape (P, D, D) or None
            Σ counts · s sᵀ of the per-count scores s (the BHHH information).
        floored : ndarray, shape (P,)
            Counts whose probability was floored (beyond the tables: outliers).
        """
        xp, dev = _xp.engine() if xp is None else xp
        p, columns, low = self._derivatives(
            self._points(values, offset, read_noise, rate, (xp, dev)), xp
        )
        counts = _xp.on(xp, dev, np.asarray(counts, dtype=float))
        scores = xp.where(low[..., None], 0.0, columns / p[..., None])
        weighted = scores * counts[..., None]
        loglik = xp.sum(counts * xp.log(p), axis=1)
        grad = xp.sum(weighted, axis=1)
        products = None
        if outer:
            products = _xp.to_numpy(xp.matmul(xp.permute_dims(weighted, (0, 2, 1)), scores))
        floored = xp.sum(xp.where(low, counts, 0.0), axis=1)
        return _xp.to_numpy(loglik), _xp.to_numpy(grad), products, _xp.to_numpy(floored)

    def information(self):
        """The expected (Fisher) information of one frame, in :meth:`coordinates`, of a
        pixel at each reference read noise (pooled rate only): ∫ p s sᵀ du over the
        tables' grid (the sum over the integers differs from it by e^(−2π²σ²)).

        Returns
        -------
        ndarray, shape (classes, D, D)
        """
        if self.per_pixel:
            raise OptionError("the expected information is the pooled rate's only")
        # Every _INFO_STRIDE-th grid point (the integrand is as smooth as the Gaussian:
        # the sum's error is e^(−2π²(σ/4h)²)), at every _INFO_STRIDE-th reference read
        # noise, linear in ln σ in between (it changes by 1e-5 from one to the next)
        u = self.u0 + self.h * np.arange(0, self.n - 1, _INFO_STRIDE)
        C = self.class_sigma.size
        at = np.unique(np.r_[np.arange(0, C, _INFO_STRIDE), C - 1])
        host = _xp.resolve("cpu")
        p, columns, low = self._derivatives(
            self._points(
                np.broadcast_to(u, (at.size, u.size)),
                np.zeros(at.size),
                self.class_sigma[at],
                None,
                host,
            ),
            host[0],
        )
        w = np.where(low, 0.0, _INFO_STRIDE * self.h / p)
        info = np.matmul(np.swapaxes(columns * w[..., None], 1, 2), columns)
        out = np.empty((C,) + info.shape[1:])
        where = np.log(self.class_sigma)
        for i in range(info.shape[1]):
            for j in range(info.shape[2]):
                out[:, i, j] = np.interp(where, where[at], info[:, i, j])
        return out

    def classes(self, read_noise):
        """The reference read noise of each pixel (indices into ``class_sigma``)."""
        at = np.searchsorted(self._grid, self._grid_index(read_noise))
        return np.clip(at, 0, self._grid.size - 1)

    def pmf(self, values, offset, read_noise, rate=None):
        """p_i(k) at ``values`` (P, K) of pixels with these offsets and read noises (and
        rates, with ``per_pixel_rate``); below the tables' round-off (about 1e-17 of the
        events' peak) a value may be 0."""
        at = self._points(values, offset, read_noise, rate, _xp.resolve("cpu"))
        p = at.A + sum(
            at.weights[..., k] * at.series(first, terms)[0]
            for k, (first, terms) in enumerate(self.parts["value"])
        )
        return np.maximum(p, 0.0)

    def _points(self, values, offset, read_noise, rate, where):
        """The interpolation at ``values`` (:class:`_Points`), computed by the namespace
        and device ``where``; each pixel's own numbers are made on the host."""
        xp, dev = where
        sigma = np.asarray(read_noise, dtype=float)
        if not self.covers(sigma):
            raise OptionError("read noise outside the tables' reach: build them again")
        # the reference read noise of each pixel and its Δ
        cls = self.classes(sigma)
        delta = 0.5 * (sigma**2 - self.class_sigma[cls] ** 2)[:, None]
        S0, sig, delta, first_row = _xp.on(
            xp,
            dev,
            np.asarray(offset, dtype=float)[:, None],
            sigma[:, None],
            delta,
            (cls * self.n)[:, None].astype(np.int64),
        )
        E = self.E if rate is None else _xp.on(xp, dev, np.asarray(rate, dtype=float)[:, None])
        u = _xp.on(xp, dev, np.asarray(values, dtype=float)) - S0
        z = u / sig
        P0 = math.exp(-E - self.c) if rate is None else xp.exp(-E - self.c)
        A = P0 * xp.exp(-0.5 * z * z) / (math.sqrt(2.0 * math.pi) * sig)
        t = (u - self.u0) / self.h
        inside = (t >= 0) & (t < self.n - 1)
        left = xp.where(inside, xp.floor(t), 0.0)
        row = xp.astype(left, xp.int64) + first_row
        if self.per_pixel:
            m = np.arange(len(self.parts["value"]))
            factorials = _xp.on(xp, dev, np.array([float(math.factorial(k)) for k in m]))
            weights = E[..., None] ** _xp.on(xp, dev, m.astype(float)) / factorials
        else:
            weights = xp.ones(tuple(u.shape[:1]) + (1, 1), dtype=xp.float64, device=dev)
        s = xp.astype(xp.where(inside, t - left, 0.0), xp.float32)
        return _Points(
            self._table_in(xp, dev), self.Q, row, s, inside, delta, A, z, sig, E, weights
        )

    def _derivatives(self, at, xp):
        """p at the points (floored), the derivatives of p by :meth:`coordinates`
        (..., D), and where p was floored (arrays of ``xp``, the points')."""
        B = dB_u = dB_delta = dB_rate = 0.0
        for k, (first, terms) in enumerate(self.parts["value"]):
            val, der, dd = at.series(first, terms, derivatives=True)
            w = at.weights[..., k]
            B, dB_u, dB_delta = B + w * val, dB_u + w * der, dB_delta + w * dd
            if self.per_pixel:
                dB_rate = dB_rate + k * w * val  # ∂/∂ ln E_i of E_i^k/k!
        A, z, sig, E = at.A, at.z, at.sig, at.E
        p = A + B
        P0 = math.exp(-E - self.c) if isinstance(E, float) else xp.exp(-E - self.c)
        floor = _FLOOR * P0 / (math.sqrt(2.0 * math.pi) * sig)
        low = (p < floor) | ~xp.isfinite(p)
        p = xp.where(low, floor, p)
        columns = [
            A * z / sig - dB_u / self.h,  # offset
            A * (z * z - 1.0) + sig**2 * dB_delta,
        ]  # ln σ
        if self.per_pixel:
            columns.append(-E * A + dB_rate)  # ln E_i
        for name in self.shared:
            part = 0.0
            for k, (first, terms) in enumerate(self.parts[name]):
                part = part + at.weights[..., k] * at.series(first, terms)[0]
            if name == "ln_rate":
                part = part - self.E * A
            elif name == "register_cic":
                part = part - A
            columns.append(part)  # (every shared part has at least one table)
        return p, xp.stack([xp.broadcast_to(c, p.shape) for c in columns], axis=-1), low


class _Points:
    """Cubic Hermite interpolation of the table's columns (each a row of ``table``, of
    values then h·∂/∂u) at fixed points, the bases computed once; each part's series
    in Δ summed from its columns."""

    def __init__(self, table, Q, row, s, inside, delta, A, z, sig, E, weights):
        self.xp = _xp.namespace(table)
        s2, s3 = s * s, s * s * s
        self.h = (2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2)
        self.dh = (6 * s2 - 6 * s, 3 * s2 - 4 * s + 1, -6 * s2 + 6 * s, 3 * s2 - 2 * s)
        self.table, self.Q, self.row, self.inside = table, Q, row, inside
        self.delta = delta
        self.A, self.z, self.sig, self.E, self.weights = A, z, sig, E, weights

    def series(self, first, terms, derivatives=False):
        """Σ_r Δ^r/r! T_r of the part whose terms are the columns ``first`` …; with
        ``derivatives`` also its u-derivative (times h) and its Δ-derivative."""
        val = der = dd = 0.0
        power, previous = 1.0, None  # Δ^r / r!, Δ^(r−1) / (r−1)!
        xp, row, h = self.xp, self.row, self.h
        flat, shape = xp.reshape(row, (-1,)), tuple(row.shape)
        at = lambda column, shift: xp.reshape(xp.take(column, flat + shift), shape)  # noqa: E731
        for r in range(terms):
            f, d = self.table[first + r, :], self.table[self.Q + first + r, :]
            f0, f1, d0, d1 = at(f, 0), at(f, 1), at(d, 0), at(d, 1)
            term = h[0] * f0 + h[1] * d0 + h[2] * f1 + h[3] * d1
            val = val + power * term
            if derivatives:
                dh = self.dh
                der = der + power * (dh[0] * f0 + dh[1] * d0 + dh[2] * f1 + dh[3] * d1)
                if previous is not None:
                    dd = dd + previous * term
            previous, power = power, power * self.delta / (r + 1)
        out = ~self.inside
        if derivatives:
            return (xp.where(out, 0.0, val), xp.where(out, 0.0, der), xp.where(out, 0.0, dd))
        return xp.where(out, 0.0, val), None, None
