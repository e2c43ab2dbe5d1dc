"""Two hosts without multicast: the tracker on one, the mapping on the other.

    sudo .venv/bin/python launch_scripts/two_hosts.py [--duration S] [--output DIR]
                                                      [--without-peers]

Builds two network namespaces joined by a veth pair (``tracker`` 10.77.0.1, ``mapper``
10.77.0.2; nothing else, so no multicast route and no shared loopback), runs the emulated
Liberty and ``liberty_driver`` on the tracker host and ``registration_node`` and
``occupancy_node`` on the mapper host, and checks that the map arrives. DDS is set up the
way a lab network without multicast needs it, with a Fast DDS profile per host
(``FASTRTPS_DEFAULT_PROFILES_FILE``; both are left in ``--output`` to copy for real hosts):
UDPv4 only (no shared memory can carry what the network should), the host's own address
as its locator, and as initial peers its own address (the other nodes of the host) and the
other host's.

``--duration`` seconds after the poses start to flow into the mapper host, the driver
stops; 2 s later the mapping nodes stop and the occupancy node saves. The script prints
what went over the veth and what the map integrated. Exit status: 0 when the map holds
every registered point and they came over the veth, 1 when not, 3 when this machine cannot
create network namespaces (not root, no ``ip``), with the reason.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from inhand_tools.launching import ProcessGroup, driver_command, mapping_graph

WORKSPACE = Path(__file__).resolve().parents[1]
EXIT_CANNOT = 3
SUBNET = '10.77.0'
FLOWING = 40_000   # bytes/s into the mapper host: poses flow (4 x 240 Hz is about 150 kB/s)


class Hosts:
    """Two network namespaces joined by a veth pair; removed on exit."""

    def __init__(self, tag: str, static_peers: bool = True) -> None:
        self.static_peers = static_peers
        self.names = {'tracker': f'inhand-tracker-{tag}', 'mapper': f'inhand-mapper-{tag}'}
        self.address = {'tracker': f'{SUBNET}.1', 'mapper': f'{SUBNET}.2'}
        self.link = {'tracker': f'ih{tag}t', 'mapper': f'ih{tag}m'}

    def __enter__(self) -> Hosts:
        try:
            for netns in self.names.values():
                _ip('netns', 'add', netns)
                _ip('-n', netns, 'link', 'set', 'lo', 'up')
            _ip('link', 'add', self.link['tracker'], 'netns', self.names['tracker'], 'type',
                'veth', 'peer', 'name', self.link['mapper'], 'netns', self.names['mapper'])
            for host, netns in self.names.items():
                _ip('-n', netns, 'addr', 'add', f'{self.address[host]}/24', 'dev',
                    self.link[host])
                _ip('-n', netns, 'link', 'set', self.link[host], 'up')
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        for netns in self.names.values():   # removing a namespace removes its veth end
            subprocess.run(['ip', 'netns', 'del', netns], capture_output=True, check=False)

    def prefix(self, host: str) -> list[str]:
        """What runs a command on ``host``."""
        return ['ip', 'netns', 'exec', self.names[host]]

    def received_bytes(self, host: str) -> int:
        out = subprocess.run([*self.prefix(host), 'cat', f'/sys/class/net/{self.link[host]}/'
                             'statistics/rx_bytes'],
                             capture_output=True, text=True, check=True).stdout
        return int(out)

    def wait_for_stream(self, rate: float, timeout: float) -> bool:
        """Wait until the mapper host receives at least ``rate`` bytes/s (the tracker's
        poses, not discovery's few packets): discovery by static peers takes seconds."""
        deadline = time.monotonic() + timeout
        before = self.received_bytes('mapper')
        while time.monotonic() < deadline:
            time.sleep(0.5)
            now = self.received_bytes('mapper')
            if now - before > rate * 0.5:
                return True
            before = now
        return False

    def dds_environment(self, host: str, profiles_dir: Path) -> dict[str, str]:
        """The environment of a host's nodes: Fast DDS with the profile of that host."""
        profile = profiles_dir / f'{host}.xml'
        profile.write_text(self.fastdds_profile(host))
        return {**os.environ, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile),
                'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT', 'ROS_DOMAIN_ID': '0',
                'PYTHONUNBUFFERED': '1'}

    def fastdds_profile(self, host: str) -> str:
        """A host's participant: UDPv4 only (no shared memory between the hosts), found
        at its own address, looking for the other nodes of its host and for the other host
        at their addresses (the initial peers; no multicast)."""
        other = 'mapper' if host == 'tracker' else 'tracker'
        peers = [self.address[host]] + ([self.address[other]] if self.static_peers else [])
        locators = ''.join(f"""
          <locator><udpv4><address>{address}</address></udpv4></locator>""" for address in peers)
        peers_xml = f"""
        <initialPeersList>{locators}
        </initialPeersList>"""
        return f"""<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="{host}" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>udp</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <metatrafficUnicastLocatorList>
          <locator><udpv4><address>{self.address[host]}</address></udpv4></locator>
        </metatrafficUnicastLocatorList>{peers_xml}
      </builtin>
      <defaultUnicastLocatorList>
        <locator><udpv4><address>{self.address[host]}</address></udpv4></locator>
      </defaultUnicastLocatorList>
    </rtps>
  </participant>
</profiles>
"""


