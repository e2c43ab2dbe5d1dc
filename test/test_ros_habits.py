"""The habits of a ROS user on a bench: sim time, frames, diagnostics.

The pure parts (health bookkeeping, the mapping nodes' reports, frame names) are tested
directly; the nodes over real DDS with a real ``bag_replay`` (with and without ``--clock``)
and a real pose publisher.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from inhand_common.frame_names import FrameNames
from inhand_common.health import ERROR, OK, WARN, Health, IntervalCounts, Problems, SimClockWatch, WarningLog
from inhand_common.parameters import ParameterError, validate
from inhand_mapping.map_io import load_npz
from inhand_mapping.mapping_config import REGISTRATION_PARAMETERS, RegistrationConfig
from inhand_mapping.node_health import (
    OccupancyActivity,
    OccupancyHealth,
    RegistrationActivity,
    RegistrationHealth,
)
from inhand_mapping.occupancy import IntegrationCounts
from inhand_mapping.registration import RegistrationStats
from polling import wait_until
from pose_sessions import sphere_session, write_pose_bag
from ros_helpers import (
    WORKSPACE,
    BackgroundNode,
    CloudCounter,
    PosePublisher,
    call_trigger,
    executable_path,
    running,
)

# -- health bookkeeping ------------------------------------------------------------------


def test_problems_give_the_worst_level_and_every_message():
    problems = Problems()
    assert problems.health('fine', {'a': 1}) == Health(OK, 'fine', {'a': '1'})
    problems.add(WARN, 'slow', 'slow stream')
    problems.add(ERROR, 'gone', 'port gone')
    health = problems.health('fine', {})
    assert health.level == ERROR
    assert health.message == 'port gone; slow stream'
    assert health.reasons == ('gone', 'slow')


def test_interval_counts_give_increases_since_the_last_step():
    counts = IntervalCounts(now=10.0)
    assert counts.step(11.0, {'frames': 240}) == (1.0, {'frames': 240})
    elapsed, new = counts.step(13.0, {'frames': 480, 'drops': 2})
    assert elapsed == 2.0 and new == {'frames': 240, 'drops': 2}


def test_warning_log_says_new_problems_at_once_and_repeats_slowly():
    log = WarningLog(repeat=10.0)
    warn = Health(WARN, '3 dropped', reasons=('dropped',))
    assert log.line(0.0, warn) == (WARN, '3 dropped')
    assert log.line(1.0, Health(WARN, '5 dropped', reasons=('dropped',))) is None
    # something new goes wrong: said at once
    both = Health(WARN, '1 dropped; 2 resyncs', reasons=('dropped', 'resyncs'))
    assert log.line(2.0, both) == (WARN, '1 dropped; 2 resyncs')
    assert log.line(12.5, both) == (WARN, '1 dropped; 2 resyncs')      # still there
    assert log.line(13.0, Health(OK, 'streaming')) == (OK, 'back to normal: streaming')
    assert log.line(14.0, Health(OK, 'streaming')) is None


def test_sim_clock_watch_counts_only_while_data_arrives_and_time_stands():
    watch = SimClockWatch(wall_now=0.0)
    assert watch.stalled(1.0, 0, data_arrived=True) == 0.0     # first look
    assert watch.stalled(2.0, 0, data_arrived=True) == 1.0
    assert watch.stalled(4.0, 0, data_arrived=True) == 3.0
    assert watch.stalled(5.0, 0, data_arrived=False) == 0.0    # no data: nothing to say
    assert watch.stalled(6.0, 0, data_arrived=True) == 1.0
    assert watch.stalled(7.0, 5, data_arrived=True) == 0.0     # /clock moved


# -- the mapping nodes' reports ----------------------------------------------------------


def test_registration_report_warns_of_a_silent_object_sensor_and_drops():
    health = RegistrationHealth(0.0, 'polhemus/object/pose', max_gap=0.05, max_pending=2.0)
    stats = RegistrationStats(received=720, registered=700, object_poses=240, pending=20)
    problems = Problems()
    message, values = health.report(1.0, stats, RegistrationActivity(700, 0, 1), problems)
    assert problems.health(message, values).level == OK
    assert values['state'] == 'registering'
    assert values['fingertips_in_hz'] == '720.0' and values['points_out_hz'] == '700.0'
    # the object sensor goes quiet: fingertips keep coming, then are dropped
    stats = RegistrationStats(received=1440, registered=700, dropped_gap=500, pending=240,
                              object_poses=240)
    problems = Problems()
    message, values = health.report(2.0, stats, RegistrationActivity(700, 0, 1), problems)
    result = problems.health(message, values)
    assert result.level == WARN
    assert set(result.reasons) == {'object_silent', 'object_gap'}
    assert 'polhemus/object/pose silent while 720 fingertip positions arrived' in result.message
    assert '500 fingertip positions dropped' in result.message
    assert values['dropped_gap'] == 500


def test_registration_report_before_any_object_pose_and_to_nobody():
    health = RegistrationHealth(0.0, 'polhemus/object/pose', 0.05, 2.0)
    problems = Problems()
    _, values = health.report(1.0, RegistrationStats(received=100, dropped_before_object=100),
                              RegistrationActivity(0, 0, 0), problems)
    assert values['state'] == 'waiting for polhemus/object/pose'
    assert {'object_silent', 'before_object'} <= set(problems.health('', {}).reasons)
    static = RegistrationHealth(0.0, None, 0.05, 2.0)
    problems = Problems()
    _, values = static.report(1.0, RegistrationStats(received=10, registered=10),
                              RegistrationActivity(10, 10, 0), problems)
    assert values['mode'] == 'static'
    assert problems.health('', {}).reasons == ('no_subscriber',)


def test_occupancy_report_warns_of_points_outside_the_workspace_only_when_the_map_meets_it():
    """Fingertips away from the object (lifts, the carry, a re-grasp) leave the workspace in
    every session: not a problem while the occupied cells keep clear of its faces; a map
    whose occupied cells reach them may be cut off, and that is warned."""
    health = OccupancyHealth(0.0, '0.35 m cube centred at [0, 0, 0]')
    problems = Problems()
    _, values = health.report(1.0, IntegrationCounts(), OccupancyActivity(publishers=0),
                              problems)
    assert values['state'] == 'waiting for registration/points'
    assert problems.health('', {}).level == OK
    for now, on_faces in ((2.0, 0), (3.0, 7)):
        problems = Problems()
        message, values = health.report(
            now, IntegrationCounts(integrated=int(90 * (now - 1)), outside=int(10 * (now - 1))),
            OccupancyActivity(received=int(100 * (now - 1)), messages=2, publishers=1,
                              touched_cells=40, occupied_cells=12,
                              occupied_on_faces=on_faces), problems)
        result = problems.health(message, values)
        assert values['state'] == 'mapping' and values['occupied_cells'] == 12
        assert message == 'mapping: 100.0 points/s in, 12 occupied of 40 touched cells'
        if not on_faces:
            assert result.level == OK and values['outside'] == 10
            continue
        assert result.level == WARN and result.reasons == ('outside',)
        assert '10 of 100 points fell outside the workspace' in result.message
        assert '7 occupied cells lie on its faces' in result.message


def test_the_grid_knows_its_outermost_layer_of_cells():
    from inhand_mapping.occupancy import GridSpec
    spec = GridSpec(0.1, 0.01, (0.0, 0.0, 0.0))      # 10 cells a side, from -0.05 to 0.05
    points = np.array([[0.0, 0.0, 0.0], [-0.049, 0.0, 0.0], [0.0, 0.0, 0.045],
                       [0.0, 0.035, 0.0], [0.2, 0.0, 0.0]])
    assert spec.on_faces(points).tolist() == [False, True, True, False, False]


# -- frame names ---------------------------------------------------------------------------


def test_frame_names_take_a_prefix_and_refuse_bad_names():
    values = validate(REGISTRATION_PARAMETERS, {'frame_prefix': 'left_hand/'})
    frames = RegistrationConfig.from_parameters(values).frames
    assert frames.tracker_frame == 'left_hand/polhemus_source'
    assert frames.map_frame == 'left_hand/object'
    assert frames.fingertip_frame('thumb') == 'left_hand/fingertip_thumb'
    assert frames.object_centric_frame == 'left_hand/object_centric'
    assert FrameNames().camera_frame == 'stereo_left_optical'
    with pytest.raises(ParameterError, match=r"'map_frame' = '/object' is not a valid frame"):
        RegistrationConfig.from_parameters(
            validate(REGISTRATION_PARAMETERS, {'map_frame': '/object'}))
    with pytest.raises(ParameterError, match="with frame_prefix 'a//'"):
        RegistrationConfig.from_parameters(
            validate(REGISTRATION_PARAMETERS, {'frame_prefix': 'a//'}))


def test_the_driver_takes_a_frame_id_with_a_slash():
    from polhemus_liberty.driver_config import DRIVER_PARAMETERS, DriverConfig
    config = DriverConfig.from_parameters(
        validate(DRIVER_PARAMETERS, {'frame_id': 'left_hand/polhemus_source'}))
    assert config.frame_id == 'left_hand/polhemus_source'
    assert DriverConfig.from_parameters(
        validate(DRIVER_PARAMETERS, {'frame_id': '/polhemus_source'})).frame_id == \
        'polhemus_source'
    with pytest.raises(ParameterError, match='frame_id'):
        DriverConfig.from_parameters(validate(DRIVER_PARAMETERS, {'frame_id': 'a b'}))


# -- over DDS ------------------------------------------------------------------------------


class GraphListener(BackgroundNode):
    """Keeps every diagnostics status and every transform the graph publishes."""

    def __init__(self):
        super().__init__('test_graph_listener')
        self.statuses: list = []
        self.transforms: list[TransformStamped] = []
        self.static: list[TransformStamped] = []
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self._on_diagnostics, 50)
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(TransformStamped, 'transforms', self._keep(self.transforms),
                                      reliable)
        self.node.create_subscription(TransformStamped, 'transforms_static',
                                      self._keep(self.static), latched)
        self.start()

    def _keep(self, into: list):
        def keep(msg):
            with self.lock:
                into.append(msg)
        return keep

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self.lock:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                self.statuses.append((msg.header.stamp, status.name, status.level[0],
                                      status.message, values))

    def of(self, node_name: str) -> list:
        with self.lock:
            return [s for s in self.statuses if s[1].endswith(node_name)]

    def wait_for(self, predicate, timeout: float, what: str) -> None:
        wait_until(predicate, timeout, what, period=0.1)


def test_sim_time_with_and_without_clock(tmp_path):
    """With use_sim_time and no /clock the map used to stay empty while save said success.
    The nodes map on their steady clocks and say that nothing publishes /clock; with
    ``bag_replay --clock`` they live in the bag's time (their diagnostics and frames
    carry it)."""
    frames, _ = sphere_session(seconds=5.0, rate=60.0, surface_points=12, moving=True)
    bag = write_pose_bag(tmp_path / 'session', frames)
    bag_start, bag_end = frames[0][0], frames[-1][0]
    config = str(WORKSPACE / 'config' / 'mapping.yaml')
    ros = ['--ros-args', '--params-file', config, '-p', 'use_sim_time:=true']
    everything = str(3 * len(frames))
    for clock in (False, True):
        name = 'with_clock' if clock else 'without_clock'
        listener = watching = GraphListener()
        try:
            with running(['registration_node', *ros]) as registration, \
                    running(['occupancy_node', *ros, '-p', f'output_dir:={tmp_path}',
                             '-p', f'map_name:={name}']) as occupancy:
                replay = subprocess.run(
                    [executable_path('bag_replay'), str(bag), '--quiet',
                     *(['--clock', '50'] if clock else [])],
                    capture_output=True, text=True, timeout=60)
                assert replay.returncode == 0, replay.stderr
                listener.wait_for(lambda w=watching: any(
                                      s[4].get('points_received') == everything
                                      for s in w.of('occupancy_node')),
                                  10, 'occupancy diagnostics with every point')
                response = call_trigger('occupancy/save')
                assert response.success, response.message
                registration_log, occupancy_log = registration.output(), occupancy.output()
                assert registration.interrupt() == 0 and occupancy.interrupt() == 0
        finally:
            listener.close()
        grid, _ = load_npz(tmp_path / f'{name}.npz')
        assert grid.hits.sum() == 3 * len(frames), name
        stall = 'nothing publishes /clock'
        if not clock:
            assert stall in registration_log and stall in occupancy_log
            assert any(s[2] == WARN and stall in s[3] for s in listener.of('registration_node'))
            continue
        assert '/clock: ' in replay.stdout
        assert stall not in registration_log + occupancy_log
        # The nodes' own stamps are the bag's time: diagnostics and the object's frame.
        stamps = [s[0].sec + s[0].nanosec * 1e-9 for s in listener.of('occupancy_node')]
        in_bag = [t for t in stamps if bag_start - 0.1 <= t <= bag_end + 0.1]
        assert len(in_bag) >= 2, stamps
        ros_times = [float(s[4]['ros_time']) for s in listener.of('registration_node')]
        assert max(ros_times) == pytest.approx(bag_end, abs=0.1)
        objects = [m for m in listener.transforms if m.child_frame_id == 'object']
        assert objects and all(bag_start <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
                               <= bag_end + 1e-6 for m in objects)


def test_frames_and_diagnostics_of_a_hand_whose_object_sensor_falls_silent():
    """Two hands would set frame_prefix; every frame the registration node publishes
    carries it. When the object sensor falls silent the node's diagnostics go WARN and
    its log says so at the time, not only at shutdown."""
    frames, _ = sphere_session(seconds=2.0, surface_points=12, moving=True)
    fingers_only = [(t + 2.0, {k: v for k, v in frame.items() if k != 'object'})
                    for t, frame in sphere_session(seconds=3.0, surface_points=12)[0]]
    config = str(WORKSPACE / 'config' / 'mapping.yaml')
    listener = GraphListener()
    points = CloudCounter('registration/points')   # a reader: points reach somebody
    publisher = PosePublisher(['object', 'thumb', 'index', 'middle'])
    try:
        with running(['registration_node', '--ros-args', '--params-file', config,
                      '-p', 'frame_prefix:=left_hand/']) as registration:
            publisher.wait_for_subscribers(reader=registration)
            # The statuses of the 2 s of data must not be lost to discovery (up to 3 s):
            # one status first, then the data.
            listener.wait_for(lambda: listener.of('registration_node'), 15, 'a first status')
            publisher.publish(frames, rate_factor=1.0)
            listener.wait_for(lambda: any(s[4].get('state') == 'registering'
                                          for s in listener.of('registration_node')),
                              10, 'a status while registering')
            assert not any('silent' in s[3] for s in listener.of('registration_node'))
            publisher.publish(fingers_only, rate_factor=1.0)
            listener.wait_for(lambda: any('silent' in s[3] for s in listener.of('registration_node')),
                              10, 'a status saying the object sensor is silent')
            assert 'polhemus/object/pose silent' in registration.output()   # logged now
            status = [s for s in listener.of('registration_node') if 'silent' in s[3]][-1]
            assert status[2] == WARN and status[1] == '/registration_node'
            assert int(status[4]['pending']) + int(status[4]['dropped_gap']) > 0
            assert registration.interrupt() == 0
    finally:
        publisher.close()
        points.close()
        listener.close()
    children = {(m.header.frame_id, m.child_frame_id) for m in listener.transforms}
    assert ('left_hand/polhemus_source', 'left_hand/object') in children
    for finger in ('thumb', 'index', 'middle'):
        assert ('left_hand/polhemus_source', f'left_hand/fingertip_{finger}') in children
    # The object's frame is its pose: the last one sent is the last object pose given.
    last = [m for m in listener.transforms if m.child_frame_id == 'left_hand/object'][-1]
    position, _ = frames[-1][1]['object']
    t = last.transform.translation
    assert np.allclose([t.x, t.y, t.z], position, atol=1e-9)




def test_a_timed_replay_started_before_the_nodes_loses_nothing(tmp_path):
    """bag_replay used to wait 1 s for subscribers and then start: a replay started two
    seconds before the nodes lost the start. It waits (up to 10 s) until every topic has
    its subscriber, as the launchers do."""
    frames, _ = sphere_session(seconds=2.0, rate=120.0, surface_points=12, moving=False)
    fingers = [(t, {k: v for k, v in frame.items() if k != 'object'}) for t, frame in frames]
    bag = write_pose_bag(tmp_path / 'static', fingers)
    config = str(WORKSPACE / 'config' / 'mapping_static.yaml')
    ros = ['--ros-args', '--params-file', config]
    listener = GraphListener()
    try:
        with running(['bag_replay', str(bag), '--quiet']) as replay:
            time.sleep(2.0)
            with running(['registration_node', *ros]), \
                    running(['occupancy_node', *ros, '-p', f'output_dir:={tmp_path}']):
                assert replay.popen.wait(30) == 0, replay.output()
                everything = str(3 * len(frames))
                listener.wait_for(lambda: any(s[4].get('points_received') == everything
                                              for s in listener.of('occupancy_node')),
                                  10, 'every point in the occupancy diagnostics')
                assert call_trigger('occupancy/save').success
    finally:
        listener.close()
    assert 'waiting for a subscriber' in replay.output()
    grid, _ = load_npz(tmp_path / 'map.npz')
    assert grid.hits.sum() == 3 * len(frames)


def test_a_second_replay_into_a_running_graph_keeps_mapping(tmp_path):
    """Stamps going back (a second replay, a loop, a clock step) used to stop mapping for
    good: everything after the jump was dropped as 'before the first object pose'. The
    registration node starts a new stream, says so, and the map takes both passes."""
    frames, _ = sphere_session(seconds=2.0, rate=120.0, surface_points=12, moving=True)
    bag = write_pose_bag(tmp_path / 'moving', frames)
    config = str(WORKSPACE / 'config' / 'mapping.yaml')
    ros = ['--ros-args', '--params-file', config]
    fingertips = 3 * len(frames)
    listener = GraphListener()
    try:
        with running(['registration_node', *ros]) as registration, \
                running(['occupancy_node', *ros, '-p', f'output_dir:={tmp_path}']):
            for _ in range(2):
                replay = subprocess.run([executable_path('bag_replay'), str(bag), '--quiet'],
                                        capture_output=True, text=True, timeout=60)
                assert replay.returncode == 0, replay.stderr
            listener.wait_for(lambda: any(int(s[4].get('received', 0)) == 2 * fingertips
                                          and s[4].get('pending') == '0'
                                          for s in listener.of('registration_node')),
                              10, 'both passes received and nothing pending')
            assert call_trigger('occupancy/save').success
            log = registration.output()
            assert registration.interrupt() == 0
    finally:
        listener.close()
    assert 'time went back' in log                 # said when it happened
    status = [s for s in listener.of('registration_node')][-1][4]
    assert status['restarts'] == '1'
    assert status['dropped_before_object'] == '0'
    registered = int(status['registered'])
    lost = 2 * fingertips - registered
    assert lost <= 3 * 12, status                  # at most one 50 ms batch in flight
    grid, _ = load_npz(tmp_path / 'map.npz')
    assert grid.hits.sum() == registered
