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
    seen = observe_grid(spec, depth, P, identity, m)
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
    first = vision.observe(depth, _camera(), (np.eye(3), np.zeros(3)))
    assert vision.integrate(depth, _camera(), (np.eye(3), np.zeros(3))) == len(first.cells)
    assert vision.exposures == 1 and vision.observed_mask().sum() == np.count_nonzero(
        first.log_odds)
    assert np.array_equal(vision.log_odds.reshape(-1)[first.cells],
                          np.clip(first.log_odds, *vision.clamp))
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


def _noisy_scene(rng, height=48, width=64):
    """A slanted wall with 1 mm of noise, a depth step, holes and a few non-positive
    depths: what a stereo matcher's depth looks like."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    depth = 0.3 + 0.0005 * u - 0.0003 * v + rng.normal(0.0, 0.001, u.shape)
    depth[:, 40:] += 0.02
    depth[rng.random(u.shape) < 0.15] = np.nan
    depth[5:9, 5:9] = np.nan
    depth[30, 30] = 0.0
    depth[31, 31] = -0.1
    return depth.astype(np.float32)


@pytest.mark.parametrize('window', [3, 5, 9])
def test_the_compiled_depth_spread_is_the_numpy_one(window):
    """vision_kernels.depth_surface against depth_spread (box filters, the reference): the
    same pixels without a spread, the same spread to float32 rounding."""
    from inhand_stereo.vision_kernels import depth_surface
    depth = _noisy_scene(np.random.default_rng(window))
    surface = np.empty((*depth.shape, 2), dtype=np.float32)
    depth_surface(depth, np.empty((0, 0), dtype=bool), window, surface)
    reference = depth_spread(depth, window)
    assert np.array_equal(np.isnan(surface[..., 1]), np.isnan(reference))
    both = ~np.isnan(reference)
    assert np.allclose(surface[..., 1][both], reference[both], rtol=2e-3, atol=2e-7)
    valid = np.isfinite(depth) & (depth > 0)
    assert np.array_equal(surface[..., 0][valid], depth[valid])
    assert np.all(np.isnan(surface[..., 0][~valid]))


@pytest.mark.parametrize('options', [{}, {'update': 'mean', 'noise': 'stereo'}])
def test_an_exposure_with_mask_and_spread_is_the_numpy_reference(options):
    """VisionMap.integrate (one compiled pass over the grid, applied in place) against the
    model computed with numpy from the same depth: every cell's projection, the object
    mask (off the object only free space), the spread, the band behind the surface, the
    clamp. The set of updated cells is the same and their log-odds agree to the spread's
    float32 rounding; fed the same spread, observe_grid gives the reference's cells."""
    rng = np.random.default_rng(7)
    spec = GridSpec(0.1, 0.005, (0.0, 0.0, 0.3))
    m = model(epsilon=0.01, tau=0.004, spread_window=5, **options)
    depth = _noisy_scene(rng)
    mask = np.zeros(depth.shape, dtype=bool)
    mask[10:40, 15:50] = True                     # the object's pixels; the rest is scene
    P = _camera()
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.96, -0.28], [0.0, 0.28, 0.96]])
    placed = (rotation, np.array([0.004, -0.003, 0.01]))
    vision = VisionMap(spec, m, (0.12, 0.97))
    vision.log_odds += rng.uniform(-3.0, 3.0, vision.log_odds.shape)   # an earlier map
    before = vision.log_odds.copy()
    updated = vision.integrate(depth, P, placed, mask)

    # the reference, cell by cell in numpy
    n = spec.cells_per_axis
    centres = spec.cell_centres(np.indices((n, n, n)).reshape(3, -1).T)
    # written out as the kernel sums them (a matrix product may add in another order and
    # move a centre that lies on a pixel's or the band's border by an ulp across it)
    camera = np.stack([rotation[r, 0] * centres[:, 0] + rotation[r, 1] * centres[:, 1]
                       + rotation[r, 2] * centres[:, 2] + placed[1][r] for r in range(3)], axis=1)
    x, y, z = camera.T
    w = z
    with np.errstate(invalid='ignore', divide='ignore'):
        u, v = np.rint((P[0, 0] * x + P[0, 2] * z) / w), np.rint((P[1, 1] * y + P[1, 2] * z) / w)
    seen = (z > 1e-3) & (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
    rows, cols = v[seen].astype(int), u[seen].astype(int)
    spread = depth_spread(depth, 5)[rows, cols].astype(float)
    measured = depth[rows, cols].astype(float)
    cell_range = np.linalg.norm(camera[seen], axis=1)
    with np.errstate(invalid='ignore'):
        measured_range = measured * cell_range / z[seen]
        behind = cell_range - measured_range
        far_side = behind + spec.resolution / 2
        on_object = mask[rows, cols]
        used = np.isfinite(measured) & (measured > 0) & np.isfinite(spread) & np.where(
            on_object, behind <= m.band_behind(spec.resolution), far_side <= -m.epsilon / 2)
    cells = np.flatnonzero(seen)[used]
    expected = m.log_odds(far_side[used], measured_range[used],
                          (spread * cell_range / z[seen])[used])
    assert updated == len(cells) > 300
    changed = np.flatnonzero(vision.log_odds.reshape(-1) != before.reshape(-1))
    assert set(changed) <= set(cells)
    assert np.allclose(vision.log_odds.reshape(-1)[cells],
                       np.clip(before.reshape(-1)[cells] + expected, *vision.clamp), atol=1e-5)
    untouched = np.ones(n ** 3, dtype=bool)
    untouched[cells] = False
    assert np.array_equal(vision.log_odds.reshape(-1)[untouched], before.reshape(-1)[untouched])
    # fed the reference spread itself, the kernel's cells are the reference's
    observed = observe_grid(spec, depth, P, placed, m, mask, depth_spread(depth, 5))
    assert np.array_equal(observed.cells, cells)
    assert np.allclose(observed.log_odds, expected, rtol=1e-9, atol=1e-12)
