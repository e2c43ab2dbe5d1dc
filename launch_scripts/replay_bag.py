"""Replay a bag of the driver's topics through the mapping graph, then save and show the map.

    .venv/bin/python launch_scripts/replay_bag.py BAG [--config FILE] [--output DIR]
        [--name NAME] [--rate FACTOR | --fast] [--no-render] [--topics T ...] [--sim-time]
        [--view [--http-port P] [--foxglove-port P]]

Starts registration_node and occupancy_node (and stereo_node with config/stereo.yaml when the
bag holds a stereo pair: it publishes stereo/points and occupancy/textured), replays BAG
with bag_replay over real DDS,
waits for the last registered points to be integrated, calls occupancy/save, stops the
nodes, then renders the map (render_map), extracts its shape (extract_shape: surface mesh,
superquadric parts and grasps, NAME_shape.png), predicts its surface and where to touch next
(predict_surface, with the bag's stereo pairs when it has any: NAME_uncertainty.png) and,
when the bag has a ground-truth sidecar (BAG.truth.npz, written by simulate_session), prints
its metrics (map_metrics). The
config defaults to config/mapping.yaml (tracked object) when the bag has an object sensor
topic, else config/mapping_static.yaml. Only the graph's inputs are replayed (driver poses,
stereo images and camera infos), so a bag recorded from a live run, which also holds maps
and diagnostics, replays like a driver's bag; --topics chooses. --sim-time runs the nodes
with use_sim_time and the replay with --clock (the graph lives in the bag's time). --view
also starts live_view (the page at http://127.0.0.1:8080/, Foxglove at ws://127.0.0.1:8765)
and keeps the graph up after the save until Ctrl-C. Ctrl-C (or SIGTERM, or the terminal
closing) during the replay stops it, saves what the graph mapped once it has drained, and
ends with exit code 130 without pictures; a second Ctrl-C does not cut the save short.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from inhand_common.bag_source import BagError, BagSource
from inhand_common.ground_truth import truth_path
from inhand_common.ros_names import OBJECT_POSE_TOPIC
from inhand_tools.launching import (
    ProcessGroup,
    TopicWatch,
    add_view_arguments,
    call_trigger,
    hold_view,
    mapping_graph,
    save_when_drained,
    start_view,
)

WORKSPACE = Path(__file__).resolve().parents[1]
QUIET = 1.0  # s without registered points after the replay: the graph has caught up
TEXTURE_WAIT = 120.0  # s the save waits for the stereo node's first textured map
QUIET_TEXTURE = 2.0  # s without a new textured map: the last one is of the final map


EXIT_INTERRUPTED = 130   # the shell's code for a command ended by Ctrl-C
STEREO_IMAGE_TOPIC = 'stereo/left/image_raw'
# What the graph takes in: the driver's poses and the stereo pairs. A bag recorded from a
# live run also holds the graph's outputs (maps, diagnostics): replaying those would wait
# for subscribers that never come, and feed the graph its own results.
GRAPH_INPUTS = re.compile(r'^(polhemus/[^/]+/pose|stereo/(left|right)/(image_raw|camera_info))$')


def graph_inputs(topics: set[str]) -> list[str]:
    """The topics of a bag the mapping graph takes in, sorted."""
    return sorted(t for t in topics if GRAPH_INPUTS.match(t))


def bag_topics(bag: Path) -> set[str] | None:
    """The bag's topics (relative), or None if it cannot be read (bag_replay says why)."""
    try:
        with BagSource(bag) as source:
            return set(source.topics)
    except BagError:
        return None


