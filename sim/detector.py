"""A model of the Hamamatsu C7942 flat panel: line integrals in, raw uint16 frames out.

Signal chain per pixel (counts): ``raw = clip(dark + gain * q * Poisson(I0 * exp(-L) / q) +
N(0, read_noise), 0, 2**bits - 1)`` where ``q`` is counts per detected quantum (so the shot noise
variance is ``q * signal``), ``gain`` a smooth non-uniformity times a small per-pixel spread, and
``dark`` a per-pixel offset. Defects are planted and known: dead pixels (no response),
under-responding pixels, noisy pixels, and whole defect columns. Binning sums charge: a 2x2 binned
pixel collects four pixels' signal and is read once, so at one source (``I0`` per unbinned pixel,
the dose) the read-out holds ``b^2`` times the counts and shot variance under one read noise -- an
SNR about ``b`` times the unbinned pixel's -- and the same 12-bit ADC clips the sum at 4095: an
open beam that fits 1x1 can saturate 2x2 or 4x4.

The open beam ``I0`` is the same on every pixel: a point source's inverse-square and obliquity
falloff on a flat panel (``cos^3`` of the ray's angle to the normal: 0.964 at the corners of the
full 112 mm panel 500 mm from the source, the pva-phantom's cone beam) and the anode heel are not
modelled. The flat field divides them out of the mean exactly; they would only raise the noise
there, by ``cos^-3/2`` (1.9 % at those corners).

Defaults follow the C7942 facts (../shared/hardware/C7942.md): 12-bit ADC, about 1100 e- read
noise against a 2.2 Me- full well (so ~2 counts rms), a dark offset of a hundred-odd counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["PanelModel", "DefectTruth"]


@dataclass
class DefectTruth:
    """Where the planted defects are (for tests and reports)."""

    dead: np.ndarray  # (k, 2) row, col
    under: np.ndarray  # (k, 2)
    noisy: np.ndarray  # (k, 2)
    columns: np.ndarray  # (m,)

    def mask(self, shape) -> np.ndarray:
        m = np.zeros(shape, bool)
        for pts in (self.dead, self.under, self.noisy):
            if len(pts):
                m[pts[:, 0], pts[:, 1]] = True
        m[:, self.columns] = True
        return m


def _smooth_gain(rows, cols, variation) -> np.ndarray:
    """The panel's smooth gain non-uniformity over the frame, mean 1."""
    y = np.linspace(-1, 1, rows)[:, None]
    x = np.linspace(-1, 1, cols)[None, :]
    smooth = 1 + variation * (0.6 * np.cos(1.3 * x + 0.4) * np.cos(0.9 * y) - 0.4 * (x * x + y * y) / 2)
    return smooth / smooth.mean()


