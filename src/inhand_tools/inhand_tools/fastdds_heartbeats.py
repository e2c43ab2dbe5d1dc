"""Fast DDS heartbeats every 20 ms instead of every 3 s, for this process's publishers.

A reliable reader acknowledges messages when a heartbeat asks it to, and Fast DDS sends
one every 3 s by default. ``bag_replay --fast`` is paced by acknowledgements and waits
for them before it destroys its publishers, so it asks for a heartbeat every 20 ms: a
default data-writer profile written to a temporary file and named in
FASTRTPS_DEFAULT_PROFILES_FILE before rclpy starts. Nothing is done when the RMW is not
Fast DDS or the user has a profiles file of their own.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ['HEARTBEAT_NS', 'fast_heartbeats']

HEARTBEAT_NS = 20_000_000
PROFILES_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'

FASTDDS_PROFILE = f"""<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="bag_replay_writer" is_default_profile="true">
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>{HEARTBEAT_NS}</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


def _user_has_a_profile() -> bool:
    return bool(os.environ.get(PROFILES_VARIABLE) or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE'))


def _rmw_is_fastdds() -> bool:
    rmw = os.environ.get('RMW_IMPLEMENTATION', '') or 'rmw_fastrtps_cpp'  # Jazzy's default
    return rmw.startswith('rmw_fastrtps')


@contextlib.contextmanager
def fast_heartbeats() -> Iterator[Path | None]:
    """``with fast_heartbeats():`` around ``rclpy.init``: the profile file (or None when
    nothing was done) exists and is named in the environment until the block ends."""
    if not _rmw_is_fastdds() or _user_has_a_profile():
        yield None
        return
    handle, name = tempfile.mkstemp(prefix='bag_replay_fastdds_', suffix='.xml')
    path = Path(name)
    with os.fdopen(handle, 'w') as out:
        out.write(FASTDDS_PROFILE)
    os.environ[PROFILES_VARIABLE] = name
    try:
        yield path
    finally:
        path.unlink(missing_ok=True)
        if os.environ.get(PROFILES_VARIABLE) == name:
            del os.environ[PROFILES_VARIABLE]
