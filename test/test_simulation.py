"""The simulator (inhand_sim): object models, exploration strokes, sessions, bags, maps."""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from inhand_common.ground_truth import TRUTH_KEYS, load_truth, truth_path
from inhand_common.rotations import quaternion_conjugate, quaternion_multiply, rotate_vectors
from inhand_mapping.map_io import load_npz
from inhand_sim.exploration import FINGERS, SAMPLE_KINDS, ExplorationSettings, TrackerNoise, explore
from inhand_sim.objects import OBJECT_NAMES, get_object
from inhand_sim.session import SessionSettings, simulate, write_session
from ros_helpers import WORKSPACE, executable_path

FAST = ExplorationSettings(pool_size=150)
TOPICS = {f'/polhemus/{name}/pose' for name in FINGERS}


def nearest_distance(points, cloud, chunk=64):
    """Distance from each point to the nearest point of ``cloud`` (brute force)."""
    out = np.empty(len(points))
    c2 = np.sum(cloud ** 2, axis=1)
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        d2 = np.sum(p ** 2, axis=1)[:, None] - 2 * p @ cloud.T + c2[None]
        out[start:start + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def to_object_frame(points, truth, index=0):
    return rotate_vectors(quaternion_conjugate(truth['object_quaternions'][index]),
                          points - truth['object_positions'][index])


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope='module', params=OBJECT_NAMES)
def model(request):
    return get_object(request.param)


@pytest.fixture(scope='module')
def static_session():
    return simulate(SessionSettings(object_name='cat', static=True, rate=240.0, duration=20.0,
                                    seed=11, exploration=FAST))


@pytest.fixture(scope='module')
def moving_session():
    return simulate(SessionSettings(object_name='cat', static=False, rate=240.0, duration=20.0,
                                    seed=12, second_object_sensor=True, exploration=FAST))


@pytest.fixture(scope='module')
def written(static_session, moving_session, tmp_path_factory):
    folder = tmp_path_factory.mktemp('bags')
    return {'static': write_session(static_session, folder / 'cat_static')[0],
            'moving': write_session(moving_session, folder / 'cat_moving')[0]}


# --- objects ------------------------------------------------------------------------------

def test_sampled_surface_points_are_on_the_surface(model):
    points, normals = model.sample_surface(20_000, np.random.default_rng(0))
    assert points.shape == (20_000, 3) and normals.shape == (20_000, 3)
    assert np.abs(model.sdf(points)).max() < 1e-6
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.min(np.sum(model.normals(points) * normals, axis=1)) > 0.999
    lo, hi = model.bounds
    assert np.all(points >= lo - 1e-9) and np.all(points <= hi + 1e-9)
    # the bounding box is tight: samples reach within 2 mm of every face
    assert np.all(points.min(axis=0) - lo < 0.002) and np.all(hi - points.max(axis=0) < 0.002)


def test_sdf_is_the_distance_or_a_lower_bound_of_it(model):
    rng = np.random.default_rng(1)
    surface, _ = model.sample_surface(60_000, rng)
    lo, hi = model.bounds
    queries = lo - 0.02 + rng.random((300, 3)) * (hi - lo + 0.04)
    sdf = model.sdf(queries)
    nearest = nearest_distance(queries, surface)
    # never more than the true distance (the nearest sample is at most ~1.5 mm beyond it)
    assert np.all(np.abs(sdf) <= nearest + 1e-9)
    if model.name in ('bottle', 'mug'):   # exact primitives only: exact outside
        outside = sdf > 0
        assert np.all(nearest[outside] - sdf[outside] < 0.0015)


