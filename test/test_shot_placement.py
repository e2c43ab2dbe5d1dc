"""Placing stereo shots on the object (shot_placement.py) while the graph's mode is learnt.

The stereo node follows the registration node's mode, which it learns a moment after it
starts; a fast replay has sent every object pose by then. The placer keeps the shots and
the object poses until the mode is known, then places them as if it had known all along.
The shots here carry only their stamp, the one thing placing reads.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from inhand_mapping.registration import Registrar
from inhand_stereo.shot_placement import (
    MAX_HELD,
    PlacedShot,
    ShotPlacer,
    UnplacedShot,
    waiting_advice,
)

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def shot(seconds: float):
    return SimpleNamespace(stamp_ns=int(seconds * 1e9))


def test_object_poses_before_the_mode_is_known_place_the_shot_once_it_is():
    placer = ShotPlacer(None)
    for t in np.arange(0.0, 2.0, 0.1):
        assert placer.add_object_pose(float(t), [float(t), 0.0, 0.0], IDENTITY) == []
    assert placer.add_shot(shot(1.05)) == [] and placer.mode is None
    (placed,) = placer.use(Registrar('tracked', 0.5))
    assert isinstance(placed, PlacedShot) and not placer.held
    assert abs(placed.object_pose[0] - 1.05) < 1e-9       # interpolated between 1.0 and 1.1


def test_static_mode_places_at_once_and_ignores_the_object_poses():
    placer = ShotPlacer(None)
    placer.add_object_pose(0.0, [0.3, 0.0, 0.0], IDENTITY)
    placer.add_shot(shot(5.0))
    (placed,) = placer.use(Registrar('static', 0.05))
    assert isinstance(placed, PlacedShot)
    assert np.array_equal(placed.object_pose, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def test_while_the_mode_is_unknown_only_the_newest_shots_wait_and_why_is_said():
    placer = ShotPlacer(None)
    given_up = []
    for k in range(MAX_HELD + 2):
        given_up += placer.add_shot(shot(float(k)))
    assert len(placer.held) == MAX_HELD and len(given_up) == 2
    assert all(isinstance(u, UnplacedShot) and 'mode was not known' in u.reason
               for u in given_up)
    reason, line = waiting_advice(None, 3.2, 0, 'polhemus/object/pose', 'no node publishes '
                                  'registration/object_frame yet')
    assert reason == 'mode not known' and 'Start the registration node' in line
    reason, line = waiting_advice('tracked', 4.0, 0, 'polhemus/object/pose', 'from /reg')
    assert reason == 'no object pose' and 'static mode' in line and '\n' not in line