@dataclass
class PanelModel:
    """A C7942-like panel with known gain, offset, noise and defects.

    Parameters
    ----------
    rows, cols : int
        Frame geometry after binning (2240 x 2240 unbinned).
    binning : int
        1, 2 or 4; signal is summed over ``binning**2`` pixels before readout.
    bits : int
        ADC depth; values clip at ``2**bits - 1``.
    dark_level, dark_spread : float
        Mean dark offset and its pixel-to-pixel spread (counts).
    read_noise : float
        Read noise (counts rms) per readout.
    counts_per_quantum : float
        Counts per detected X-ray quantum: the shot-noise variance is this times the signal.
    gain_variation : float
        Peak relative amplitude of the smooth gain non-uniformity.
    pixel_gain_spread : float
        Relative pixel-to-pixel gain spread.
    n_dead, n_under, n_noisy : int
        Planted isolated defect pixels; under-responding pixels have 30 % response, noisy ones
        ten times the read noise.
    defect_columns : tuple of int
        Whole columns at 40 % response (a defect line).
    seed : int
        Everything fixed by the model (gain, offsets, defect positions) comes from this seed;
        noise comes from the ``rng`` passed to each call (or a fresh one).
    """

    rows: int = 2240
    cols: int = 2240
    binning: int = 1
    bits: int = 12
    dark_level: float = 120.0
    dark_spread: float = 6.0
    read_noise: float = 2.0
    counts_per_quantum: float = 1.0
    gain_variation: float = 0.08
    pixel_gain_spread: float = 0.01
    n_dead: int = 12
    n_under: int = 12
    n_noisy: int = 12
    defect_columns: tuple = (701,)
    seed: int = 7
    gain: np.ndarray = field(init=False, repr=False)
    offset: np.ndarray = field(init=False, repr=False)
    noise: np.ndarray = field(init=False, repr=False)
    truth: DefectTruth = field(init=False, repr=False)

    @classmethod
    def open_beam_ceiling(cls, spread: float = 3.0) -> float:
        """The largest open-beam signal (counts above the dark offset, one read-out pixel, the
        panel's mean gain) whose flat frames stay below the ADC's top code: the brightest pixels
        (the smooth gain's peak times ``spread`` pixel-gain deviations) plus the dark offset
        (``spread`` of its deviations) plus ``spread`` standard deviations of shot and read noise.
        The mean alone against the ceiling let a quarter of the flats clip at 4095 (their gain
        is up to ~5 % over the mean), which the calibration then marks defective or, once over
        its 10 %, refuses; a clipped flat biases the line integral low where the gain is high.
        Binned by ``b``, the dose per unbinned pixel may be at most this over ``b**2``
        (``sim.scene.Scene.validate`` checks it)."""
        g = _smooth_gain(257, 257, cls.gain_variation).max() * (1 + spread * cls.pixel_gain_spread)
        top = (1 << cls.bits) - 1 - cls.dark_level - spread * cls.dark_spread
        # g i0 + spread sqrt(q g i0 + r^2) = top, a quadratic in sqrt(i0)-like form: solved by
        # fixed point (the noise term is a ~2 % correction, so three rounds settle it)
        i0 = top / g
        for _ in range(8):
            i0 = (top - spread * math.sqrt(cls.counts_per_quantum * g * i0 + cls.read_noise**2)) / g
        return float(i0)

    def __post_init__(self):
        if self.binning not in (1, 2, 4):
            raise ValueError(f"binning={self.binning}: the C7942 bins 1x1, 2x2 or 4x4")
        rng = np.random.default_rng(self.seed)
        shape = (self.rows, self.cols)
        gain = _smooth_gain(self.rows, self.cols, self.gain_variation)
        gain *= 1 + self.pixel_gain_spread * rng.standard_normal(shape)
        self.offset = (self.dark_level + self.dark_spread * rng.standard_normal(shape)).astype(np.float32)
        self.noise = np.full(shape, self.read_noise, np.float32)
        cols = [c for c in self.defect_columns if 0 <= c < self.cols]
        # Keep isolated defects off the defect lines and the border, and apart from each other.
        free = np.ones(shape, bool)
        free[:, [max(c - 2, 0) for c in cols] + [min(c + 2, self.cols - 1) for c in cols] + cols] = False
        free[:2], free[-2:], free[:, :2], free[:, -2:] = False, False, False, False
        k = self.n_dead + self.n_under + self.n_noisy
        cand = np.flatnonzero(free)
        picks = rng.choice(cand, size=min(k * 4, cand.size), replace=False)
        chosen = []
        for p in picks:  # at least 3 pixels apart, so each is an isolated defect
            r, c = divmod(int(p), self.cols)
            if all(abs(r - r2) > 2 or abs(c - c2) > 2 for r2, c2 in chosen):
                chosen.append((r, c))
            if len(chosen) == k:
                break
        pts = np.array(chosen, dtype=np.int64).reshape(-1, 2)
        dead, under, noisy = np.split(pts, [self.n_dead, self.n_dead + self.n_under])
        if len(dead):
            gain[dead[:, 0], dead[:, 1]] = 0.0
        if len(under):
            gain[under[:, 0], under[:, 1]] *= 0.3
        if len(noisy):
            self.noise[noisy[:, 0], noisy[:, 1]] *= 10
        gain[:, cols] *= 0.4
        self.gain = gain.astype(np.float32)
        self.truth = DefectTruth(dead, under, noisy, np.array(cols, dtype=np.int64))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def saturation(self) -> int:
        return (1 << self.bits) - 1

    def _read(self, signal: np.ndarray, n: int, rng) -> np.ndarray:
        """Read ``n`` frames of a mean ``signal`` (counts above dark, before gain)."""
        rng = rng if rng is not None else np.random.default_rng()
        out = np.empty((n,) + self.shape, np.uint16)
        q = self.counts_per_quantum
        lam = np.maximum(signal, 0) * (self.binning**2) / q
        for i in range(n):
            quanta = rng.poisson(lam) if np.any(lam) else np.zeros(self.shape)
            value = self.offset + self.gain * (q * quanta) + self.noise * rng.standard_normal(self.shape, np.float32)
            np.clip(np.rint(value), 0, self.saturation, out=value)
            out[i] = value
        return out

    def dark_frames(self, n=10, rng=None) -> np.ndarray:
        """``n`` frames with the beam off, (n, rows, cols) uint16."""
        return self._read(np.zeros(self.shape, np.float32), n, rng)

    def flat_frames(self, n=10, i0=2500.0, rng=None) -> np.ndarray:
        """``n`` open-beam frames of ``i0`` counts per unbinned pixel (a read-out pixel sums
        ``binning**2`` of them, clipped at the ADC's top)."""
        return self._read(np.full(self.shape, i0, np.float32), n, rng)

    def expose(self, line_integral, i0=2500.0, n=1, rng=None) -> np.ndarray:
        """Frames of an object with line integral ``-ln(I/I0)`` per pixel, (n, rows, cols) uint16;
        ``i0`` per unbinned pixel, as in :meth:`flat_frames`."""
        line_integral = np.asarray(line_integral, np.float32)
        if line_integral.shape != self.shape:
            raise ValueError(f"line integral is {line_integral.shape}; the panel is {self.shape}")
        if not np.isfinite(line_integral).all():
            raise ValueError("line integral contains NaN or inf")
        return self._read(i0 * np.exp(-line_integral), n, rng)

    def expected(self, line_integral, i0=2500.0) -> np.ndarray:
        """The noise-free mean raw signal (float), before clipping."""
        return self.offset + self.gain * i0 * self.binning**2 * np.exp(-np.asarray(line_integral, np.float32))
