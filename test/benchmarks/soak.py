#!/usr/bin/env python3
"""A soak run: the live graph against the emulator for half an hour, with faults.

    .venv/bin/python test/benchmarks/soak.py [--minutes 30] [--fault-every 60]
                                             [--autosave 30] [--output output/soak]

The emulator streams 4 stations at 240 Hz to ``liberty_driver``; ``registration_node`` and
``occupancy_node`` map (autosave as the live launcher's), and ``bag_record`` records the
driver's poses and the registered points. Every ``--fault-every`` seconds the emulator
injects the next fault of garbage, drop (bytes cut out of a frame), skip (frames never
sent), pause, stall (the device stops until the host resets it) and disconnect (the port
vanishes for 3 s). Once, half way between two faults after the middle of the run, the
occupancy node is killed with SIGKILL and started again from its autosave
(``initial_map``). At the end the driver and the emulator stop, the graph drains and the
map is saved; then the run is checked:

* no crash: every process but the killed one ended by itself with exit code 0, and no
  traceback;
* memory flat: the resident memory of every process a minute after its start and at the
  end (``--max-growth`` MB at most), sampled every 10 s into ``rss.csv`` and drawn in
  ``rss.png`` with the faults and the kill marked;
* frames lost only where a fault removed them: the bag holds one stamp for each frame the
  driver published; of the frames the emulator sent, the driver published all but at most
  2 per fault that damages the stream (garbage, drop, disconnect), 5 at the stop and those
  the re-plugged device sent before the driver had the port open again; and
  every outage lies in the window of a fault (a step of over 50 ms between two frame
  stamps, unless the 2 s either side hold every frame their length takes: then the frames
  came late, a process that did not read for a while, and none is missing);
* the final map is ``build_map``'s of the recorded bag but for what the kill lost: the
  registered points after the autosave the node restarted from and before the restarted
  node's first, found in the recorded ``registration/points``. Every cell whose log-odds
  or hits differ must lie within ``--reach`` cells of a point registered within
  ``--margin`` s of that stretch.

Prints a line a minute, then the figures; writes ``summary.json`` beside the bag, the maps,
``run.json`` (times, exit codes), ``rss.csv``, ``rss.png`` and ``soak.log`` (every process's
output, time-stamped) in ``--output``; ``--check DIR`` runs the checks again on such a
folder. Exit status 0 when every check passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inhand_mapping.surface_layer import LAYER_RADIUS

WORKSPACE = Path(__file__).resolve().parents[2]
STATIONS = ('thumb', 'index', 'middle', 'object')
POSE_TOPICS = tuple(f'polhemus/{name}/pose' for name in STATIONS)
POINTS_TOPIC = 'registration/points'
RATE = 240.0
# (emulator fault, argument, seconds the stream may be out after it: the fault itself,
# then the driver's silence timeout, reset and set-up, or a reconnect)
FAULTS = (('garbage', '400', 1.0), ('drop', '20', 1.0), ('skip', '24', 1.0),
          ('pause', '2', 4.0), ('stall', None, 5.0), ('disconnect', '3', 7.0))
# s: a longer step between two frame stamps is an outage. The stamps are times of receipt
# (backdated within a read), so steps of 11-15 ms come and go without a frame lost; a
# frame lost is seen in the counts instead.
OUTAGE = 0.05
DAMAGING = ('garbage', 'drop', 'disconnect')   # faults that may cost frames in flight
FRAMES_PER_DAMAGE = 2
FRAMES_AT_STOP = 5   # sent between the driver's stop command and the device obeying it
LATE_WINDOW = 2.0    # s either side of a step over OUTAGE where its frames are counted
RESTART_AFTER = 2.0  # s from the kill to the restart, as a supervisor would


class TimedLines:
    """The output stream of a ProcessGroup: each line kept with its wall time, written to
    the log, and shown when it says something a watcher wants (faults, warnings, errors)."""

    SHOWN = re.compile(r'fault at|WARN|ERROR|Traceback|Error|killed|started from')

    def __init__(self, log: Path | None):
        self.lines: list[tuple[float, str]] = []
        self._log = open(log, 'w', buffering=1) if log else None

    @classmethod
    def read(cls, log: Path) -> TimedLines:
        """The lines of a run's soak.log (for --check)."""
        lines = cls(None)
        for text in log.read_text().splitlines():
            stamp, _, line = text.partition(' ')
            lines.lines.append((float(stamp), line))
        return lines

    def write(self, text: str) -> None:
        now = time.time()
        for line in text.splitlines():
            self.lines.append((now, line))
            if self._log:
                self._log.write(f'{now:.3f} {line}\n')
            if self.SHOWN.search(line):
                print(f'  {line}', flush=True)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._log:
            self._log.close()

    def matching(self, pattern: str) -> list[tuple[float, re.Match]]:
        regex = re.compile(pattern)
        return [(t, m) for t, line in self.lines if (m := regex.search(line))]


