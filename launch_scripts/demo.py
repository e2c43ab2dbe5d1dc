"""The main demo: the bundled non-static cat session through the whole graph.

Replays bags/cat_moving (a simulated exploration of a wooden-cat-like figure that moves and
is re-grasped by the other hand: 120 s at 15 Hz, the paper's rate, like the static cat in
bags/cat_static; 7,200 messages from thumb, index, middle and the object sensor, and one
stereo pair taken before the exploration; ground truth beside it) through
registration_node, occupancy_node and stereo_node over real DDS, as fast as the graph
keeps up (the replay itself is over in well under a second), saves the map (with the
colours of its occupied cells), renders the pictures with the rig's config/stereo.yaml
(so the stereo points, the textured map and their registration are among them), extracts
the map's shape (surface mesh, superquadric parts, the graspable part and its grasps:
cat_moving_shape.png, the paper's Fig. 1), predicts the surface where no finger went with
its uncertainty and where to touch next (cat_moving_uncertainty.png) and prints the
metrics. Everything lands in
output/demo/; the last line names the textured map's
picture. --view also starts live_view (the page at http://127.0.0.1:8080/, Foxglove at
ws://127.0.0.1:8765) and keeps the graph up after the save until Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from inhand_tools.launching import add_view_arguments
from replay_bag import WORKSPACE, replay

BAG = WORKSPACE / 'bags' / 'cat_moving'
OUTPUT = WORKSPACE / 'output' / 'demo'
STEREO_PICTURES = ('stereo_points.png', 'textured_map.png', 'texture_registration.png')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    add_view_arguments(parser)
    args = parser.parse_args(argv)
    if not BAG.exists():
        print(f'demo: {BAG} is missing; regenerate the bundled bags with '
              'bash launch_scripts/make_bags.sh', file=sys.stderr)
        return 2
    for name in (*STEREO_PICTURES, 'cat_moving_shape.png', 'cat_moving_uncertainty.png'):
        # only this run's are shown
        (OUTPUT / name).unlink(missing_ok=True)
    code = replay(BAG, WORKSPACE / 'config' / 'mapping.yaml', OUTPUT, 'cat_moving',
                  ['--fast'], view_args=args)
    if code != 0:
        return code
    shape = OUTPUT / 'cat_moving_shape.png'
    if shape.exists():
        print(f'[demo] surface mesh, superquadric parts, graspable part and grasps: {shape}',
              flush=True)
    guidance = OUTPUT / 'cat_moving_uncertainty.png'
    if guidance.exists():
        print(f'[demo] predicted surface, its uncertainty and where to touch next: {guidance}',
              flush=True)
    textured = OUTPUT / 'textured_map.png'
    if textured.exists():
        print(f'[demo] textured map: {textured}', flush=True)
    else:
        print('[demo] no textured map was drawn (render_map said why above)', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
