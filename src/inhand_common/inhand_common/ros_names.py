"""Names of the interface contract used by several packages: frames, and the topics built
from a station name.

Relative names (no leading slash), so namespaces and remapping apply. A bag stores them with
the leading slash of the absolute name; :func:`inhand_common.bag_source.relative_name`
strips it.
"""

from __future__ import annotations

__all__ = ['DEFAULT_OBJECT_STATION', 'MAP_FRAME', 'OBJECT_POSE_TOPIC', 'STEREO_FRAME',
           'TRACKER_FRAME', 'station_pose_topic']

# The tracker's transmitter frame (x forward, y right, z down, as the device defines it).
TRACKER_FRAME = 'polhemus_source'
# The map frame: the object sensor's body frame in tracked mode, the tracker frame's twin in
# static mode (see docs/mapping.md, frames).
MAP_FRAME = 'object'
# The left camera of the stereo pair, optical axes (z forward, x right, y down).
STEREO_FRAME = 'stereo_left_optical'

# The station name of the object sensor unless configured otherwise (the driver's
# station_names and the registration node's object_name).
DEFAULT_OBJECT_STATION = 'object'


def station_pose_topic(station: str) -> str:
    """The driver's PoseStamped topic of one station: ``polhemus/<station>/pose``."""
    return f'polhemus/{station}/pose'


OBJECT_POSE_TOPIC = station_pose_topic(DEFAULT_OBJECT_STATION)