@dataclass
class Memory:
    """Resident memory (MB) of each process life, sampled over the run."""

    samples: list[tuple[float, str, float]] = field(default_factory=list)  # (t, life, MB)

    def sample(self, now: float, lives: dict[str, int]) -> None:
        for life, pid in lives.items():
            rss = _rss_mb(pid)
            if rss is not None:
                self.samples.append((now, life, rss))

    def start_end(self, life: str, settle: float) -> tuple[float, float] | None:
        """RSS ``settle`` s after the life's first sample (warm-up: JIT, buffers) and at
        its last sample."""
        mine = [(t, mb) for t, name, mb in self.samples if name == life]
        if not mine:
            return None
        after = [mb for t, mb in mine if t >= mine[0][0] + settle] or [mine[-1][1]]
        return after[0], mine[-1][1]


def _rss_mb(pid: int) -> float | None:
    try:
        with open(f'/proc/{pid}/status') as status:
            for line in status:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def fault_arguments(minutes: float, every: float) -> list[tuple[float, str, str | None]]:
    """(seconds after the emulator's start, kind, argument): one fault every ``every`` s,
    cycling through FAULTS, none in the last half period."""
    schedule, t = [], every
    while t <= minutes * 60.0 - every / 2:
        kind, arg, _ = FAULTS[len(schedule) % len(FAULTS)]
        schedule.append((t, kind, arg))
        t += every
    return schedule


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--minutes', type=float, default=30.0,
                        help='minutes of streaming (default 30)')
    parser.add_argument('--fault-every', type=float, default=60.0, metavar='S',
                        help='seconds between faults (default 60)')
    parser.add_argument('--autosave', type=float, default=30.0, metavar='S',
                        help="the occupancy node's autosave period (default 30, the live "
                        "launcher's)")
    parser.add_argument('--kill-at', type=float, metavar='S',
                        help='seconds into the run to kill the occupancy node (default: half '
                        'way between the faults after the middle)')
    parser.add_argument('--max-growth', type=float, default=20.0, metavar='MB',
                        help='most a process may grow from a minute after its start to the '
                        'end (default 20 MB)')
    parser.add_argument('--reach', type=int, default=3 + LAYER_RADIUS, metavar='CELLS',
                        help='cells around the points the kill lost where the maps may differ '
                        f'(default {3 + LAYER_RADIUS}: 3, and the surface layer spreads a '
                        f'change of evidence {LAYER_RADIUS} cells further)')
    parser.add_argument('--margin', type=float, default=2.0, metavar='S',
                        help='seconds of stream either side of what the kill lost whose '
                        'points may differ too: tracks restart there (default 2)')
    parser.add_argument('--output', type=Path, default=WORKSPACE / 'output' / 'soak')
    parser.add_argument('--check', type=Path, metavar='DIR',
                        help='no run: check again the run whose output is in DIR (its '
                        'run.json, soak.log, rss.csv, bag and maps), e.g. with other limits')
    args = parser.parse_args()
    if args.check:
        return Soak.checked_again(args)
    if args.minutes <= 0 or args.fault_every <= 0 or args.autosave <= 0:
        parser.error('--minutes, --fault-every and --autosave must be positive')
    duration = args.minutes * 60.0
    kill_at = args.kill_at if args.kill_at is not None else \
        (int(duration / 2 / args.fault_every) + 1.5) * args.fault_every
    if not args.autosave < kill_at < duration - 20:
        parser.error(f'the kill at {kill_at:g} s must come after the first autosave and 20 s '
                     'before the end: give a longer --minutes or an earlier --kill-at')
    if args.output.exists():
        shutil.rmtree(args.output)
    args.output.mkdir(parents=True)
    return Soak(args, duration, kill_at).run()


