"""Log when a data topic's other end connects or goes away.

A volatile reliable topic delivers only what is published after both ends matched, and
discovery matches each topic on its own, in a second or more on a loaded machine. A line
per match ("polhemus/thumb/pose: 1 publisher(s)") tells a user that the driver reached
the node (or vanished), and lets a script or a test start its data once every topic of a
node is connected rather than after a guessed pause.
"""

from __future__ import annotations

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node

__all__ = ['logged_publisher_matches', 'logged_subscription_matches', 'match_line']


def match_line(topic: str, count: int, other_end: str) -> str:
    """The line logged for a match: ``topic: N publisher(s)`` or ``N subscriber(s)``."""
    return f'{topic}: {count} {other_end}(s)'


def logged_subscription_matches(node: Node, topic: str) -> SubscriptionEventCallbacks:
    """Event callbacks for a subscription that log its publishers as they come and go."""
    return SubscriptionEventCallbacks(matched=lambda status: node.get_logger().info(
        match_line(topic, status.current_count, 'publisher')))


def logged_publisher_matches(node: Node, topic: str) -> PublisherEventCallbacks:
    """Event callbacks for a publisher that log its subscribers as they come and go."""
    return PublisherEventCallbacks(matched=lambda status: node.get_logger().info(
        match_line(topic, status.current_count, 'subscriber')))
