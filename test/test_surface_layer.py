"""The surface layer (surface_layer.py): of two cells stacked along the local normal, the
weaker keeps ``layer_factor`` of its evidence; the map read applies it lazily, around the
cells whose evidence changed, and the result does not depend on when it was read.

Expected values come from the rule's arithmetic: a plane of cells carrying evidence has its
normal across the plane; a cell above it with less evidence than the plane cell below keeps
0.4 of its evidence; cells of the plane, and a cell that is no weaker than its neighbours
along the normal, keep all of theirs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from inhand_mapping import map_io
from inhand_mapping.occupancy import GridSpec, OccupancyGrid, SensorModel
from inhand_mapping.path_kernels import PathModel
from inhand_mapping.surface_layer import BRIDGE_MIN_TOUCHES, apply_layer, layered_evidence

N = 16
C = 0.45


def flat(ix, iy, iz):
    return (ix * N + iy) * N + iz


def sheet(height=3.0, z=8):
    """Evidence (N^3,) of a 10 x 10 sheet of cells at z, ``height`` touches each."""
    evidence = np.zeros(N ** 3)
    for ix in range(3, 13):
        for iy in range(3, 13):
            evidence[flat(ix, iy, z)] = height
    return evidence


def test_a_cell_of_the_layer_above_a_sheet_keeps_the_factor_of_its_evidence_and_its_share():
    evidence = sheet()
    evidence[flat(8, 8, 9)] = 1.5          # a lift-off's pass just above the sheet
    # 0.4 of it, times its share of the stronger cell under it (1.5 of 3)
    assert layered_evidence(evidence, N, flat(8, 8, 9), 0.4, 1.0) == pytest.approx(0.3)
    assert layered_evidence(evidence, N, flat(8, 8, 8), 0.4, 1.0) == 3.0
    assert layered_evidence(evidence, N, flat(8, 8, 9), 1.0, 1.0) == 1.5   # factor 1: off
    # A much-rubbed spot's noise in the cell above: 6 touches over a sheet of 30 keep 0.48,
    # where the factor alone would keep 2.4 (occupied)
    rubbed = sheet(height=30.0)
    rubbed[flat(8, 8, 9)] = 6.0
    assert layered_evidence(rubbed, N, flat(8, 8, 9), 0.4, 1.0) == pytest.approx(0.48)


def test_two_sheets_side_by_side_keep_both_a_thin_wall():
    # A wall explored from both sides: two stacked sheets as strong as each other.
    evidence = sheet(z=8) + sheet(z=9)
    for z in (8, 9):
        assert layered_evidence(evidence, N, flat(8, 8, z), 0.4, 1.0) == 3.0


def air(evidence, zs, touches=0.1):
    """``evidence`` with the path's air (carries, lifts: under AIR_TOUCHES) over the sheet's
    area at the heights ``zs``."""
    evidence = evidence.copy()
    for z in zs:
        for ix in range(3, 13):
            for iy in range(3, 13):
                evidence[flat(ix, iy, z)] = touches
    return evidence


def test_a_thin_walls_weaker_side_is_kept_where_the_air_lies_on_both_sides_of_the_wall():
    """Two stacked sheets, one weaker: with the air on both outer sides they are a thin
    wall's two sides (the fingers reached each from its own side) and the weaker keeps its
    evidence; with the air above both, the weaker is the layer above the surface."""
    stacked = sheet(3.0, z=8) + sheet(2.0, z=9)
    wall = air(stacked, (6, 7, 10, 11))
    assert layered_evidence(wall, N, flat(8, 8, 9), 0.4, 1.0) == 2.0
    assert layered_evidence(wall, N, flat(8, 8, 8), 0.4, 1.0) == 3.0
    hover = air(stacked, (10, 11))
    assert layered_evidence(hover, N, flat(8, 8, 9), 0.4, 1.0) == pytest.approx(0.4 * 2.0 * 2.0 / 3.0)
    # no air at all: nothing says which side is open, the weaker is the layer as before
    assert layered_evidence(stacked, N, flat(8, 8, 9), 0.4, 1.0) == pytest.approx(0.4 * 2.0 * 2.0 / 3.0)


def test_of_two_stacked_sheets_as_strong_the_one_outside_the_other_is_the_layer():
    """A hover as slow as the stroke under it earns as much evidence: with the air above
    both sheets the upper one is outside the lower one's surface and keeps the factor of its
    evidence; with the air on both outer sides (a wall touched from both sides) both keep all
    of it; with no air nothing says which is outside."""
    stacked = sheet(2.0, z=8) + sheet(2.0, z=9)
    hover = air(stacked, (10, 11))
    assert layered_evidence(hover, N, flat(8, 8, 9), 0.4, 1.0) == pytest.approx(0.8)
    assert layered_evidence(hover, N, flat(8, 8, 8), 0.4, 1.0) == 2.0
    wall = air(stacked, (6, 7, 10, 11))
    for z in (8, 9):
        assert layered_evidence(wall, N, flat(8, 8, z), 0.4, 1.0) == 2.0
        assert layered_evidence(stacked, N, flat(8, 8, z), 0.4, 1.0) == 2.0


def test_a_lone_stroke_keeps_its_evidence():
    # A line of cells: the plane through it is any plane containing it; the cells beside
    # the line carry nothing, so no cell of the line is weaker than its neighbours.
    evidence = np.zeros(N ** 3)
    for ix in range(2, 14):
        evidence[flat(ix, 8, 8)] = 2.0
    # Nor is it a sheet: no gain (one stroke alone does not confirm a surface).
    assert layered_evidence(evidence, N, flat(7, 8, 8), 0.4, 1.75) == 2.0


def test_a_cell_of_a_flat_sheet_counts_its_evidence_gain_times_once_it_holds_a_pass():
    # One pass at stroke speed through each cell of an explored patch (1.5 touches: p 0.77,
    # under 0.8): confirmed by the sheet around it, the pass is enough.
    evidence = sheet(height=1.5)
    assert layered_evidence(evidence, N, flat(8, 8, 8), 0.4, 1.75) == pytest.approx(2.625)
    # Under SHEET_MIN_TOUCHES (a pass that turned back, a glancing touch): no gain.
    weak = sheet(height=0.8)
    assert layered_evidence(weak, N, flat(8, 8, 8), 0.4, 1.75) == 0.8
    # The layer above the sheet gets none either: it is the weaker one along the normal.
    evidence[flat(8, 8, 9)] = 1.4
    assert layered_evidence(evidence, N, flat(8, 8, 9), 0.4, 1.75) == pytest.approx(0.4 * 1.4 * 1.4 / 1.5)


def test_a_cell_far_under_the_local_level_is_the_layer_whatever_the_plane_says():
    # A well-explored patch (12 touches a cell) with a cell two touches strong in the air
    # beside its edge, off the plane: nothing stronger one step along the normal (the test
    # of the layer misses it), but it holds 2 / 12 of the level around it (under 0.2).
    evidence = sheet(height=12.0)
    hover = flat(13, 8, 9)
    evidence[hover] = 2.0
    level = np.sum(evidence[evidence > 0] ** 2) / np.sum(evidence)   # the 7^3 box holds all
    assert 2.0 < 0.2 * level
    assert layered_evidence(evidence, N, hover, 0.4, 1.0) == pytest.approx(0.8)
    # A region passed a few times has its level there: the same cell beside a patch of 3
    # touches keeps its evidence.
    light = sheet(height=3.0)
    light[hover] = 2.0
    assert layered_evidence(light, N, hover, 0.4, 1.0) == 2.0


def read_map(evidence, factor=0.4, gain=1.75):
    """Touches the map counts per cell after every rule (apply_layer over all of it)."""
    size = N ** 3
    per_touch = -math.log(C)
    model = PathModel(transit_speed=0.2, transit_falloff=2.0, speed_context=0.25,
                      speed_window=0.1, track_gap=0.25, pass_time=0.25, pass_gap=0.5,
                      return_share=0.65, visit_gap=1.0, stay_radius=0.01, step=0.001,
                      max_steps=100, log_odds_per_touch=per_touch, prior=0.0,
                      l_min=-100.0, l_max=100.0)
    dirty = np.flatnonzero(evidence).astype(np.int64)
    log_odds = np.zeros(size)
    apply_layer(evidence, N, factor, gain, model, dirty, len(dirty), np.zeros(size, np.bool_),
                np.empty(size, np.int64), np.zeros(size), np.zeros(size, np.bool_),
                np.zeros((size, 3), np.float32), np.zeros(size), log_odds, np.zeros(size))
    return log_odds / per_touch


def test_a_gap_in_an_explored_surface_counts_as_the_surface_around_it():
    # A patch passed three times, but one cell of it clipped by the passes (0.7 touches,
    # no sheet gain): between two cells of the surface, it is bridged (rule 5).
    evidence = sheet()
    gap = flat(8, 8, 8)
    evidence[gap] = 0.7
    touches = read_map(evidence)
    assert touches[flat(7, 8, 8)] == pytest.approx(3.0 * 1.75)     # the sheet's cells
    assert touches[gap] == pytest.approx(3.0 * 1.75)
    # Under BRIDGE_MIN_TOUCHES (nothing went through it): a hole stays a hole.
    evidence[gap] = 0.5 * BRIDGE_MIN_TOUCHES
    assert read_map(evidence)[gap] < 1.0
    # The layer is never bridged: a cell over the sheet between two others over it, all
    # three weaker than the sheet under them, keeps its own layered evidence.
    evidence = sheet()
    for ix in (7, 8, 9):
        evidence[flat(ix, 8, 9)] = 1.5 if ix != 8 else 0.7
    assert read_map(evidence)[flat(8, 8, 9)] == pytest.approx(0.4 * 0.7 * 0.7 / 3.0)
    # Factor 1 (the layer off): no bridge either.
    evidence = sheet()
    evidence[gap] = 0.7
    assert read_map(evidence, factor=1.0, gain=1.0)[gap] == pytest.approx(0.7)


def test_a_stroke_alone_is_not_bridged():
    # A line of cells is no surface (its plane is any plane through it): a clipped cell of
    # one stroke stays as it is, whatever its neighbours hold.
    evidence = np.zeros(N ** 3)
    for ix in range(2, 14):
        evidence[flat(ix, 8, 8)] = 3.0
    evidence[flat(8, 8, 8)] = 0.7
    assert read_map(evidence)[flat(8, 8, 8)] == pytest.approx(0.7)


def lifted_stroke():
    """A finger stroking a row of cells at 2 cm/s at 30 Hz, then lifting off along +z at
    0.1 m/s (slower than ``transit_speed``: the path model gives it a touch per cell)."""
    rate = 30.0
    t = np.arange(0.0, 2.0, 1.0 / rate)
    slide = np.column_stack([0.01 + 0.02 * t, np.full_like(t, 0.0025), np.full_like(t, 0.0025)])
    lift_times = t[-1] + np.arange(1, 13) / rate
    rise = 0.1 * (lift_times - t[-1])
    lift = np.column_stack([np.full_like(rise, slide[-1, 0]), np.full_like(rise, 0.0025),
                            0.0025 + rise])
    points = np.vstack([slide, lift])
    times = np.concatenate([t, lift_times])
    return points, times


def grid_of(model, calls=1, read_between=False):
    points, times = lifted_stroke()
    # Strokes beside it and past where it lifts off, so that the lift rises from the
    # middle of a sheet.
    t = np.arange(0.0, 2.8, 1.0 / 30.0)
    parts, stamps = [points], [times]
    for k in range(-2, 3):
        parts.append(np.column_stack([0.01 + 0.02 * t, np.full_like(t, 0.0025 + 0.005 * k),
                                      np.full_like(t, 0.0025)]))
        stamps.append(t + 10.0 * (k + 3))
    points, times = np.vstack(parts), np.concatenate(stamps)
    grid = OccupancyGrid(GridSpec(size=0.08, resolution=0.005, centre=(0.04, 0.0, 0.0)), model)
    for part in np.array_split(np.arange(len(times)), calls):
        grid.integrate(points[part], times[part])
        if read_between:
            grid.probabilities()
    grid.flush()
    return grid


def test_the_map_read_is_the_same_however_often_it_is_read():
    model = SensorModel(touch_model='path')
    once = grid_of(model).log_odds.copy()
    often = grid_of(model, calls=37, read_between=True).log_odds
    np.testing.assert_array_equal(once, often)


def test_the_lift_above_the_stroke_loses_its_touch_and_the_stroke_keeps_its_own():
    layered = grid_of(SensorModel(touch_model='path'))
    plain = grid_of(SensorModel(touch_model='path', layer_factor=1.0, sheet_gain=1.0))
    p_layered, p_plain = layered.probabilities(), plain.probabilities()
    # The grid's z cells are 5 mm from -40 mm: the stroked row (z 2.5 mm) is z index 8.
    above = (slice(None), slice(None), 9)                # 5-10 mm above the stroked row
    stroked = (slice(None), slice(None), 8)
    # The lift's cell just above the surface: over a touch without the layer (1.34: a
    # slow pass), under one with it (0.4 of that). The cells higher up the lift are no
    # weaker than their neighbours along it and keep their 1.34 touches, under 0.8.
    assert p_plain[above].max() > 1.0 / (1.0 + C)
    assert p_layered[above].max() < 1.0 / (1.0 + C)
    assert p_layered[:, :, 10:].max() < 0.8
    # The stroked cells are the sheet: untouched by the rule.
    np.testing.assert_array_equal(p_layered[stroked] > 0.8, p_plain[stroked] > 0.8)
    assert (p_layered[stroked] > 0.8).sum() >= 10


def test_a_map_saved_before_the_layer_loads_without_it_and_a_new_one_with_it(tmp_path):
    import json
    import zipfile
    grid = grid_of(SensorModel(touch_model='path'))
    map_io.save_npz(grid, tmp_path / 'new.npz')
    loaded, _ = map_io.load_npz(tmp_path / 'new.npz')
    assert loaded.model.layer_factor == 0.4
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)
    # The same file as an earlier version wrote it: no layer_factor in its metadata.
    with zipfile.ZipFile(tmp_path / 'new.npz') as source, \
            zipfile.ZipFile(tmp_path / 'old.npz', 'w') as target:
        for item in source.infolist():
            data = source.read(item)
            if item.filename == 'metadata.npy':
                array = np.load(tmp_path / 'new.npz')['metadata']
                metadata = json.loads(bytes(array).decode())
                for key in ('layer_factor', 'sheet_gain', 'transit_falloff'):
                    del metadata[key]
                from io import BytesIO
                buffer = BytesIO()
                np.save(buffer, np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8))
                data = buffer.getvalue()
            target.writestr(item, data)
    old, _ = map_io.load_npz(tmp_path / 'old.npz')
    assert old.model.layer_factor == 1.0 and old.model.sheet_gain == 1.0


def test_a_layer_factor_outside_0_1_is_refused():
    with pytest.raises(ValueError, match='layer_factor must be in'):
        SensorModel(layer_factor=1.5)
    with pytest.raises(ValueError, match='sheet_gain must be in'):
        SensorModel(sheet_gain=0.5)
    assert math.isclose(SensorModel().layer_factor, 0.4)


def test_a_map_resumed_from_its_file_goes_on_as_if_never_saved(tmp_path):
    # The first half of a session, saved and loaded, then the second half: the map is the
    # whole session's (the file keeps the evidence before the layer: resumed from the
    # layered log-odds instead, the layer would apply twice around the new touches).
    from inhand_mapping.map_products import resume_from
    model = SensorModel(touch_model='path')
    spec = GridSpec(size=0.08, resolution=0.005, centre=(0.04, 0.0, 0.0))
    points, times = lifted_stroke()
    t = np.arange(0.0, 2.8, 1.0 / 30.0)
    later = np.column_stack([0.01 + 0.02 * t, np.full_like(t, 0.0075), np.full_like(t, 0.0025)])
    whole = OccupancyGrid(spec, model)
    for chunk, stamps in ((points, times), (later, t + 20.0)):
        whole.integrate(chunk, stamps)
        whole.flush()
    first = OccupancyGrid(spec, model)
    first.integrate(points, times)
    first.flush()
    map_io.save_npz(first, tmp_path / 'half.npz')
    resumed = OccupancyGrid(spec, model)
    resume_from(resumed, tmp_path / 'half.npz')
    resumed.integrate(later, t + 20.0)
    resumed.flush()
    np.testing.assert_array_equal(resumed.log_odds, whole.log_odds)
    np.testing.assert_array_equal(resumed.touch_evidence, whole.touch_evidence)