def test_known_inside_and_outside_points():
    cat, bottle, mug = (get_object(n) for n in ('cat', 'bottle', 'mug'))
    cm = 0.01
    # cat (origin on the belly): inside the body, the head; above the head and between the legs outside
    assert cat.sdf(np.array([[0.0, 0.0, 2.0 * cm], [4.4 * cm, 0.0, 5.0 * cm]])).max() < 0
    assert cat.sdf(np.array([[4.4 * cm, 0.0, 12 * cm], [0.0, 0.0, -1.5 * cm]])).min() > 0
    # bottle (origin on the body's side, 14 cm up): on its axis inside, far above the lip exact
    axis = np.array([-3.75 * cm, 0.0, 0.0])
    assert bottle.sdf(axis[None])[0] == pytest.approx(-3.75 * cm)
    assert bottle.sdf((axis + [0, 0, 26 * cm])[None])[0] == pytest.approx(0.1)
    # mug (origin under the bottom): the cavity is empty, the wall, bottom and handle are solid
    assert mug.sdf(np.array([[0.0, 0.0, 5 * cm]]))[0] == pytest.approx(3.6 * cm)
    assert mug.sdf(np.array([[3.8 * cm, 0.0, 5 * cm], [0.0, 0.0, 0.3 * cm],
                             [4.0 * cm + math.hypot(0.3, 2.6) * cm, 0.0, 4.75 * cm]])).max() < 0
    assert mug.sdf(np.array([[5.5 * cm, 0.0, 4.75 * cm]]))[0] > 0   # inside the handle's loop


def test_sizes_match_the_specification():
    def close(value, want):
        return abs(value - want) <= 0.2 * want
    cat = get_object('cat').size
    assert close(cat[0], 0.12) and close(cat[1], 0.06) and close(cat[2], 0.10)
    bottle = get_object('bottle').size
    assert close(bottle[2], 0.30) and close(bottle[0], 0.075) and close(bottle[1], 0.075)
    mug = get_object('mug').size
    assert close(mug[1], 0.08) and close(mug[2], 0.095)
    assert mug[0] - mug[1] > 0.025   # the handle sticks out


def test_projection_lands_on_the_surface(model):
    rng = np.random.default_rng(2)
    points, normals = model.sample_surface(2000, rng)
    offset = rng.uniform(-0.003, 0.01, (2000, 1))
    projected = model.project_to_surface(points + offset * normals)
    assert np.abs(model.sdf(projected)).max() < 1e-9
    assert np.median(np.linalg.norm(projected - points, axis=1)) < 1e-4


def test_sampling_is_uniform_by_area():
    bottle = get_object('bottle')
    points, _ = bottle.sample_surface(100_000, np.random.default_rng(3))
    axis = np.array([-0.0375, 0.0])
    rho = np.linalg.norm(points[:, :2] - axis, axis=1)
    z = points[:, 2] + 0.14   # height above the bottom
    lateral = (np.abs(rho - 0.0375) < 1e-9) & (z > 0.01) & (z < 0.19)
    expected = 2 * math.pi * 0.0375 * 0.18 / bottle.surface_area()
    assert lateral.mean() == pytest.approx(expected, rel=0.03)
    # and evenly along the side
    counts = np.histogram(z[lateral], bins=9, range=(0.01, 0.19))[0]
    assert counts.std() / counts.mean() < 0.05


def test_the_cat_fits_both_workspaces(static_session):
    cat = get_object('cat')
    surface = static_session.truth['surface_points']
    assert np.abs(surface).max() < 0.175 - 0.01             # tracked: cube around the sensor
    tracker = static_session.truth['object_positions'][0] + rotate_vectors(
        static_session.truth['object_quaternions'][0], surface)
    assert np.abs(tracker - [0.25, 0.0, 0.05]).max() < 0.175 - 0.01   # static config
    centre = tracker.min(axis=0) / 2 + tracker.max(axis=0) / 2
    assert np.allclose(centre, [0.25, 0.0, 0.05], atol=2e-4)   # samples: box within 0.2 mm
    # upright on the table: the object's up is the tracker's up (-z)
    up = rotate_vectors(static_session.truth['object_quaternions'][0], [0.0, 0.0, 1.0])
    assert np.allclose(up, [0.0, 0.0, -1.0])
    assert cat.table_z == pytest.approx(cat.bounds[0, 2])


# --- exploration --------------------------------------------------------------------------

def test_contacts_lie_on_the_surface_and_strays_off_it(static_session, moving_session):
    for session in (static_session, moving_session):
        truth, obj = session.truth, session.object
        assert np.abs(obj.sdf(truth['contacts'])).max() < 1e-4
        # lifts are continuous: strays at every height, never closer than min_height
        assert obj.sdf(truth['stray_points']).min() >= 0.9 * FAST.min_height
        assert len(truth['contacts']) + len(truth['stray_points']) == 3 * len(truth['object_times'])
        assert 0.6 < len(truth['contacts']) / (3 * len(truth['object_times'])) < 0.95
    # lifts between frames (the sessions made before): every stray well off the surface
    cat = static_session.object
    jumps = explore(cat, 8.0, 240.0, np.random.default_rng(8), replace(FAST, continuous_lifts=False))
    assert cat.sdf(jumps.positions[~jumps.contact]).min() >= 0.005


