"""The latest transform of every frame, and every frame's pose in a chosen frame (no ROS).

The graph publishes one ``geometry_msgs/TransformStamped`` per message (``transforms``,
``transforms_static``; ``/tf`` and ``/tf_static`` on a full ROS install): the pose of a child
frame in its parent, ``p_parent = R p_child + t``. :class:`FrameTree` keeps the newest of
each child and walks the tree both ways, so the page can draw every frame connected to the
one it draws in (``object``: the map's frame; ``polhemus_source``: the tracker's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inhand_common.rotations import quaternion_to_matrix

__all__ = ['FrameTree', 'Transform']


@dataclass(frozen=True)
class Transform:
    """``child`` in ``parent`` at ``stamp`` (s): translation (3,), quaternion (x, y, z, w)."""

    parent: str
    child: str
    stamp: float
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    static: bool = False

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix taking child coordinates to parent coordinates."""
        pose = np.eye(4)
        pose[:3, :3] = quaternion_to_matrix(np.asarray(self.rotation, dtype=float))
        pose[:3, 3] = self.translation
        return pose


class FrameTree:
    """The newest transform of each child frame (a frame has one parent: the latest wins)."""

    def __init__(self) -> None:
        self.transforms: dict[str, Transform] = {}
        self.received = 0
        self.refused = 0      # no child, its own parent, non-finite, or a zero quaternion

    def add(self, transform: Transform) -> bool:
        """Keep ``transform`` as its child's latest; False (and counted) if it is unusable."""
        self.received += 1
        values = np.array([*transform.translation, *transform.rotation], dtype=float)
        if not transform.child or transform.child == transform.parent or \
                not np.all(np.isfinite(values)) or np.linalg.norm(values[3:]) < 1e-9:
            self.refused += 1
            return False
        self.transforms[transform.child] = transform
        return True

    def clear(self) -> None:
        self.transforms.clear()

    def latest(self, child: str) -> Transform | None:
        return self.transforms.get(child)

    def poses_in(self, frame: str) -> dict[str, np.ndarray]:
        """Every frame connected to ``frame``, as its 4x4 pose in ``frame`` (``frame`` itself
        the identity; an empty dict when no transform names ``frame``)."""
        edges: dict[str, list[tuple[str, np.ndarray]]] = {}
        for transform in self.transforms.values():
            matrix = transform.matrix()
            edges.setdefault(transform.parent, []).append((transform.child, matrix))
            edges.setdefault(transform.child, []).append((transform.parent,
                                                          np.linalg.inv(matrix)))
        if frame not in edges:
            return {}
        poses = {frame: np.eye(4)}
        stack = [frame]
        while stack:
            here = stack.pop()
            for there, step in edges[here]:
                if there not in poses:
                    poses[there] = poses[here] @ step
                    stack.append(there)
        return poses