class Soak:
    def __init__(self, args, duration: float, kill_at: float, log: TimedLines | None = None):
        self.args, self.duration, self.kill_at = args, duration, kill_at
        self.out: Path = args.output
        self.log = log or TimedLines(self.out / 'soak.log')
        self.memory = Memory()
        self.config = str(WORKSPACE / 'config' / 'mapping.yaml')
        self.port = f'/tmp/liberty-soak-{os.getpid()}'
        self.faults = fault_arguments(args.minutes, args.fault_every)
        self.lives: dict[str, int] = {}
        self.killed_at: float | None = None       # wall time of the SIGKILL
        self.restarted_at: float | None = None
        self.started = 0.0                         # wall time the points began to flow
        self.exits: list[tuple[str, int | None, bool]] = []   # (name, code, killed by us)
        self.problems: list[str] = []

    RECORDED = ('minutes', 'fault_every', 'autosave')   # the run's arguments in run.json

    @classmethod
    def checked_again(cls, args) -> int:
        """--check: the checks of a finished run, from what it left in its folder."""
        run = json.loads((args.check / 'run.json').read_text())
        for name in cls.RECORDED:
            setattr(args, name, run[name])
        args.output = args.check
        soak = cls(args, run['minutes'] * 60.0, run['kill_at'],
                   TimedLines.read(args.check / 'soak.log'))
        soak.started, soak.killed_at = run['started'], run['killed_at']
        soak.exits = [tuple(exit) for exit in run['exits']]
        for row in (args.check / 'rss.csv').read_text().splitlines()[1:]:
            seconds, life, mb = row.split(',')
            soak.memory.samples.append((soak.started + float(seconds), life, float(mb)))
        return soak._checks()

    # ------------------------------------------------------------------ the run
    def run(self) -> int:
        from sensor_msgs.msg import PointCloud2

        from inhand_tools.launching import (
            ProcessGroup,
            TopicWatch,
            driver_command,
            mapping_graph,
            save_when_drained,
        )
        print(f'[soak] {self.args.minutes:g} min at 4 x {RATE:g} Hz, a fault every '
              f'{self.args.fault_every:g} s ({len(self.faults)} in all), occupancy_node killed '
              f'at {self.kill_at:g} s; output in {self.out}', flush=True)
        with ProcessGroup(stream=self.log) as group, \
                TopicWatch(POINTS_TOPIC, PointCloud2) as watch:
            self.group = group
            fault_flags = [f'--fault={kind}{":" + arg if arg else ""}@{t:g}'
                           for t, kind, arg in self.faults]
            self._start('recorder', ['bag_record', '-o', str(self.out / 'bag'), *POSE_TOPICS,
                                     POINTS_TOPIC])
            mapping_graph(group, self.config, str(self.out), 'soak',
                          autosave=self.args.autosave)
            self.lives['registration'] = self._pid('registration')
            self.lives['occupancy'] = self._pid('occupancy')
            self._start('driver', driver_command(
                str(WORKSPACE / 'config' / 'liberty_emulator.yaml'), self.port))
            # Every reader in place before the first frame (the driver waits for its port),
            # so that the bag and the map start from the same one; the faults are timed
            # from the emulator's start.
            if not (self._wait_lines(r'bag_record: recording', 5, 60.0)
                    and watch.wait_reader('occupancy_node', timeout=60.0)
                    and watch.wait_connected(publishers=1, subscribers=3, timeout=60.0,
                                             settle=1.0)):
                self.problems.append('the recorder and the mapping nodes did not connect '
                                     'within 60 s')
                return self._finish(group, ok=False)
            self._start('emulator', ['liberty_emulator', '--port', self.port,
                                     '--status-every', '0', *fault_flags])
            if not watch.wait_first(60.0):
                self.problems.append('no registered points within 60 s of the start')
                return self._finish(group, ok=False)
            self.started = time.time()
            print('[soak] points flow; running', flush=True)
            try:
                self._watch()
            except KeyboardInterrupt:
                print('[soak] interrupted: stopping without the checks', flush=True)
                return 130
            print('[soak] stopping the driver and the emulator; saving once drained',
                  flush=True)
            ok, message = save_when_drained(group, watch, 1.0, ('driver', 'emulator'))
            if not ok:
                self.problems.append(f'final occupancy/save failed: {message}')
            self.memory.sample(time.time(), self.lives)
            group.stop_named('recorder')
        return self._finish(group, ok=True)

    def _wait_lines(self, pattern: str, count: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while len(self.log.matching(pattern)) < count:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.1)
        return True

    def _start(self, name: str, args: list[str]) -> None:
        self.lives[name] = self.group.start(name, args).pid

    def _pid(self, name: str) -> int:
        return [p for n, p in self.group.processes if n == name][-1].pid

    def _watch(self) -> None:
        """Sample memory every 10 s, a progress line a minute, the kill and the restart;
        a process that ends by itself is a crash."""
        from inhand_tools.launching import start_occupancy
        next_line, next_sample = self.started + 60.0, 0.0
        while time.time() - self.started < self.duration:
            now = time.time()
            if now >= next_sample:
                self.memory.sample(now, self.lives)
                next_sample = now + 10.0
            for name, process in self.group.processes:
                if process.poll() is not None and process.pid in self.lives.values():
                    crash = f'{name} ended by itself (exit code {process.returncode})'
                    self.problems.append(crash)
                    print(f'[soak] {crash}', flush=True)
                    return
            if self.killed_at is None and now - self.started >= self.kill_at:
                self._kill_occupancy()
            elif self.killed_at is not None and self.restarted_at is None and \
                    now - self.killed_at >= RESTART_AFTER:
                self.restarted_at = now
                process = start_occupancy(
                    self.group, self.config, str(self.out), 'soak',
                    autosave=self.args.autosave, initial_map=str(self.out / 'soak.npz'))
                self.lives['occupancy (restarted)'] = process.pid
                print('[soak] occupancy_node started from its autosave', flush=True)
            if now >= next_line:
                self._progress(now)
                next_line += 60.0
            time.sleep(0.5)

    def _kill_occupancy(self) -> None:
        os.kill(self.lives.pop('occupancy'), signal.SIGKILL)   # sampled no more
        self.killed_at = time.time()
        shutil.copy(self.out / 'soak.npz', self.out / 'soak_autosave_at_kill.npz')
        print(f'[soak] occupancy_node killed (SIGKILL) at {self.killed_at - self.started:.0f} s',
              flush=True)

    def _progress(self, now: float) -> None:
        faults = len(self.log.matching(r'fault at'))
        latest = {}
        for _, life, mb in self.memory.samples:
            latest[life] = mb
        rss = ', '.join(f'{life} {mb:.0f}' for life, mb in latest.items() if life in self.lives)
        print(f'[soak] {_clock(now - self.started)} / {_clock(self.duration)} | faults '
              f'{faults} | RSS MB: {rss}', flush=True)

    # ------------------------------------------------------------------ the checks
    def _finish(self, group, ok: bool) -> int:
        self.log.close()
        if not ok:
            return self._verdict()
        self.exits = [(name, process.returncode,
                       name == 'occupancy' and process.pid not in self.lives.values())
                      for name, process in group.processes]
        run = {name: getattr(self.args, name) for name in self.RECORDED}
        run.update(kill_at=self.kill_at, started=self.started, killed_at=self.killed_at,
                   exits=self.exits)
        (self.out / 'run.json').write_text(json.dumps(run, indent=2) + '\n')
        with open(self.out / 'rss.csv', 'w') as csv:
            csv.write('seconds,process,rss_mb\n')
            for t, life, mb in self.memory.samples:
                csv.write(f'{t - self.started:.1f},{life},{mb:.1f}\n')
        return self._checks()

    def _checks(self) -> int:
        summary = {'minutes': self.args.minutes, 'faults': len(self.faults)}
        summary['crashes'] = self._check_exits()
        summary['memory'] = self._check_memory()
        summary['frames'] = self._check_frames()
        summary['map'] = self._check_map()
        summary['problems'] = self.problems
        (self.out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
        self._draw_memory()
        return self._verdict()

    def _verdict(self) -> int:
        print()
        if self.problems:
            print(f'[soak] FAILED: {len(self.problems)} problem(s)')
            for problem in self.problems:
                print(f'  - {problem}')
            return 1
        print('[soak] passed: no crash, memory flat, frames lost only in faults, the map is '
              "build_map's of the bag but for what the kill lost")
        return 0

    def _check_exits(self) -> int:
        crashes = 0
        for name, code, killed in self.exits:
            if not killed and code != 0:
                crashes += 1
                self.problems.append(f'{name} exit code {code}')
        tracebacks = self.log.matching(r'Traceback')
        if tracebacks:
            crashes += len(tracebacks)
            self.problems.append(f'{len(tracebacks)} traceback(s) in soak.log')
        print(f'processes: {len(self.exits)} lives, {crashes} crash(es)')
        return crashes

    def _check_memory(self) -> dict[str, list[float]]:
        print(f'\nresident memory, MB (a minute after start -> end; at most '
              f'+{self.args.max_growth:g} MB):')
        figures = {}
        for life in dict.fromkeys(life for _, life, _ in self.memory.samples):
            span = self.memory.start_end(life, 60.0)
            if span is None:
                continue
            start, end = span
            figures[life] = [round(start, 1), round(end, 1)]
            print(f'  {life:<24} {start:8.1f} -> {end:8.1f}  ({end - start:+.1f})')
            if end - start > self.args.max_growth:
                self.problems.append(f'{life} grew {end - start:.1f} MB')
        return figures

    def _check_frames(self) -> dict[str, object]:
        from inhand_common.bag_source import BagSource
        from inhand_mapping.pose_cdr import decode_pose_stamped_many
        with BagSource(self.out / 'bag') as bag:
            if bag.problem:
                self.problems.append(f'the bag: {bag.problem}')
            raw = [data for _, _, data in bag.messages(set(POSE_TOPICS))]
        stamps_ns, _, _ = decode_pose_stamped_many(raw)
        frames = np.unique(stamps_ns).astype(np.float64) * 1e-9
        sent = self._number(r'liberty_emulator: stopped;.*frames sent (\d+)')
        full = self._number(r'liberty_emulator: stopped;.*lost (\d+)')
        skipped = self._number(r'liberty_emulator: stopped;.*skipped (\d+)')
        unread = self._number(r'liberty_emulator: stopped;.*before the host came back (\d+)') or 0
        published = self._number(r'stopped: (\d+) frames published')
        incomplete = self._number(r'frames published, \d+ dropped, (\d+) incomplete')
        out_for = {kind: seconds for kind, _, seconds in FAULTS}
        windows = [(kind, out_for[kind], self._fault_wall_time(kind, t))
                   for t, kind, _ in self.faults]
        steps = np.diff(frames)
        outages = [(frames[i], frames[i + 1]) for i in np.flatnonzero(steps > OUTAGE)]
        explained: dict[str, int] = {}
        unexplained, late = [], []
        for start, end in outages:
            # Frames that came late, not lost: the stream around the step holds as many
            # frames as its length takes (a process that did not read for a while, then
            # stamped a burst at receipt).
            near = np.count_nonzero((frames >= start - LATE_WINDOW) & (frames <= end + LATE_WINDOW))
            if (end - start + 2 * LATE_WINDOW) * RATE - near <= FRAMES_PER_DAMAGE:
                late.append(end - start)
                continue
            cause = next((kind for kind, span, at in windows
                          if at is not None and at - 0.5 <= start <= at + span), None)
            if cause is None:
                unexplained.append((start, end))
            else:
                explained[cause] = explained.get(cause, 0) + 1
        lost = None if sent is None or published is None else sent - published
        # A re-plugged device streams before the driver has the port open again: what it
        # sends meanwhile reaches no reader (the emulator counts it), as with a real cable.
        allowed = FRAMES_PER_DAMAGE * sum(kind in DAMAGING for _, kind, _ in self.faults) + \
            FRAMES_AT_STOP + unread
        print(f'\nframes: emulator sent {sent} (skipped {skipped} by the skip faults, {full} '
              f'lost to a full buffer); driver published {published} ({incomplete} incomplete); '
              f'the bag holds {len(frames)}; sent but not published: {lost} (at most '
              f'{allowed}: {FRAMES_PER_DAMAGE} per garbage, drop or disconnect, '
              f'{FRAMES_AT_STOP} at the stop, {unread} sent by the re-plugged device before '
              f'the driver was back)')
        print(f'  steps over {OUTAGE * 1000:.0f} ms between frame stamps: {len(outages)}; '
              f'frames late, none missing: {len(late)}'
              f'{f" (longest {max(late) * 1000:.0f} ms)" if late else ""}; outages in a fault '
              f'window: {dict(sorted(explained.items()))}; elsewhere: {len(unexplained)}')
        for start, end in unexplained[:10]:
            print(f'    at {_clock(start - self.started)}: {(end - start) * 1000:.0f} ms')
        if published is not None and len(frames) != published:
            self.problems.append(f'the bag holds {len(frames)} frames, the driver published '
                                 f'{published}')
        if lost is None or lost > allowed or full:
            self.problems.append(f'{lost} frames sent but not published (at most {allowed}), '
                                 f'{full} lost to a full buffer')
        if unexplained:
            self.problems.append(f'{len(unexplained)} outage(s) outside any fault')
        return {'sent': sent, 'skipped': skipped, 'lost_buffer_full': full,
                'before_the_host_came_back': unread,
                'published': published, 'incomplete': incomplete, 'in_bag': len(frames),
                'sent_not_published': lost, 'allowed': allowed,
                'outages': len(outages) - len(late), 'late_not_lost': len(late),
                'outages_by_fault': explained, 'outages_elsewhere': len(unexplained)}

    def _number(self, pattern: str) -> int | None:
        found = self.log.matching(pattern)
        return int(found[-1][1].group(1)) if found else None

    def _fault_wall_time(self, kind: str, at: float) -> float | None:
        """When the emulator said it injected the fault scheduled at ``at`` s."""
        for t, match in self.log.matching(r'fault at ([\d.]+) s: (\w+)'):
            if match.group(2) == kind and abs(float(match.group(1)) - at) < 1.0:
                return t
        return None

    def _check_map(self) -> dict[str, object]:
        from inhand_common.bag_source import BagSource
        from inhand_common.point_cloud import decode_point_cloud2
        from inhand_mapping.cloud_layouts import unpack_registered
        from inhand_mapping.map_io import load_npz
        print('\nbuild_map of the recorded bag ...', flush=True)
        build = subprocess.run(
            [str(Path(sys.executable).parent / 'build_map'), str(self.out / 'bag'),
             '--config', self.config, '--output-dir', str(self.out), '--name', 'bag_map'])
        if build.returncode != 0:
            self.problems.append(f'build_map exit code {build.returncode}')
            return {}
        live, _ = load_npz(self.out / 'soak.npz')
        rebuilt, _ = load_npz(self.out / 'bag_map.npz')
        at_kill, _ = load_npz(self.out / 'soak_autosave_at_kill.npz')
        with BagSource(self.out / 'bag') as bag:
            clouds = [unpack_registered(decode_point_cloud2(data).points)
                      for _, _, data in bag.messages({POINTS_TOPIC})]
        points = np.concatenate([c[0] for c in clouds])
        times = np.concatenate([c[1] for c in clouds])

        def given(grid) -> int:
            return grid.counts.integrated + grid.counts.outside + grid.counts.invalid
        # The stream's points in order: the autosave had the first given(at_kill); the
        # restarted node had the last given(live) - given(at_kill).
        lost_from = given(at_kill)
        lost_to = len(points) - (given(live) - given(at_kill))
        lost = max(lost_to - lost_from, 0)
        near = np.zeros(live.spec.shape, dtype=bool)
        if lost_to > lost_from:
            t0, t1 = times[lost_from] - self.args.margin, times[lost_to - 1] + self.args.margin
            window = points[(times >= t0) & (times <= t1)]
            cells = live.spec.cell_indices(window[live.spec.contains(window)])
            reach = self.args.reach
            for offset in np.ndindex(2 * reach + 1, 2 * reach + 1, 2 * reach + 1):
                shifted = np.clip(cells + np.array(offset) - reach, 0,
                                  live.spec.cells_per_axis - 1)
                near[tuple(shifted.T)] = True
        differ = (np.abs(live.log_odds - rebuilt.log_odds) > 1e-9) | (live.hits != rebuilt.hits)
        outside_reach = int(np.count_nonzero(differ & ~near))
        occupied_live = live.probabilities() > 0.8
        occupied_rebuilt = rebuilt.probabilities() > 0.8
        flipped = int(np.count_nonzero(occupied_live ^ occupied_rebuilt))
        print(f'map: {len(points):,} points registered (the bag); build_map gave '
              f'{given(rebuilt):,}; the node {given(live):,} ({lost:,} lost to the kill: '
              f'{lost / RATE / 3:.1f} s of 3 fingertips)')
        print(f'  cells: {int(np.count_nonzero(occupied_live)):,} occupied in the node\'s map, '
              f'{int(np.count_nonzero(occupied_rebuilt)):,} in build_map\'s; '
              f'{int(np.count_nonzero(differ)):,} differ ({flipped} occupied in one only), '
              f'{outside_reach} of them beyond {self.args.reach} cells of the stretch the kill '
              'lost')
        registered = self._number(r'stopped: (\d+) of \d+ fingertip positions registered')
        if registered != len(points):
            self.problems.append(f'the bag holds {len(points)} registered points, the '
                                 f'registration node registered {registered}')
        if given(rebuilt) != len(points):
            self.problems.append(f'build_map registered {given(rebuilt)} points, the node '
                                 f'{len(points)}')
        if outside_reach:
            self.problems.append(f'{outside_reach} cells differ away from what the kill lost')
        return {'registered': len(points), 'build_map_points': given(rebuilt),
                'node_points': given(live), 'lost_to_kill': lost,
                'cells_differing': int(np.count_nonzero(differ)),
                'occupied_in_one_only': flipped, 'differing_beyond_reach': outside_reach}

    def _draw_memory(self) -> None:
        """rss.png: MB over minutes per process, faults and the kill marked."""
        import cv2
        width, height, margin = 1000, 500, 60
        image = np.full((height, width, 3), 255, np.uint8)
        top = max(mb for _, _, mb in self.memory.samples) * 1.1
        span = max(self.duration, 1.0)

        def xy(t: float, mb: float) -> tuple[int, int]:
            return (int(margin + (t - self.started) / span * (width - 2 * margin)),
                    int(height - margin - mb / top * (height - 2 * margin)))
        colours = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194)]
        for t, _ in self.log.matching(r'fault at'):
            cv2.line(image, xy(t, 0), xy(t, top), (200, 200, 200), 1)
        if self.killed_at:
            cv2.line(image, xy(self.killed_at, 0), xy(self.killed_at, top), (0, 0, 255), 2)
        lives = list(dict.fromkeys(life for _, life, _ in self.memory.samples))
        for index, life in enumerate(lives):
            line = np.array([xy(t, mb) for t, name, mb in self.memory.samples if name == life])
            colour = colours[index % len(colours)][::-1]
            cv2.polylines(image, [line.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
            cv2.putText(image, life, (margin + 10, margin + 18 * index), cv2.FONT_HERSHEY_SIMPLEX,
                        0.45, colour, 1, cv2.LINE_AA)
        cv2.line(image, xy(self.started, 0), xy(self.started + span, 0), (0, 0, 0), 1)
        cv2.line(image, xy(self.started, 0), xy(self.started, top), (0, 0, 0), 1)
        for mb in np.linspace(0, top, 5):
            cv2.putText(image, f'{mb:.0f}', (5, xy(self.started, mb)[1] + 4),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        for minute in range(0, int(span // 60) + 1, max(1, int(span // 60) // 10)):
            x, y = xy(self.started + minute * 60, 0)
            cv2.putText(image, f'{minute}', (x - 5, y + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(image, 'resident memory (MB) over minutes; grey: faults, red: the kill',
                    (margin, height - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                    cv2.LINE_AA)
        cv2.imwrite(str(self.out / 'rss.png'), image)


def _clock(seconds: float) -> str:
    return f'{int(seconds // 60)}:{int(seconds % 60):02d}'


if __name__ == '__main__':
    sys.exit(main())