def test_strokes_are_continuous_paths_at_a_few_cm_per_second(static_session):
    ex = static_session.exploration
    st = FAST
    v_max = st.speed_range[1] * (1 + st.speed_variation)
    rate = static_session.settings.rate
    lengths = []
    for f in range(len(FINGERS)):
        p, c, sid = ex.positions[f], ex.contact[f], ex.stroke[f]
        same = c[1:] & c[:-1] & (sid[1:] == sid[:-1]) & (sid[1:] >= 0)
        steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
        assert steps[same].max() < 1.5 * v_max / rate + 0.001
        for s in np.unique(sid[sid >= 0]):
            lengths.append(steps[same & (sid[1:] == s)].sum())
        assert len(np.unique(sid[sid >= 0])) >= 3   # several strokes per finger in 20 s
    # strokes slide over the surface (not isolated touches): centimetres long, typically
    assert np.median(lengths) > 0.02
    # median sliding speed a few cm/s
    speeds = []
    for f in range(len(FINGERS)):
        moving = (ex.kind[f, 1:] == SAMPLE_KINDS.index('stroke')) & (ex.stroke[f, 1:] == ex.stroke[f, :-1])
        steps = np.linalg.norm(np.diff(ex.positions[f], axis=0), axis=1)[moving]
        speeds.append(np.median(steps[steps > 0]) * rate)
    assert 0.01 < np.median(speeds) < 0.06


def test_involuntary_lifts_and_transits_are_off_surface_moves(static_session):
    ex, obj = static_session.exploration, static_session.object
    kinds = {name: ex.kind == i for i, name in enumerate(SAMPLE_KINDS)}
    assert kinds['lift'].any() and kinds['transit'].any()
    lift_height = obj.sdf(ex.positions[kinds['lift']])
    assert 0.9 * FAST.min_height <= lift_height.min() < 0.001 and 0.008 < lift_height.max() < 0.06
    assert not ex.contact[kinds['lift'] | kinds['transit']].any()
    assert ex.contact[kinds['stroke'] | kinds['dwell']].all()


def test_the_held_region_gets_no_contacts(static_session, moving_session):
    obj = static_session.object
    contacts = static_session.truth['contacts']
    assert not obj.static_grip.contains(contacts).any()
    # the held region is really on the surface (a hole in the map, not empty air)
    surface = static_session.truth['surface_points']
    assert obj.static_grip.contains(surface).mean() > 0.02
    # no contact below the table's reach either
    assert contacts[:, 2].min() > obj.table_z + 0.003
    # moving: each grip's region is untouched while that grip holds the object
    ex = moving_session.exploration
    for g, region in enumerate(ex.held_regions):
        during = ex.contact & (ex.grip == g)[None, :]
        assert not region.contains(ex.positions[during]).any()


def test_regrasp_turns_the_object_while_the_fingers_are_off(moving_session):
    truth, ex = moving_session.truth, moving_session.exploration
    assert len(moving_session.regrasp_windows) == 1
    wa, wb = moving_session.regrasp_windows[0]
    t = ex.times
    inside = (t > wa + 0.2) & (t < wb - 0.2)
    assert not ex.contact[:, inside].any()
    q = truth['object_quaternions']
    before, after = q[np.searchsorted(t, wa)], q[np.searchsorted(t, wb)]
    dq = quaternion_multiply(quaternion_conjugate(before), after)
    angle = math.degrees(2 * math.acos(min(1.0, abs(dq[3]))))
    assert 50 < angle < 140   # 60-120 degrees, plus or minus the sway
    # exploration resumes on the object after the re-grasp
    assert ex.contact[:, t > wb + 1.5].any()
    # and the object moved during the whole session (drift)
    assert np.ptp(truth['object_positions'], axis=0).max() > 0.005


