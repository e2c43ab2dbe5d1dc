"""Parameters of the ``live_view`` node (plain Python, no ROS)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from inhand_common.parameters import ParamSpec
from inhand_view.view_state import ViewSettings

__all__ = ['VIEW_PARAMETERS', 'ViewConfig']

VIEW_PARAMETERS = (
    ParamSpec('host', '127.0.0.1', 'Address the page and the Foxglove WebSocket server listen '
              'on (127.0.0.1: this machine only; 0.0.0.0: every interface)'),
    ParamSpec('http_port', 8080, 'TCP port of the web page (http://host:http_port/)',
              minimum=1, maximum=65535),
    ParamSpec('foxglove_port', 8765, 'TCP port of the Foxglove WebSocket server '
              '(ws://host:foxglove_port)', minimum=1, maximum=65535),
    ParamSpec('trail_seconds', 3.0, 'Seconds of fingertip path the page draws behind each '
              'fingertip', minimum=0.0, maximum=120.0),
    ParamSpec('page_rate', 5.0, 'Times per second the page asks the node for news',
              minimum=0.1, maximum=30.0),
    ParamSpec('scan_period', 1.0, 'Seconds between looks at the graph for topics to forward '
              '(new ones, gone ones)', minimum=0.1, maximum=60.0),
    ParamSpec('finger_labels', ['thumb', 'index', 'middle'], 'Names shown for the fingers of '
              'registration/points, in the registration node\'s finger_names order',
              min_length=1),
    ParamSpec('explored_fraction', 0.1, 'The most explored region: this fraction of the hit '
              'cells, those with the most hits (render_map --top-fraction)',
              minimum=0.001, maximum=1.0),
    ParamSpec('max_cells', 100000, 'Most map cells the page draws (the most probable first)',
              minimum=1, maximum=10_000_000),
    ParamSpec('service_timeout', 30.0, 'Seconds a reset, save or shape extraction waits for '
              "its node's answer", minimum=0.1, maximum=600.0),
)


@dataclass(frozen=True)
class ViewConfig:
    host: str
    http_port: int
    foxglove_port: int
    scan_period: float
    service_timeout: float
    settings: ViewSettings

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any]) -> ViewConfig:
        return cls(values['host'], values['http_port'], values['foxglove_port'],
                   values['scan_period'], values['service_timeout'],
                   ViewSettings(trail_seconds=values['trail_seconds'],
                                explored_fraction=values['explored_fraction'],
                                max_cells=values['max_cells'],
                                finger_labels=tuple(values['finger_labels']),
                                page_rate=values['page_rate']))
