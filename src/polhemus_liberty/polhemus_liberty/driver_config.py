"""The driver's parameters: the table users set in ``config/*.yaml`` and its checks."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from inhand_common.frame_names import frame_name_problem
from inhand_common.parameters import ParameterError, ParamSpec
from inhand_common.ros_names import DEFAULT_OBJECT_STATION, TRACKER_FRAME
from polhemus_liberty.protocol import DEFAULT_OUTPUT_ITEMS, ITEMS, MAX_STATIONS, OutputList

__all__ = ['DRIVER_PARAMETERS', 'DriverConfig']

STANDARD_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')

DRIVER_PARAMETERS = (
    ParamSpec('port', '/dev/ttyUSB0', 'Serial device of the Liberty (RS-232 or USB-serial), '
              'or the emulator\'s pty link'),
    ParamSpec('baud', 115200, 'Serial speed in bit/s (8N1); the link budget check uses it',
              choices=STANDARD_BAUDS),
    ParamSpec('stations', [1, 2, 3, 4], 'Station numbers to publish, paired with '
              'station_names', minimum=1, maximum=MAX_STATIONS, min_length=1),
    ParamSpec('station_names', ['thumb', 'index', 'middle', DEFAULT_OBJECT_STATION],
              'Topic name of each station in stations: publishes polhemus/<name>/pose',
              min_length=1),
    ParamSpec('units', 'cm', 'Position units the device is set to (U1 = cm, U0 = inch); '
              'poses are published in metres either way', choices=('cm', 'inch')),
    ParamSpec('frame_rate', 240, 'Tracker frame rate in Hz (R4 = 240, R3 = 120)',
              choices=(120, 240)),
    ParamSpec('hemisphere', [1.0, 0.0, 0.0], 'Hemisphere of operation (H*,x,y,z); '
              '[0, 0, 0] turns on hemisphere tracking', minimum=-1.0, maximum=1.0, length=3),
    ParamSpec('output_format', 'binary', 'Device output format (F1 binary, F0 ASCII)',
              choices=('binary', 'ascii')),
    ParamSpec('output_items', list(DEFAULT_OUTPUT_ITEMS), 'Output item list (O*,...): must '
              'hold a position (2 or 3) and an orientation (7, 4, 5 or 6); add 9 to detect '
              'dropped frames and 11 to report distortion', minimum=0, maximum=max(ITEMS),
              min_length=2),
    ParamSpec('frame_id', TRACKER_FRAME, 'frame_id of the published poses (the '
              "transmitter frame; e.g. 'left_hand/polhemus_source' for one of two trackers)"),
    ParamSpec('latency_offset', 0.0, 'Seconds subtracted from the host receipt time to '
              'stamp a frame (device and transport latency)', minimum=0.0, maximum=1.0),
    ParamSpec('silence_timeout', 2.0, 'Seconds without a record before the reset sequence '
              '(CR, P, flush, set-up, C)', minimum=0.1, maximum=60.0),
    ParamSpec('reconnect_period', 1.0, 'Seconds between attempts to open a missing port',
              minimum=0.05, maximum=60.0),
)


@dataclass(frozen=True)
class DriverConfig:
    """Validated driver settings (see DRIVER_PARAMETERS for meanings)."""

    port: str
    baud: int
    stations: dict[int, str]
    units: str
    frame_rate: int
    hemisphere: tuple[float, float, float]
    binary: bool
    output_list: OutputList
    frame_id: str
    latency_offset: float
    silence_timeout: float
    reconnect_period: float

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any]) -> DriverConfig:
        """Build from validated parameter values; checks what spans several parameters."""
        problems = []
        stations, names = list(values['stations']), list(values['station_names'])
        if len(stations) != len(names):
            problems.append(f"parameters 'stations' ({len(stations)} entries) and "
                            f"'station_names' ({len(names)} entries) must pair up one to one")
        if len(set(stations)) != len(stations):
            problems.append(f"parameter 'stations' = {stations} repeats a station")
        if len(set(names)) != len(names):
            problems.append(f"parameter 'station_names' = {names} repeats a name")
        bad_names = [n for n in names if not _NAME.match(n)]
        if bad_names:
            problems.append(f"parameter 'station_names': {bad_names} are not valid topic "
                            'name tokens (letter first, then letters, digits, _)')
        try:
            output_list = OutputList(values['output_items'])
            if not (output_list.has_position and output_list.has_orientation):
                problems.append(f"parameter 'output_items' = {list(output_list.codes)} needs a "
                                'position item (2 or 3) and an orientation item (7, 4, 5 or 6)')
        except ValueError as error:
            problems.append(f"parameter 'output_items': {error}")
            output_list = None
        # tf2 takes no leading slash; one given (ROS 1 habit) is dropped.
        frame_problem = frame_name_problem('frame_id', values['frame_id'].lstrip('/'))
        if frame_problem is not None:
            problems.append(frame_problem)
        if not values['port']:
            problems.append("parameter 'port' must not be empty")
        if problems:
            raise ParameterError(problems)
        return cls(
            port=values['port'], baud=values['baud'], stations=dict(zip(stations, names)),
            units=values['units'], frame_rate=values['frame_rate'],
            hemisphere=tuple(values['hemisphere']), binary=values['output_format'] == 'binary',
            output_list=output_list, frame_id=values['frame_id'].lstrip('/'),
            latency_offset=values['latency_offset'], silence_timeout=values['silence_timeout'],
            reconnect_period=values['reconnect_period'])

    def bytes_per_second(self) -> float:
        """What the stream needs: rate x stations x record size (ASCII lines estimated)."""
        layout = self.output_list
        per_record = layout.record_size if self.binary else layout.ascii_line_size
        return float(self.frame_rate * len(self.stations) * per_record)
