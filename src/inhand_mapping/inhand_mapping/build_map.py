"""``build_map``: the map the registration and occupancy nodes would build, from a bag.

    build_map BAG [--config config/mapping.yaml] [--output-dir maps] [--name NAME]
                  [--set NAME=VALUE ...]

Reads a rosbag2 bag (MCAP or sqlite3) holding the driver's ``polhemus/<name>/pose``
topics, runs the same registration and occupancy code with the same parameters (the
``registration_node`` and ``occupancy_node`` sections of the YAML file, then ``--set``
overrides), and writes ``<name>.npz`` and ``<name>.ply`` as ``occupancy/save`` would. No
DDS involved. A truncated bag is reported with what could be read, and the map of that
part is still written (exit code 1); a bag without the topics is refused (exit code 2).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from inhand_common.bag_source import BagSource, Progress
from inhand_common.parameters import ParameterError, load_yaml_parameters, validate
from inhand_mapping.clouds import pack_registered, unpack_registered
from inhand_mapping.map_products import MapProducts, save_map
from inhand_mapping.mapping_config import (OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS,
                                           make_grid, make_registrar)
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.registration import HISTORY_SECONDS

EXIT_TRUNCATED = 1
EXIT_BAD_INPUT = 2
CHUNK = 4096  # messages decoded and registered together


def parse_overrides(pairs: list[str]) -> dict:
    values = {}
    for pair in pairs:
        name, sep, text = pair.partition('=')
        if not sep or not name:
            raise ParameterError([f'--set {pair!r}: expected NAME=VALUE'])
        values[name.strip()] = yaml.safe_load(text)
    return values


def load_parameters(config: str | None, overrides: dict) -> tuple[dict, dict]:
    """Validated (registration, occupancy) parameter values, as the nodes would get them."""
    registration = load_yaml_parameters(config, 'registration_node') if config else {}
    occupancy = load_yaml_parameters(config, 'occupancy_node') if config else {}
    registration_names = {s.name for s in REGISTRATION_PARAMETERS}
    occupancy_names = {s.name for s in OCCUPANCY_PARAMETERS}
    unknown = sorted(set(overrides) - registration_names - occupancy_names)
    if unknown:
        raise ParameterError([f"--set: unknown parameter '{name}'" for name in unknown])
    registration.update({k: v for k, v in overrides.items() if k in registration_names})
    occupancy.update({k: v for k, v in overrides.items() if k in occupancy_names})
    return validate(REGISTRATION_PARAMETERS, registration), validate(OCCUPANCY_PARAMETERS,
                                                                    occupancy)


class BagMessages:
    """The driver's pose topics of a bag, raw, in time order (over :class:`BagSource`).

    Refuses a bag that lacks one of ``topics`` or holds it with another type than
    PoseStamped; ``problem`` says what stopped the reading early (None if the bag was read
    to its end, e.g. a truncated MCAP read up to the cut).
    """

    def __init__(self, bag: Path, topics: set[str]):
        self.source = BagSource(bag)
        self.bag, self.topics = Path(bag), topics
        self.total = 0

    def __enter__(self) -> 'BagMessages':
        self.source.__enter__()
        available = self.source.topics
        missing = sorted(self.topics - set(available))
        if missing:
            self.source.__exit__(None, None, None)
            raise ValueError(f'{self.bag}: no {", ".join(missing)} in this bag; it has '
                             f'{sorted(available) or "no topics"}')
        for topic in sorted(self.topics):
            if available[topic].msgtype != 'geometry_msgs/msg/PoseStamped':
                self.source.__exit__(None, None, None)
                raise ValueError(f'{self.bag}: {topic} is {available[topic].msgtype}, '
                                 'expected geometry_msgs/msg/PoseStamped')
        self.total = sum(available[topic].count for topic in self.topics)
        return self

    @property
    def problem(self) -> str | None:
        return self.source.problem

    @property
    def start_ns(self) -> int:
        return self.source.start_ns

    @property
    def end_ns(self) -> int:
        return self.source.end_ns

    def __iter__(self):
        return self.source.messages(self.topics)

    def __exit__(self, *exc) -> None:
        self.source.__exit__(*exc)


class BagRegistration:
    """The registered fingertip points of a bag, batch by batch, exactly as the
    registration node would publish them (same Registrar, same parameters, through the
    topic's float32 layout). Also keeps the raw fingertip positions when asked, and a
    report of what was read.
    """

    def __init__(self, bag: Path, registration_values: dict, progress: bool = False,
                 keep_raw: bool = False):
        self.bag = bag
        self.values = registration_values
        self.progress = progress
        self.registrar = make_registrar(registration_values)
        fingers = list(registration_values['finger_names'])
        self.topics = {f'polhemus/{name}/pose': index for index, name in enumerate(fingers)}
        self.object_topic = None
        if registration_values['mode'] == 'tracked':
            self.object_topic = f'polhemus/{registration_values["object_name"]}/pose'
        self.report = {'messages': 0, 'truncated': None, 'bag_start': None, 'bag_end': None}
        self.raw: list[tuple[np.ndarray, np.ndarray]] | None = [] if keep_raw else None

    def __iter__(self):
        wanted = set(self.topics) | ({self.object_topic} if self.object_topic else set())
        report = self.report
        chunk: list[tuple[str, bytes]] = []
        with BagMessages(self.bag, wanted) as source:
            bar = Progress('build_map', source.start_ns, source.end_ns) if self.progress \
                else None
            started = time.monotonic()
            for topic, timestamp, raw in source:
                chunk.append((topic, raw))
                report['bag_start'] = report['bag_start'] or timestamp
                report['bag_end'] = timestamp
                report['messages'] += 1
                if len(chunk) >= CHUNK:
                    yield from self._process(chunk)
                    chunk = []
                    if bar:
                        bar.update(timestamp, report['messages'], source.start_ns,
                                   time.monotonic() - started)
            yield from self._process(chunk)
            if bar:
                bar.update(report['bag_end'] or source.start_ns, report['messages'],
                           source.start_ns, time.monotonic() - started, force=True)
                bar.close()
            report['truncated'] = source.problem
            report['expected_messages'] = source.total
        yield self._as_published(*self.registrar.finish())

    def _process(self, chunk: list[tuple[str, bytes]]):
        if not chunk:
            return
        stamps, _, poses = decode_pose_stamped_many([raw for _, raw in chunk])
        times = stamp_seconds(stamps)
        is_object = np.array([topic == self.object_topic for topic, _ in chunk])
        finger_ids = np.array([self.topics.get(topic, -1) for topic, _ in chunk])
        if self.raw is not None:
            self.raw.append((poses[~is_object, :3], finger_ids[~is_object]))
        # Feed the registrar in short slices of sensor time, object poses before
        # fingertips, the way a live stream interleaves them.
        slice_ids = np.floor(times / (HISTORY_SECONDS / 2.0))
        for slice_id in np.unique(slice_ids):
            part = slice_ids == slice_id
            for k in np.flatnonzero(part & is_object):
                self.registrar.add_object_pose(times[k], poses[k, :3], poses[k, 3:])
            tips = part & ~is_object
            if tips.any():
                self.registrar.add_fingertips(times[tips], poses[tips, :3], finger_ids[tips])
            yield self._as_published(*self.registrar.drain())

    @staticmethod
    def _as_published(points, times, finger_ids):
        # Through the topic's float32 layout, so the map equals the node's to the bit.
        return unpack_registered(pack_registered(points, times, finger_ids))


def build(bag: Path, registration_values: dict, occupancy_values: dict,
          progress: bool = True) -> dict:
    """Run the bag through registration and occupancy; returns the pieces and a report."""
    grid = make_grid(occupancy_values)
    registration = BagRegistration(bag, registration_values, progress)
    for points, times, fingers in registration:
        grid.integrate(points, times, fingers)
    grid.flush()   # the samples held back for their dwell weights: the bag has ended
    return {'grid': grid, 'registrar': registration.registrar, 'report': registration.report}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='build_map', description=__doc__.split('\n\n')[0],
                                     epilog=__doc__.split('\n\n', 2)[2],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', type=Path, help='bag folder, or .mcap / .db3 file')
    parser.add_argument('--config', help='ROS parameter file with registration_node and '
                        'occupancy_node sections (e.g. config/mapping.yaml)')
    parser.add_argument('--output-dir', type=Path, default=Path('maps'))
    parser.add_argument('--name', help='file name stem (default: the bag name)')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='override a parameter (repeatable)')
    parser.add_argument('--quiet', action='store_true', help='no progress line')
    args = parser.parse_args(argv)
    try:
        registration_values, occupancy_values = load_parameters(args.config,
                                                                parse_overrides(args.set))
        if not args.bag.exists():
            raise ValueError(f'{args.bag}: no such bag')
        start = time.monotonic()
        result = build(args.bag, registration_values, occupancy_values,
                       progress=not args.quiet)
    except (ParameterError, ValueError, OSError) as error:
        print(f'build_map: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    elapsed = time.monotonic() - start
    grid, registrar, report = result['grid'], result['registrar'], result['report']
    threshold = occupancy_values['occupied_threshold']
    name = args.name or args.bag.name.rsplit('.', 1)[0] or 'map'
    paths = save_map(grid, args.output_dir, name, threshold, 'object',
                     extra={'bag': str(args.bag), 'truncated': report['truncated']})
    stats = registrar.stats
    span = ((report['bag_end'] or 0) - (report['bag_start'] or 0)) * 1e-9
    products = MapProducts(grid, threshold)
    touched, occupied = products.cells()
    frame = products.object_frame()
    print(f'build_map: {report["messages"]} messages, {span:.1f} s of data in {elapsed:.2f} s '
          f'({span / elapsed if elapsed > 0 else float("inf"):.1f}x real time)')
    print(f'  registration ({registration_values["mode"]}): {stats.registered} of '
          f'{stats.received} fingertip positions; dropped {stats.dropped_gap} (object pose '
          f'gap), {stats.dropped_before_object} (before the first object pose), '
          f'{stats.dropped_invalid} (invalid)')
    print(f'  map: {grid.counts.integrated} points integrated, {grid.counts.outside} outside '
          f'the workspace, {grid.counts.invalid} invalid; {len(touched)} cells touched, '
          f'{len(occupied)} above {threshold:g}')
    if frame is not None:
        print('  centre of mass (object frame): '
              + ', '.join(f'{v:+.4f}' for v in frame.centre_of_mass) + ' m')
    print('  wrote ' + ', '.join(str(p) for p in paths))
    if report['truncated']:
        print(f'build_map: the bag is truncated or damaged: {report["truncated"]}. The map '
              f'above is built from the {report["messages"]} messages that could be read.',
              file=sys.stderr)
        return EXIT_TRUNCATED
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
