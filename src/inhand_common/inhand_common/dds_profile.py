"""The Fast DDS profile every program of the graph runs with: camera images arrive.

Fast DDS (Jazzy's default RMW) hands a message to another process on the same machine
through the *writer's* shared-memory segment, 512 KiB by default; a larger message (a
640x480 rgb8 image is 921,600 bytes, the full 70^3 map's cloud 8.2 MB) goes over UDP on
loopback instead, cut into fragments, and a best-effort reader (the sensor-data QoS that
camera drivers use) loses the whole message when one fragment is dropped, which a socket's
default 208 KiB receive buffer does at once. Measured here (``benchmark.sh stereo-node``):
640x480 rgb8 images published best effort at 15 Hz for 60 s, 411 of 900 received with the
defaults, 900 of 900 with this profile. The profile gives:

* a shared-memory transport with a 32 MiB segment (``SHM_SEGMENT``): a few frames of a
  1280x720 rgb8 camera, or the map's cloud, in flight at once;
* UDPv4 with 4 MiB socket buffers (``UDP_BUFFER``) for other hosts; Linux caps them at
  ``net.core.rmem_max`` / ``wmem_max`` (often 208 KiB: raise them with sysctl on both
  hosts, as docs/stereo.md says).

Only the *publisher's* segment counts: a camera driver in its own process must run with
this profile too (``export FASTRTPS_DEFAULT_PROFILES_FILE=...`` with the file
``dds_profile`` writes), or its images stay on UDP whatever the graph does (measured: the
profile on the reader's side only, 413 of 900).

Nothing is done when the RMW is not Fast DDS or the user names a profiles file of their
own (FASTRTPS_DEFAULT_PROFILES_FILE or FASTDDS_DEFAULT_PROFILES_FILE): theirs is used as it
is. ``bag_replay`` adds a data-writer profile with a heartbeat every 20 ms: a reliable
reader acknowledges when a heartbeat asks (every 3 s by default), and a fast replay is
paced by acknowledgements.

A process whose messages are large and latched (``occupancy_node``: the full map's cloud is
8.2 MB) asks for *asynchronous publication* (``asynchronous=True``): ``publish`` copies the
message into the writer's history and returns, and Fast DDS's own thread copies it into the
reader's shared memory and wakes it. With one subscriber in another process, ``publish`` of
the 8.2 MB cloud took 3.9 ms synchronous and 2.0 ms asynchronous (``benchmark.sh
mapping``); the subscriber gets it as soon as before (6.2 vs 6.5 ms after the call began).
The graph's data path (poses, registered points, a replay paced by acknowledgements) stays
synchronous: there a message is small and the extra thread hop would only add latency.
The user's own ``RMW_FASTRTPS_PUBLICATION_MODE`` is left as it is.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ['PROFILES_VARIABLE', 'PUBLICATION_MODE_VARIABLE', 'SHM_SEGMENT', 'UDP_BUFFER',
           'profile_xml', 'shipped_profile']

PROFILES_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'
PUBLICATION_MODE_VARIABLE = 'RMW_FASTRTPS_PUBLICATION_MODE'   # rmw_fastrtps reads it at init
SHM_SEGMENT = 32 * 1024 * 1024
UDP_BUFFER = 4 * 1024 * 1024


def profile_xml(writer_heartbeat_ns: int | None = None) -> str:
    """The profile's XML; with a default data-writer heartbeat period when given (ns)."""
    writer = '' if writer_heartbeat_ns is None else f"""
  <data_writer profile_name="inhand_writer" is_default_profile="true">
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>{writer_heartbeat_ns}</nanosec></heartbeatPeriod>
    </times>
  </data_writer>"""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>inhand_shm</transport_id>
      <type>SHM</type>
      <segment_size>{SHM_SEGMENT}</segment_size>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>inhand_udp</transport_id>
      <type>UDPv4</type>
      <sendBufferSize>{UDP_BUFFER}</sendBufferSize>
      <receiveBufferSize>{UDP_BUFFER}</receiveBufferSize>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="inhand_participant" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>inhand_shm</transport_id>
        <transport_id>inhand_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>{writer}
</profiles>
"""


def _user_has_a_profile() -> bool:
    return bool(os.environ.get(PROFILES_VARIABLE) or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE'))


def _rmw_is_fastdds() -> bool:
    rmw = os.environ.get('RMW_IMPLEMENTATION', '') or 'rmw_fastrtps_cpp'  # Jazzy's default
    return rmw.startswith('rmw_fastrtps')


@contextlib.contextmanager
def shipped_profile(writer_heartbeat_ns: int | None = None, asynchronous: bool = False
                    ) -> Iterator[Path | None]:
    """``with shipped_profile():`` around a process's ROS session: the profile written to a
    temporary file and named in the environment until the block ends (Fast DDS reads it
    when the first participant is made); yields its path, or None when nothing was done.
    ``asynchronous``: the process's writers publish asynchronously (module doc), unless the
    user chose a publication mode."""
    if not _rmw_is_fastdds() or _user_has_a_profile():
        yield None
        return
    handle, name = tempfile.mkstemp(prefix='inhand_fastdds_', suffix='.xml')
    path = Path(name)
    with os.fdopen(handle, 'w') as out:
        out.write(profile_xml(writer_heartbeat_ns))
    os.environ[PROFILES_VARIABLE] = name
    mode_set = asynchronous and PUBLICATION_MODE_VARIABLE not in os.environ
    if mode_set:
        os.environ[PUBLICATION_MODE_VARIABLE] = 'ASYNCHRONOUS'
    try:
        yield path
    finally:
        path.unlink(missing_ok=True)
        if os.environ.get(PROFILES_VARIABLE) == name:
            del os.environ[PROFILES_VARIABLE]
        if mode_set:
            os.environ.pop(PUBLICATION_MODE_VARIABLE, None)
