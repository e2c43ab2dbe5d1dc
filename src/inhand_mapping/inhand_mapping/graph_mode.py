"""The graph's registration mode, asked from the node that publishes it.

One mode for the whole graph: the registration node's ``mode`` parameter (static or tracked).
A node that depends on it (the stereo node places its pairs by it, the exploration node knows
from it whether the object stands on a support, the occupancy node records it in the maps it
saves) looks for the publisher of the latched
``registration/object_frame`` every :data:`QUERY_PERIOD` seconds, asks that node for its
``mode`` over its ``get_parameters`` service, and once one answers calls back with the mode and
where it came from. :attr:`GraphModeQuery.source` says, for people, where things stand.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rcl_interfaces.srv import GetParameters
from rclpy.node import Node

from inhand_common.ros_clock import steady_timer

__all__ = ['MODES', 'QUERY_PERIOD', 'GraphModeQuery']

MODES = ('static', 'tracked')
QUERY_PERIOD = 0.5     # s between looks for the registration node
OBJECT_FRAME_TOPIC = 'registration/object_frame'


class GraphModeQuery:
    """Asks for the graph's mode until a node answers; ``on_mode(mode, source)`` once then."""

    def __init__(self, node: Node, on_mode: Callable[[str, str], None], period: float = QUERY_PERIOD):
        self.node = node
        self.on_mode = on_mode
        self.source = f'no node publishes {OBJECT_FRAME_TOPIC} yet'
        self._pending: Any = None
        # the steady clock: a node on sim time asks even before anything publishes /clock
        self._timer = steady_timer(node, period, self._ask)

    def _ask(self) -> None:
        if self._pending is not None:
            return
        topic = self.node.resolve_topic_name(OBJECT_FRAME_TOPIC)
        publishers = self.node.get_publishers_info_by_topic(topic)
        if not publishers:
            return
        info = publishers[0]
        name = f"{info.node_namespace.rstrip('/')}/{info.node_name}"
        client = self.node.create_client(GetParameters, f'{name}/get_parameters')
        if not client.service_is_ready():
            self.source = f'{name} (publishes {topic}) does not answer yet'
            self.node.destroy_client(client)
            return
        self._pending = client.call_async(GetParameters.Request(names=['mode']))
        self._pending.add_done_callback(lambda future: self._answered(name, client, future))

    def _answered(self, name: str, client: Any, future: Any) -> None:
        values = getattr(future.result(), 'values', None)
        mode = values[0].string_value if values else ''
        self.node.destroy_client(client)
        if mode not in MODES:
            self.source = f'{name} has no mode parameter'
            self._pending = None          # ask again (another node may take the topic)
            return
        self._timer.cancel()
        self.source = f'from {name}'
        self.on_mode(mode, name)
