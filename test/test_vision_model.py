"""The vision sensor model (paper eqs. 5-7) and one exposure on the grid, by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from inhand_mapping.occupancy import GridSpec
from inhand_stereo.vision_model import VisionMap, VisionModel, depth_spread, observe_grid

EPS, TAU = 0.01, 0.004


def model(**values) -> VisionModel:
    return VisionModel(**{'epsilon': EPS, 'tau': TAU, 'sigma_min': 0.001, 'zeta': 0.002,
                          **values})


def test_mu_is_eq6_in_front_inside_the_band_and_behind():
    m = model()
    assert m.mu(-0.02) == 0.0 and m.mu(-EPS / 2) == 0.0          # free in front
    assert m.mu(0.0) == pytest.approx(0.5)                        # on the surface
    assert m.mu(0.002) == pytest.approx(0.5 + 0.002 / EPS)        # the ramp
    assert m.mu(EPS / 2 + 1e-6) == 1.0 and m.mu(0.05) == 1.0      # occupied behind


def test_sigma_is_eq7_with_the_linear_and_the_stereo_noise():
    m = model()
    d = 0.4
    inside = (0.001 + 0.002 * d) / EPS
    assert m.sigma(0.0, d) == pytest.approx(inside)
    assert m.sigma(0.004, d) == pytest.approx(inside)             # flat inside the band
    far = 0.02
    assert m.sigma(-far, d) == pytest.approx(inside * math.exp(-(far - EPS / 2) / TAU))
    assert m.sigma(far, d) == pytest.approx(m.sigma(-far, d))     # symmetric
    stereo = model(noise='stereo')
    assert stereo.sigma_s(d) == pytest.approx(0.001 + 0.002 * d * d)
    assert stereo.sigma_s(2 * d) - stereo.sigma_s(0) == pytest.approx(
        4 * (stereo.sigma_s(d) - stereo.sigma_s(0)))              # grows with d^2


def test_the_two_readings_of_a_belief_as_a_probability():
    mass, mean = model(update='mass'), model(update='mean')
    d = 0.4
    sigma = mass.sigma(0.002, d)
    mu = mass.mu(0.002)
    from scipy.stats import norm, truncnorm
    assert mass.probability(0.002, d) == pytest.approx(norm.cdf((mu - 0.5) / sigma))
    a, b = (0 - mu) / sigma, (1 - mu) / sigma
    assert mean.probability(0.002, d) == pytest.approx(truncnorm.mean(a, b, mu, sigma))
    # on the surface both say 1/2; far in front both say free, far behind occupied
    for m in (mass, mean):
        assert m.probability(0.0, d) == pytest.approx(0.5)
        assert m.probability(-0.05, d) < 1e-4 and m.probability(0.05, d) > 1 - 1e-4
    # one observation is clamped: it cannot make a cell certain
    assert np.exp(mass.log_odds(0.05, d)) / (1 + np.exp(mass.log_odds(0.05, d))) == \
        pytest.approx(0.97)
    assert 1 / (1 + np.exp(-mass.log_odds(-0.05, d))) == pytest.approx(0.12)


def test_bad_parameters_are_refused_by_name():
    with pytest.raises(ValueError, match='epsilon'):
        VisionModel(epsilon=0.0)
    with pytest.raises(ValueError, match='noise'):
        VisionModel(noise='quadratic')
    with pytest.raises(ValueError, match='p_free'):
        VisionModel(p_free=0.6)


def _camera(width=64, height=48, focal=60.0):
    P = np.array([[focal, 0, (width - 1) / 2, 0], [0, focal, (height - 1) / 2, 0],
                  [0, 0, 1, 0]], dtype=float)
    return P


@pytest.mark.parametrize('options', [{}, {'update': 'mean', 'noise': 'stereo'}])
def test_one_exposure_against_a_brute_force_reference(options):
    """A wall at z = 0.3 m seen by a camera at the origin looking along +z (the map frame is
    the camera frame): every cell is checked one by one against the model (the compiled
    kernel against the numpy arithmetic of VisionModel)."""
    spec = GridSpec(0.1, 0.01, (0.0, 0.0, 0.3))
    P = _camera()
    depth = np.full((48, 64), 0.3, dtype=np.float32)
    depth[:, :10] = np.nan                                  # no measurement there
    m = model(epsilon=0.02, tau=0.01, **options)
    n = spec.cells_per_axis
    ijk = np.indices((n, n, n)).reshape(3, -1).T
    centres = spec.cell_centres(ijk)
    identity = (np.eye(3), np.zeros(3))
    seen = observe_grid(centres, spec.resolution, depth, P, identity, m)
    expected = {}
    for index, c in enumerate(centres):                     # the reference: cell by cell
        u = round(P[0, 0] * c[0] / c[2] + P[0, 2])
        v = round(P[1, 1] * c[1] / c[2] + P[1, 2])
        if not (0 <= u < 64 and 0 <= v < 48) or not np.isfinite(depth[v, u]):
            continue
        cell_range = math.sqrt(c @ c)
        measured = float(depth[v, u]) * cell_range / c[2]
        if cell_range - measured > spec.resolution / 2:
            continue                                        # behind the shell: unknown
        delta = cell_range - measured + spec.resolution / 2
        expected[index] = float(m.log_odds(delta, measured))
    assert sorted(expected) == seen.cells.tolist()
    assert np.allclose([expected[i] for i in seen.cells], seen.log_odds)
    # the wall's cells (the layer the surface passes through) lean occupied, those in
    # front of it free, none behind it is updated
    z = centres[seen.cells, 2]
    assert np.all(z <= 0.3 + spec.resolution)
    assert np.all(seen.log_odds[z < 0.28] < 0)


def test_the_vision_map_integrates_each_exposure_once_and_clamps():
    spec = GridSpec(0.1, 0.01, (0.0, 0.0, 0.3))
    vision = VisionMap(spec, model(), (0.12, 0.97))
    depth = np.full((48, 64), 0.3, dtype=np.float32)
    first = vision.integrate(depth, _camera(), (np.eye(3), np.zeros(3)))
    assert vision.exposures == 1 and vision.observed_mask().sum() == np.count_nonzero(
        first.log_odds)
    for _ in range(5):
        vision.integrate(depth, _camera(), (np.eye(3), np.zeros(3)))
    p = vision.probabilities()
    assert p.max() <= 0.97 + 1e-12 and p.min() >= 0.12 - 1e-12
    vision.reset()
    assert vision.exposures == 0 and not vision.observed_mask().any()


def test_the_depth_spread_is_the_matchers_scatter_zero_on_any_plane():
    v, u = np.mgrid[0:60, 0:80].astype(np.float64)
    slanted = (0.4 + 0.0005 * u - 0.0003 * v).astype(np.float32)
    spread = depth_spread(slanted, 5)
    inner = spread[3:-3, 3:-3]
    assert np.all(inner < 2e-6)                      # float32 rounding only, on a slant
    # white noise of 1 mm: each pixel less the mean of its 3x3 (itself included) has the
    # variance sigma^2 (1 - 2/9 + 1/9) = 8/9 sigma^2
    rng = np.random.default_rng(3)
    noisy = slanted + rng.normal(0.0, 0.001, slanted.shape).astype(np.float32)
    assert np.median(depth_spread(noisy, 5)[3:-3, 3:-3]) == pytest.approx(
        0.001 * math.sqrt(8 / 9), rel=0.1)
    # a depth edge scatters; no depth at all says nothing
    stepped = slanted.copy()
    stepped[:, 40:] += 0.05
    assert np.nanmin(depth_spread(stepped, 5)[10:50, 38:42]) > 0.005
    holed = slanted.copy()
    holed[20:40, 20:40] = np.nan
    assert np.all(np.isnan(depth_spread(holed, 5)[25:35, 25:35]))