def replay(bag: Path, config: Path | None, output: Path, name: str, rate_args: list[str],
           render: bool = True, only: list[str] | None = None, sim_time: bool = False,
           view_args=None) -> int:
    if not bag.exists():
        print(f'replay_bag: {bag}: no such bag', file=sys.stderr)
        return 2
    topics = bag_topics(bag)
    replayed = only
    if replayed is None and topics is not None:   # unreadable: bag_replay says why
        replayed = graph_inputs(topics)
        if not replayed:
            print(f'replay_bag: {bag} holds none of the graph\'s inputs (polhemus/<station>/pose, '
                  f'stereo pairs); its topics: {", ".join(sorted(topics))}; --topics chooses',
                  file=sys.stderr)
            return 2
    if config is None:
        tracked = topics is None or OBJECT_POSE_TOPIC in topics
        config = WORKSPACE / 'config' / ('mapping.yaml' if tracked else 'mapping_static.yaml')
    # A bag with a stereo pair gets the stereo node too (the rig of config/stereo.yaml).
    stereo = WORKSPACE / 'config' / 'stereo.yaml' if topics and STEREO_IMAGE_TOPIC in topics \
        else None
    output.mkdir(parents=True, exist_ok=True)
    print(f'[launch] mapping graph with {config}; replaying {bag}', flush=True)
    started = time.monotonic()
    from sensor_msgs.msg import PointCloud2
    with ProcessGroup() as group, TopicWatch('registration/points', PointCloud2) as watch, \
            TopicWatch('occupancy/textured', PointCloud2) as textured:
        mapping_graph(group, str(config), str(output), name,
                      stereo_config=str(stereo) if stereo else None, sim_time=sim_time,
                      shape=bool(getattr(view_args, 'view', False)),
                      exploration=bool(getattr(view_args, 'view', False)))
        view = start_view(group, view_args)
        # The registration node's first points must find the occupancy node (and the
        # view) listening. The graph shows a reader before the registration node's writer
        # has matched it; the view starts with the shape and exploration nodes, which load
        # for a while on a busy machine, so it gets longer to match (a fast replay of a
        # small bag is over in well under a second).
        if not watch.wait_connected(subscribers=3 if view else 2, settle=2.0 if view else 0.5):
            print('[launch] the mapping nodes did not come up', file=sys.stderr)
            return 1
        clock = ['--clock'] if sim_time else []
        try:
            code = group.run('replay', ['bag_replay', str(bag), *rate_args, *clock,
                                        *(['--topics', *replayed] if replayed else [])])
        except KeyboardInterrupt:   # Ctrl-C, SIGTERM, SIGHUP: save what was mapped, no more
            group.say('[launch] interrupted: saving what the graph mapped once it has '
                      'drained')
            save_when_drained(group, watch, QUIET)
            return EXIT_INTERRUPTED
        if code != 0:
            print(f'[launch] bag_replay ended with exit code {code}', file=sys.stderr)
            if code != 1:  # 1: truncated bag, replayed what could be read
                return code
        watch.wait_quiet(QUIET)
        if stereo:
            # The colours come from the stereo node once it has the map (its first pair can
            # take a while: the numba kernels compile on a first run): the save waits for
            # them, and for the texture of the final map.
            if not textured.wait_first(TEXTURE_WAIT):
                print(f'[launch] no occupancy/textured from the stereo node within '
                      f'{TEXTURE_WAIT:g} s: the map is saved without colours', flush=True)
            textured.wait_quiet(QUIET_TEXTURE)
        ok, message = call_trigger('occupancy/save')
        print(f'[launch] occupancy/save: {message}', flush=True)
        if not ok:
            return 1
        if view:
            hold_view(group, view)
    print(f'[launch] graph stopped after {time.monotonic() - started:.1f} s', flush=True)
    npz = output / f'{name}.npz'
    truth = truth_path(bag)
    # the same parameter files as the nodes: the registration of --bag, the rig's camera_pose
    configs = ['--config', str(config)] + (['--config', str(stereo)] if stereo else [])
    with ProcessGroup() as group:
        if render:
            args = ['render_map', str(npz), '--bag', str(bag), '--output', str(output),
                    *configs]
            if truth.exists():
                args += ['--truth', str(truth)]
            if group.run('render', args) != 0:
                return 1
            # the paper's Fig. 1: surface mesh, superquadric parts, graspable part, grasps
            # a bag without the object sensor is mapped in the tracker frame, whose z is down
            up = 'z' if topics is None or OBJECT_POSE_TOPIC in topics else '-z'
            if group.run('shape', ['extract_shape', str(npz), '--output-dir', str(output), '--quiet',
                                   f'--up={up}', *configs]) != 0:
                return 1
            # what the map does not know yet, and where to touch next (the map records the
            # mode), with what the bag's camera saw, as the live exploration node has it
            if group.run('predict', ['predict_surface', str(npz), '--bag', str(bag),
                                     '--output-dir', str(output), '--quiet', f'--up={up}',
                                     *configs]) != 0:
                return 1
        if truth.exists():
            if group.run('metrics', ['map_metrics', str(npz), '--truth', str(truth), '--bag',
                                     str(bag), *configs, '--json',
                                     str(output / f'{name}.metrics.json')]):
                return 1
    print(f'[launch] done: map, pictures and metrics are in {output}/', flush=True)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path)
    parser.add_argument('--config', type=Path)
    parser.add_argument('--output', type=Path, default=WORKSPACE / 'output')
    parser.add_argument('--name', help='map name (default: the bag name)')
    speed = parser.add_mutually_exclusive_group()
    speed.add_argument('--rate', type=float, help='replay speed factor (default: --fast)')
    speed.add_argument('--fast', action='store_true', help='as fast as the graph keeps up')
    parser.add_argument('--no-render', action='store_true')
    parser.add_argument('--topics', nargs='+', metavar='T',
                        help="replay these topics (default: the graph's inputs the bag holds: "
                        'driver poses, stereo images and camera infos)')
    parser.add_argument('--sim-time', action='store_true',
                        help="the nodes run with use_sim_time, the replay publishes the bag's "
                        'time on /clock')
    add_view_arguments(parser)
    args = parser.parse_args(argv)
    rate_args = ['--rate', str(args.rate)] if args.rate else ['--fast']
    return replay(args.bag, args.config, args.output, args.name or args.bag.name, rate_args,
                  render=not args.no_render, only=args.topics, sim_time=args.sim_time,
                  view_args=args)


if __name__ == '__main__':
    raise SystemExit(main())