def _ip(*args: str) -> None:
    result = subprocess.run(['ip', *args], capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f'ip {" ".join(args)}: {result.stderr.strip()}')


def cannot_create_namespaces() -> str | None:
    """Why this machine cannot run the two hosts, or None when it can."""
    if shutil.which('ip') is None:
        return "no 'ip' command (iproute2)"
    if os.geteuid() != 0:
        return 'network namespaces need root (run with sudo)'
    probe = f'inhand-probe-{os.getpid()}'
    result = subprocess.run(['ip', 'netns', 'add', probe], capture_output=True, text=True,
                            check=False)
    subprocess.run(['ip', 'netns', 'del', probe], capture_output=True, check=False)
    if result.returncode != 0:
        return f'cannot create a network namespace: {result.stderr.strip()}'
    return None


class Lines:
    """Everything the process group prints, kept for the checks at the end."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, text: str) -> None:
        sys.stdout.write(text)
        self.lines.extend(text.splitlines())

    def flush(self) -> None:
        sys.stdout.flush()

    def wait_for(self, pattern: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(re.search(pattern, line) for line in list(self.lines)):
                return True
            time.sleep(0.1)
        return False

    def number(self, pattern: str) -> int | None:
        for line in reversed(self.lines):
            found = re.search(pattern, line)
            if found:
                return int(found.group(1))
        return None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=10.0,
                        help='seconds of streaming (default 10)')
    parser.add_argument('--output', type=Path, default=WORKSPACE / 'output' / 'two_hosts')
    parser.add_argument('--without-peers', action='store_true',
                        help="no initial peer on the other host: the control run, where "
                        'nothing may arrive')
    args = parser.parse_args(argv)
    reason = cannot_create_namespaces()
    if reason:
        print(f'two_hosts: cannot run here: {reason}', file=sys.stderr)
        return EXIT_CANNOT
    args.output.mkdir(parents=True, exist_ok=True)
    port = f'/tmp/liberty-two-hosts-{os.getpid()}'
    log = Lines()
    with Hosts(str(os.getpid() % 100000), not args.without_peers) as hosts, ProcessGroup(stream=log) as group:
        group.say(f'[launch] tracker host {hosts.address["tracker"]} and mapper host '
                  f'{hosts.address["mapper"]}: '
                  f'{"no static peers" if args.without_peers else "static peers"}, '
                  'no multicast, UDPv4 only')
        mapping_graph(group, str(WORKSPACE / 'config' / 'mapping.yaml'), str(args.output),
                      'two_hosts', env=hosts.dds_environment('mapper', args.output),
                      prefix=hosts.prefix('mapper'))
        # The mapper's own link first, so that every point registered reaches the map.
        if not log.wait_for(r'registration/points: 1 subscriber', 30.0):
            group.say('[launch] occupancy_node did not subscribe within 30 s')
        tracker = hosts.dds_environment('tracker', args.output)
        group.start('emulator', ['liberty_emulator', '--port', port], tracker,
                    hosts.prefix('tracker'))
        group.start('driver', driver_command(str(WORKSPACE / 'config' / 'liberty_emulator.yaml'),
                                             port), tracker, hosts.prefix('tracker'))
        started = time.monotonic()
        if hosts.wait_for_stream(FLOWING, timeout=10.0 if args.without_peers else 30.0):
            group.say(f'[launch] poses flow into the mapper host '
                      f'{time.monotonic() - started:.1f} s after the driver started')
        else:
            group.say('[launch] no poses reached the mapper host')
        time.sleep(args.duration)
        group.say('[launch] stopping the tracker host; the mapper saves once it drained')
        group.stop_named('driver', 'emulator')
        time.sleep(2.0)   # what was in flight reaches the map
        carried = hosts.received_bytes('mapper')
        group.stop_all()   # SIGINT: the occupancy node saves what it has
    frames = log.number(r'stopped: (\d+) frames published')
    registered = log.number(r'stopped: (\d+) of \d+ fingertip positions registered')
    integrated = log.number(r'(\d+) points integrated')
    print(f'two_hosts: the driver published {frames} frames on the tracker host; the mapper '
          f'received {carried:,} bytes over the veth, registered {registered} fingertip '
          f'positions and integrated {integrated} into {args.output / "two_hosts.npz"}')
    saved = (args.output / 'two_hosts.npz').exists()
    ok = bool(frames and registered and integrated == registered and saved and
              carried > 100 * registered)
    print('two_hosts: ' + ('the map arrived' if ok else 'FAILED: the map did not arrive whole'))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