def test_tracker_noise_statistics():
    rng = np.random.default_rng(4)
    offsets = TrackerNoise(0.001, 0.002, (0.01, 0.02)).sample((200_000,), rng)
    norms = np.linalg.norm(offsets, axis=1)
    outliers = norms > 0.008
    assert 0.0015 < outliers.mean() < 0.0025
    assert np.std(offsets[~outliers], axis=0) == pytest.approx([0.001] * 3, rel=0.02)
    assert norms.max() < 0.021 + 0.006


def test_exploration_is_deterministic():
    cat = get_object('cat')
    a = explore(cat, 6.0, 15.0, np.random.default_rng(5), FAST)
    b = explore(cat, 6.0, 15.0, np.random.default_rng(5), FAST)
    c = explore(cat, 6.0, 15.0, np.random.default_rng(6), FAST)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.contact, b.contact)
    assert not np.array_equal(a.positions, c.positions)


# --- sessions, files ----------------------------------------------------------------------

def test_bag_has_exactly_the_driver_topics_one_stamp_per_frame(written, static_session,
                                                                 moving_session):
    from rosbags.highlevel import AnyReader

    from inhand_mapping.pose_cdr import decode_pose_stamped
    for key, session in (('static', static_session), ('moving', moving_session)):
        expected = set(TOPICS) if key == 'static' else TOPICS | {'/polhemus/object/pose',
                                                                   '/polhemus/object2/pose'}
        with AnyReader([written[key]]) as reader:
            assert {c.topic for c in reader.connections} == expected
            assert {c.msgtype for c in reader.connections} == {'geometry_msgs/msg/PoseStamped'}
            stamps, frame_ids, count = {}, set(), 0
            for connection, log_time, raw in reader.messages():
                sec, nsec, frame_id, pose = decode_pose_stamped(raw)
                stamp = sec * 1_000_000_000 + nsec
                assert stamp == log_time
                frame_ids.add(frame_id)
                stamps.setdefault(stamp, set()).add(connection.topic)
                count += 1
        n_frames = len(session.stamps_ns)
        assert frame_ids == {'polhemus_source'}
        assert count == n_frames * len(expected)
        assert len(stamps) == n_frames and all(v == expected for v in stamps.values())
        assert min(stamps) == 1_700_000_000 * 10 ** 9
        gaps = np.diff(sorted(stamps))
        assert np.all(np.abs(gaps - 1e9 / session.settings.rate) <= 1)


def test_bag_poses_are_the_truth_plus_noise(moving_session):
    truth, s = moving_session.truth, moving_session
    obj_p, obj_q = truth['object_positions'], truth['object_quaternions']
    # fingertips: the object pose applied to the object-frame positions, plus ~1 mm noise
    for f in range(3):
        true_trk = obj_p + rotate_vectors(obj_q, s.exploration.positions[f])
        error = np.linalg.norm(s.poses[f, :, :3] - true_trk, axis=1)
        assert 0.0012 < np.median(error) < 0.002   # sqrt(3) x 1 mm, roughly
    # the object sensor: the object frame itself, with 0.5 mm / 0.1 degree noise
    obj = s.poses[s.stations.index('object')]
    assert np.median(np.linalg.norm(obj[:, :3] - obj_p, axis=1)) < 0.0012
    dq = quaternion_multiply(quaternion_conjugate(obj_q), obj[:, 3:])
    assert np.degrees(2 * np.arccos(np.minimum(1, np.abs(dq[:, 3])))).max() < 1.0
    # the second sensor is rigidly attached: constant offset in the object frame
    second = s.poses[s.stations.index('object2')]
    local = rotate_vectors(quaternion_conjugate(obj_q), second[:, :3] - obj_p)
    assert np.abs(local - np.asarray(s.object.second_sensor[0])).max() < 0.005


