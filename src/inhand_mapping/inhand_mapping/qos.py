"""QoS profiles shared by the mapping nodes.

The data path (poses in, registered points between the nodes) is reliable with KEEP_ALL
history: a reliable KEEP_ALL reader only acknowledges what it has room for, so a fast
publisher (``bag_replay --fast``) or a slow map update holds the sender back instead of
losing samples. Maps and the object frame are latched (transient-local, depth 1) so a
late subscriber gets the latest one. Map updates (changed cells, many a second) are
reliable and volatile: a viewer that joins late takes the latched map first.
"""

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['DATA_QOS', 'LATCHED_QOS', 'UPDATES_QOS']

DATA_QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_ALL,
                      reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
UPDATES_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
