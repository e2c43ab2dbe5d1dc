"""Fusion of the touch and vision local maps (paper eqs. 8-12) on hand-made maps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from inhand_mapping.entropy import cell_entropy
from inhand_mapping.fusion import fuse

CLAMP = (math.log(0.12 / 0.88), math.log(0.97 / 0.03))


def logit(p):
    return np.log(np.asarray(p, dtype=float) / (1 - np.asarray(p, dtype=float)))


def sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x)))


def test_none_is_the_touch_map_and_no_vision_map_changes_nothing():
    touch = logit(np.array([0.2, 0.5, 0.9])).reshape(1, 1, 3)
    for fusion in ('none', 'product', 'entropy'):
        assert np.array_equal(fuse(fusion, touch, None, CLAMP).log_odds, touch)
    assert np.array_equal(fuse('none', touch, np.ones_like(touch), CLAMP).log_odds, touch)


def test_product_adds_the_evidence_and_clamps():
    touch = logit([0.7, 0.7, 0.9, 0.5]).reshape(1, 1, 4)
    vision = logit([0.7, 0.3, 0.9, 0.5]).reshape(1, 1, 4)
    fused = sigmoid(fuse('product', touch, vision, CLAMP).log_odds).ravel()
    # 0.7 and 0.7 agree: 0.49 / (0.49 + 0.09); 0.7 and 0.3 cancel; 0.9 and 0.9 clamp
    assert fused[0] == pytest.approx(0.49 / 0.58)
    assert fused[1] == pytest.approx(0.5)
    assert fused[2] == pytest.approx(0.97)
    assert fused[3] == pytest.approx(0.5)


EQ_12 = {'entropy_radius': 0, 'entropy_pooling': 'linear'}   # the paper's, as written


def test_entropy_weights_by_hand_whole_map():
    # touch: two certain-ish cells; vision: one vague cell and one it did not see
    p_touch = np.array([0.9, 0.1])
    p_vision = np.array([0.6, 0.5])
    h_touch = cell_entropy(p_touch).sum()
    h_vision = cell_entropy(p_vision).sum()
    w_touch = 1 - h_touch / (h_touch + h_vision)       # eq. 11
    w_vision = 1 - h_vision / (h_touch + h_vision)
    assert w_touch + w_vision == pytest.approx(1.0) and w_touch > w_vision
    fused = fuse('entropy', logit(p_touch).reshape(1, 1, 2), logit(p_vision).reshape(1, 1, 2),
                 CLAMP, **EQ_12)
    assert fused.touch_weight == pytest.approx(w_touch)
    expected = np.clip(w_touch * p_touch + w_vision * p_vision, 0.12, 0.97)   # eq. 12
    assert np.allclose(sigmoid(fused.log_odds).ravel(), expected)


def test_local_entropy_trusts_each_sensor_where_it_is_confident():
    # two regions along x: touch knows the left half, vision the right half
    shape = (12, 3, 3)
    touch = np.zeros(shape)
    vision = np.zeros(shape)
    touch[:6] = logit(0.95)
    vision[6:] = logit(0.95)
    whole = fuse('entropy', touch, vision, CLAMP, **EQ_12)
    local = fuse('entropy', touch, vision, CLAMP, entropy_radius=1, entropy_pooling='linear')
    # the whole-map weights are one number per sensor (here equal): the known cells fall to
    # the middle; the local weights follow the sensor that knows
    assert whole.touch_weight == pytest.approx(0.5)
    assert sigmoid(whole.log_odds[0, 1, 1]) == pytest.approx(0.725)
    h_known = float(cell_entropy(0.95))
    w_known = 1 - h_known / (h_known + 1.0)                 # eq. 11 against 1 bit a cell
    assert local.touch_weight[2, 1, 1] == pytest.approx(w_known)
    assert local.vision_weight[9, 1, 1] == pytest.approx(w_known)
    expected = w_known * 0.95 + (1 - w_known) * 0.5
    assert sigmoid(local.log_odds[2, 1, 1]) == pytest.approx(expected)
    assert sigmoid(local.log_odds[9, 1, 1]) == pytest.approx(expected) and expected > 0.8


def test_a_bad_fusion_name_or_radius_is_refused():
    grid = np.zeros((2, 2, 2))
    with pytest.raises(ValueError, match='fusion must be one of none, product, entropy'):
        fuse('average', grid, grid, CLAMP)
    with pytest.raises(ValueError, match='radius'):
        fuse('entropy', grid, grid, CLAMP, entropy_radius=-1)


def test_log_pooling_keeps_the_confident_sensors_evidence():
    # touch is sure of cell 0, which vision did not see; vision is sure the rest is free
    # (so its map is the less uncertain one and weighs more); both agree on the last cell
    touch = logit([0.97, 0.5, 0.5, 0.5, 0.9]).reshape(1, 1, 5)
    vision = logit([0.5, 0.03, 0.03, 0.03, 0.9]).reshape(1, 1, 5)
    linear = fuse('entropy', touch, vision, CLAMP, **EQ_12)
    log = fuse('entropy', touch, vision, CLAMP, entropy_radius=0, entropy_pooling='log')
    w_touch, w_vision = log.touch_weight, log.vision_weight
    assert w_vision > w_touch and linear.touch_weight == pytest.approx(w_touch)
    expected = (w_touch * touch + w_vision * vision) / max(w_touch, w_vision)
    assert np.allclose(log.log_odds, np.clip(expected, *CLAMP))
    assert sigmoid(linear.log_odds[0, 0, 0]) < 0.8          # the sum of probabilities loses it
    assert sigmoid(log.log_odds[0, 0, 0]) > 0.8             # the weighted log-odds keep it
    assert sigmoid(log.log_odds[0, 0, 4]) > 0.9             # agreement is kept
    with pytest.raises(ValueError, match='pooling'):
        fuse('entropy', touch, vision, CLAMP, entropy_pooling='max')


def test_entropy_on_its_defaults_is_the_form_that_measured_best_not_eq_12_literally():
    """A user who picks fusion: entropy gets local entropies pooled in log-odds (bench_fusion:
    within 0.02 of the product form; eq. 12 as written loses half the map)."""
    from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS
    defaults = {spec.name: spec.default for spec in OCCUPANCY_PARAMETERS}
    assert (defaults['entropy_radius'], defaults['entropy_pooling']) == (1, 'log')
    # a patch touch is sure of and vision did not see (it is sure of free space elsewhere)
    # stays occupied on the defaults
    touch = np.zeros((7, 7, 7))
    vision = np.full((7, 7, 7), logit(0.03))
    touch[1:4, 1:4, 1:4], vision[1:4, 1:4, 1:4] = logit(0.97), 0.0
    default = fuse('entropy', touch, vision, CLAMP)
    literal = fuse('entropy', touch, vision, CLAMP, **EQ_12)
    assert sigmoid(default.log_odds[2, 2, 2]) > 0.8 > sigmoid(literal.log_odds[2, 2, 2])