def test_truth_sidecar_format(written, static_session):
    path = truth_path(written['static'])
    assert path == written['static'].parent / 'cat_static.truth.npz'
    with np.load(path, allow_pickle=False) as data:
        assert set(data.files) == set(TRUTH_KEYS)
        arrays = {k: data[k] for k in data.files}
    for key in ('object_name', 'static', 'rate', 'seed'):
        assert arrays[key].shape == ()
    assert arrays['object_name'].item() == 'cat' and arrays['static'].item() is True
    assert arrays['rate'].dtype == np.float64 and arrays['rate'].item() == 240.0
    assert np.issubdtype(arrays['seed'].dtype, np.integer) and arrays['seed'].item() == 11
    settings = json.loads(arrays['settings_json'].tobytes().decode('utf-8'))
    assert settings['object_name'] == 'cat' and settings['exploration']['pool_size'] == 150
    assert arrays['surface_points'].shape[0] >= 100_000
    for key, width in (('surface_points', 3), ('surface_normals', 3)):
        assert arrays[key].dtype == np.float32 and arrays[key].shape[1] == width
    for key, width in (('contacts', 3), ('stray_points', 3), ('object_positions', 3),
                       ('object_quaternions', 4)):
        assert arrays[key].dtype == np.float64 and arrays[key].shape[1] == width
    assert len(arrays['contacts']) == len(arrays['contact_times'])
    assert len(arrays['stray_points']) == len(arrays['stray_times'])
    assert np.all(np.diff(arrays['contact_times']) >= 0)
    times = arrays['object_times']
    assert len(times) == len(arrays['object_positions']) == 20 * 240
    assert times[0] == 1_700_000_000.0
    assert np.all(arrays['object_positions'] == arrays['object_positions'][0])   # static
    assert set(np.round(arrays['contact_times'], 6)) <= set(np.round(times, 6))
    truth = load_truth(path)
    assert truth.settings['seed'] == 11 and truth.object_name == 'cat'


def test_same_seed_same_bytes_other_seed_other_data(tmp_path):
    def run(seed, name):
        settings = SessionSettings(object_name='mug', static=False, rate=15.0, duration=12.0,
                                   seed=seed, surface_samples=100_000, exploration=FAST)
        session = simulate(settings)
        bag, truth = write_session(session, tmp_path / name / 'bag')
        return session, bag, truth
    a, bag_a, truth_a = run(21, 'a')
    b, bag_b, truth_b = run(21, 'b')
    c, _, _ = run(22, 'c')
    for key in TRUTH_KEYS:
        assert np.array_equal(a.truth[key], b.truth[key])
    assert sha(bag_a / 'bag.mcap') == sha(bag_b / 'bag.mcap')
    assert sha(bag_a / 'metadata.yaml') == sha(bag_b / 'metadata.yaml')
    assert sha(truth_a) == sha(truth_b)
    assert not np.array_equal(a.poses, c.poses)
    assert not np.array_equal(a.truth['contacts'][:100], c.truth['contacts'][:100])


