"""How the stereo camera's range noise grows with range: the sigma_min and zeta of eq. 7.

The paper leaves ``sigma_s(d) = sigma_min + zeta d`` to "sensor calibration". Given range
errors (measured minus true) at known ranges, :func:`fit_noise` bins them by range, takes
a robust spread per bin (1.4826 x the median absolute deviation: wild matches do not
inflate it) and fits both models by weighted least squares (weights: the bins' sample
counts), each with non-negative coefficients:

* ``linear``: ``sigma_min + zeta d`` (the paper);
* ``stereo``: ``sigma_min + zeta d^2``, the triangulation error of a stereo pair, ``d^2
  sigma_disparity / (f B)`` for a disparity noise in pixels, focal f (px), baseline B (m).

The better fit is the one with the lower weighted RMS residual over the bins; both are
reported. Ranges from one viewpoint span a few centimetres, where the two models cannot be
told apart: calibrate with sessions at several distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_stereo.vision_model import NOISE_MODELS

__all__ = ['NoiseFit', 'NoiseModelFit', 'fit_noise', 'robust_sigma']

MIN_PER_BIN = 50


def robust_sigma(errors: ArrayLike) -> float:
    """1.4826 x the median absolute deviation: the standard deviation of a Gaussian core."""
    values = np.asarray(errors, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


@dataclass(frozen=True)
class NoiseModelFit:
    noise: str               # 'linear' or 'stereo'
    sigma_min: float         # m
    zeta: float              # 1 (linear) or 1/m (stereo)
    rms: float               # m: weighted RMS of the bins' spreads about the model

    def sigma(self, d: ArrayLike) -> NDArray[np.float64]:
        d = np.asarray(d, dtype=np.float64)
        growth = d if self.noise == 'linear' else d * d
        sigma: NDArray[np.float64] = self.sigma_min + self.zeta * growth
        return sigma


@dataclass(frozen=True)
class NoiseFit:
    """Both fits, the bins they were made from, and which fits better."""

    fits: dict[str, NoiseModelFit]
    bin_ranges: NDArray[np.float64]     # m, the median range of each bin
    bin_sigmas: NDArray[np.float64]     # m, the robust spread of each bin
    bin_counts: NDArray[np.int64]
    bias: float                         # m, the median error (a calibration offset)

    @property
    def best(self) -> NoiseModelFit:
        return min(self.fits.values(), key=lambda fit: fit.rms)


def _fit(noise: str, ranges: NDArray[np.float64], sigmas: NDArray[np.float64],
         weights: NDArray[np.float64]) -> NoiseModelFit:
    growth = ranges if noise == 'linear' else ranges ** 2
    w = np.sqrt(weights)
    design = np.stack([np.ones_like(growth), growth], axis=1)
    candidates = []
    solution, *_ = np.linalg.lstsq(design * w[:, None], sigmas * w, rcond=None)
    candidates.append((float(solution[0]), float(solution[1])))
    # the non-negative alternatives: only the growth, or only the constant
    wg, ws = w * growth, w * sigmas
    zeta_only = max(float(wg @ ws) / max(float(wg @ wg), 1e-300), 0.0)
    candidates += [(0.0, zeta_only), (float(np.average(sigmas, weights=weights)), 0.0)]
    best = None
    for sigma_min, zeta in candidates:
        if sigma_min < 0 or zeta < 0:
            continue
        residual = sigmas - (sigma_min + zeta * growth)
        rms = float(np.sqrt(np.average(residual ** 2, weights=weights)))
        if best is None or rms < best.rms:
            best = NoiseModelFit(noise, sigma_min, zeta, rms)
    assert best is not None      # the constant candidate is always non-negative
    return best


def fit_noise(ranges: ArrayLike, errors: ArrayLike, bins: int = 8) -> NoiseFit:
    """Fit both noise models to range errors (m) at true ranges (m); ValueError when there
    are too few (fewer than 2 bins of at least 50 samples)."""
    d = np.asarray(ranges, dtype=np.float64).reshape(-1)
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    finite = np.isfinite(d) & np.isfinite(e) & (d > 0)
    d, e = d[finite], e[finite]
    if len(d) < 2 * MIN_PER_BIN:
        raise ValueError(f'{len(d)} range errors: need at least {2 * MIN_PER_BIN}')
    edges = np.quantile(d, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, d, side='right') - 1, 0, bins - 1)
    ranges_out, sigmas_out, counts_out = [], [], []
    for k in range(bins):      # a handful of bins, not a loop per sample
        member = which == k
        if member.sum() >= MIN_PER_BIN:
            ranges_out.append(float(np.median(d[member])))
            sigmas_out.append(robust_sigma(e[member]))
            counts_out.append(int(member.sum()))
    if len(ranges_out) < 2:
        raise ValueError('the range errors fill fewer than 2 bins of 50: nothing to fit')
    bin_ranges = np.array(ranges_out)
    bin_sigmas = np.array(sigmas_out)
    bin_counts = np.array(counts_out, dtype=np.int64)
    weights = bin_counts.astype(np.float64)
    fits: dict[str, NoiseModelFit] = {noise: _fit(noise, bin_ranges, bin_sigmas, weights)
                                      for noise in NOISE_MODELS}
    return NoiseFit(fits, bin_ranges, bin_sigmas, bin_counts, float(np.median(e)))
