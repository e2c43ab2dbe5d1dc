"""The frame names a node uses, as parameters: the defaults are the interface's
(``polhemus_source``, ``object``, ``object_centric``, ``stereo_left_optical``,
``fingertip_<name>``) and ``frame_prefix`` puts two hands side by side on one TF tree
(``left_hand/`` -> ``left_hand/object``, ...).

No rclpy here. A frame name is what tf2 accepts: no leading slash, segments of letters,
digits and underscores separated by single slashes.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from inhand_common.parameters import ParamSpec
from inhand_common.ros_names import MAP_FRAME, STEREO_FRAME, TRACKER_FRAME

__all__ = ['FRAME_PARAMETERS', 'OBJECT_CENTRIC_FRAME', 'FrameNames', 'frame_name_problem']

OBJECT_CENTRIC_FRAME = 'object_centric'
_FRAME = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')

FRAME_PARAMETERS = (
    ParamSpec('frame_prefix', '', "Prepended to every frame name this node uses (e.g. "
              "'left_hand/' for one of two hands); empty: the names as given"),
    ParamSpec('tracker_frame', TRACKER_FRAME, "The tracker's transmitter frame (the driver's "
              'frame_id without the prefix)'),
    ParamSpec('map_frame', MAP_FRAME, 'The map frame: the object sensor (tracked mode) or '
              "the tracker's twin (static mode)"),
)


def frame_name_problem(parameter: str, name: str) -> str | None:
    """Why ``name`` (given as ``parameter``) is not a valid frame name, or None."""
    if _FRAME.match(name):
        return None
    return (f'parameter {parameter!r} = {name!r} is not a valid frame name (letters, digits '
            "and '_', segments separated by single '/', no leading '/')")


@dataclass(frozen=True)
class FrameNames:
    """Every frame a node of the graph names, prefix applied."""

    prefix: str = ''
    tracker: str = TRACKER_FRAME
    map: str = MAP_FRAME

    def _full(self, name: str) -> str:
        return f'{self.prefix}{name}'

    @property
    def tracker_frame(self) -> str:
        return self._full(self.tracker)

    @property
    def map_frame(self) -> str:
        return self._full(self.map)

    @property
    def object_centric_frame(self) -> str:
        return self._full(OBJECT_CENTRIC_FRAME)

    @property
    def camera_frame(self) -> str:
        return self._full(STEREO_FRAME)

    def fingertip_frame(self, finger: str) -> str:
        return self._full(f'fingertip_{finger}')

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any], problems: list[str]) -> FrameNames:
        """From the FRAME_PARAMETERS values; each bad name adds a sentence to ``problems``."""
        names = cls(values.get('frame_prefix', ''), values.get('tracker_frame', TRACKER_FRAME),
                    values.get('map_frame', MAP_FRAME))
        for parameter, full in (('tracker_frame', names.tracker_frame),
                                ('map_frame', names.map_frame)):
            problem = frame_name_problem(parameter, full)
            if problem is not None:
                if names.prefix:
                    problem += f" (with frame_prefix {names.prefix!r}: {full!r})"
                problems.append(problem)
        return names