def test_write_session_refuses_to_overwrite_and_replaces_with_force(tmp_path):
    session = simulate(SessionSettings(object_name='cat', static=True, rate=15.0, duration=4.0,
                                       seed=1, surface_samples=100_000, exploration=FAST))
    bag, truth = write_session(session, tmp_path / 'x')
    with pytest.raises(FileExistsError):
        write_session(session, tmp_path / 'x')
    (bag / 'stale').write_text('old')
    write_session(session, tmp_path / 'x', force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['x', 'x.truth.npz']   # no leftovers
    assert not (bag / 'stale').exists()


def test_command_line(tmp_path):
    exe = executable_path('simulate_session')
    out = tmp_path / 'bags' / 'mug_moving'
    args = [exe, '--object', 'mug', '--moving', '--no-regrasp', '--rate', '15', '--duration', '5',
            '--seed', '3', '--output', str(out)]
    result = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert 'wrote' in result.stdout and '300 messages' in result.stdout
    assert 'contacts' in result.stdout and 'strays' in result.stdout
    assert (out / 'metadata.yaml').exists() and truth_path(out).exists()
    again = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and '--force' in again.stderr
    for bad, says in ((['--rate', '16'], '15'), (['--duration', '-1'], 'duration'),
                      (['--object', 'dog'], 'dog'), (['--static', '--regrasp'], '--moving')):
        argv = [exe, '--object', 'cat', '--static', '--rate', '15', '--duration', '2',
                '--seed', '1', '--output', str(tmp_path / 'other')]
        for i in range(0, len(bad), 2):
            if bad[i] in argv and bad[i] not in ('--static',):
                argv[argv.index(bad[i]) + 1] = bad[i + 1]
            else:
                argv += bad[i:i + 2]
        result = subprocess.run(argv, capture_output=True, text=True, timeout=60)
        assert result.returncode == 2 and says in result.stderr, (bad, result.stderr)
    assert not (tmp_path / 'other').exists()


# --- maps of simulated sessions -----------------------------------------------------------

def build(bag: Path, config: str, out: Path):
    result = subprocess.run([executable_path('build_map'), str(bag), '--config',
                             str(WORKSPACE / 'config' / config), '--output-dir', str(out),
                             '--name', bag.name, '--quiet'],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    grid, _ = load_npz(out / f'{bag.name}.npz')
    return grid.spec.cell_centres(np.argwhere(grid.probabilities() > 0.8))


def test_static_map_lies_on_the_true_surface(written, static_session, tmp_path):
    cells = build(written['static'], 'mapping_static.yaml', tmp_path)   # tracker frame
    truth = static_session.truth
    local = to_object_frame(cells, truth)
    distance = nearest_distance(local, truth['surface_points'])
    # 20 s: only the places touched twice (two fingers, or again after the visit gap)
    assert len(cells) > 15
    assert np.mean(distance <= 0.005) > 0.95
    assert np.median(distance) < 0.003


def test_tracked_map_lies_on_the_true_surface(written, moving_session, tmp_path):
    cells = build(written['moving'], 'mapping.yaml', tmp_path)   # object frame
    truth = moving_session.truth
    distance = nearest_distance(cells, truth['surface_points'])
    # 20 s: only the places touched twice (two fingers, or again after the visit gap)
    assert len(cells) > 15
    assert np.mean(distance <= 0.005) > 0.95
    assert np.median(distance) < 0.003


def test_the_camera_viewpoint_is_a_setting_and_the_default_keeps_old_sessions_bytes():
    import json
    import math

    from inhand_sim.session import SessionSettings
    from inhand_sim.stereo_rig import DEFAULT_VIEW_DIRECTION
    default = SessionSettings()
    assert default.camera_direction == DEFAULT_VIEW_DIRECTION
    assert 'camera_azimuth_deg' not in json.loads(default.to_json())
    above = SessionSettings(camera_azimuth_deg=0.0, camera_elevation_deg=60.0)
    x, y, z = above.camera_direction
    # tracker z points down: 60 degrees above the horizontal, towards +x
    assert (x, y, z) == pytest.approx((0.5, 0.0, -math.sqrt(3) / 2))
    assert json.loads(above.to_json())['camera_elevation_deg'] == 60.0
    # only the azimuth given: the default rig's elevation
    side = SessionSettings(camera_azimuth_deg=90.0)
    default_elevation = math.asin(0.55 / math.dist((0, 0, 0), DEFAULT_VIEW_DIRECTION))
    assert side.camera_direction[2] == pytest.approx(-math.sin(default_elevation))
    with pytest.raises(ValueError, match='camera_elevation_deg'):
        SessionSettings(camera_elevation_deg=95.0)


def test_several_stereo_pairs_the_first_before_the_exploration(tmp_path):
    from inhand_common.bag_source import BagSource
    settings = SessionSettings(object_name='cat', static=False, rate=15.0, duration=4.0,
                               seed=9, stereo=True, stereo_shots=3)
    assert json.loads(settings.to_json())['stereo_shots'] == 3
    assert 'stereo_shots' not in json.loads(SessionSettings(stereo=True).to_json())
    session = simulate(settings)
    assert [frame for frame, _ in session.stereo_shots] == [0, 20, 40]
    assert session.stereo_shot is session.stereo_shots[0][1]
    # the held object turned between the shots: each pair shows it otherwise
    first, second = (shot.left for _, shot in session.stereo_shots[:2])
    assert np.mean(np.any(first != second, axis=2)) > 0.01
    bag, _ = write_session(session, tmp_path / 'three')
    stamps: dict[str, list[int]] = {}
    with BagSource(bag) as source:
        for topic, stamp, _ in source.messages({'stereo/left/image_raw',
                                                'stereo/right/camera_info'}):
            stamps.setdefault(topic, []).append(stamp)
    expected = [int(session.stamps_ns[k]) for k in (0, 20, 40)]
    assert stamps == {'stereo/left/image_raw': expected, 'stereo/right/camera_info': expected}
    assert session.message_count == 4 * 60 + 4 * 3
    with pytest.raises(ValueError, match='stereo_shots'):
        SessionSettings(stereo=True, stereo_shots=0)
