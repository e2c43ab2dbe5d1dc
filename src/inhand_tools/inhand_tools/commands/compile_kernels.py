"""``compile_kernels``: compile every numba kernel of the mapping graph into its cache, once.

    compile_kernels [--quiet]

numba compiles a kernel on its first call and keeps the machine code in its cache (the
``__pycache__`` folders beside the sources, or ``NUMBA_CACHE_DIR``); a later process loads
it in well under a second. Without this, the first ``build_map``, ``occupancy_node`` or
``stereo_node`` on a machine waits about 25 s for the compiler. ``bootstrap.sh`` runs it
after installing, so the first start after the README's set-up is as quick as any other.

What it runs is what the programs run, on scratch data (the kernels' argument types do
not depend on the sizes): the occupancy update of both touch models with its surface
layer (``occupancy.warm_up``) and the gathering of the map's cells, the fusion of a touch
and a vision map by every fusion and pooling (``fusion.fuse``), and one exposure of the
vision map with the scene segmentation that precedes it (``vision_model.warm_up``,
``scene_segmentation.warm_up``), and the texture of a map (``texture.warm_up``).
``benchmark.sh startup`` checks that a build_map and both nodes then compile nothing.
Exit status 0, or 1 when a kernel fails to compile (the message says which).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from inhand_common.cli_types import command_parser
from inhand_mapping.cloud_layouts import map_cells
from inhand_mapping.fusion import FUSIONS, POOLINGS, fuse
from inhand_mapping.mapping_config import load_parameters
from inhand_mapping.occupancy import TOUCH_MODELS, GridSpec, OccupancyGrid
from inhand_mapping.occupancy import warm_up as warm_up_occupancy
from inhand_stereo.scene_segmentation import warm_up as warm_up_segmentation
from inhand_stereo.stereo_config import load_stereo_config
from inhand_stereo.texture import warm_up as warm_up_texture
from inhand_stereo.vision_model import warm_up as warm_up_vision

PROG = 'compile_kernels'


def _occupancy() -> None:
    for touch_model in TOUCH_MODELS:
        overrides: dict = {'touch_model': touch_model}
        if touch_model != 'path':
            overrides['neighbourhood'] = 27
        _, occupancy = load_parameters(None, overrides)
        resolution = occupancy.grid.resolution
        warm_up_occupancy(occupancy.model, resolution)
        # the cells gathered for the published clouds and the saved map
        map_cells(OccupancyGrid(GridSpec(size=8 * resolution, resolution=resolution),
                                occupancy.model), 0.8)


def _fusion() -> None:
    _, occupancy = load_parameters(None, {})
    spec = GridSpec(size=8 * occupancy.grid.resolution, resolution=occupancy.grid.resolution)
    touch = OccupancyGrid(spec, occupancy.model).log_odds
    vision = np.zeros(spec.shape)
    for fusion in FUSIONS:
        for pooling in POOLINGS:
            for radius in (0, 1):
                fuse(fusion, touch, vision, occupancy.log_odds_clamp, radius, pooling)


def _vision() -> None:
    config = load_stereo_config((), {})
    warm_up_vision(config.vision, config.grid.resolution)
    warm_up_segmentation(config.grid, config.segmentation)
    warm_up_texture()


STEPS = (('occupancy update and surface layer', _occupancy), ('fusion', _fusion),
         ('vision map, scene segmentation and texture', _vision))


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('--quiet', action='store_true', help='print nothing but errors')
    args = parser.parse_args(argv)
    started = time.monotonic()
    for name, step in STEPS:
        begun = time.monotonic()
        try:
            step()
        except Exception as error:   # say which kernel, then fail
            print(f'{PROG}: the {name} kernels did not compile: {error}', file=sys.stderr)
            return 1
        if not args.quiet:
            print(f'{PROG}: {name}: {time.monotonic() - begun:.1f} s')
    if not args.quiet:
        print(f'{PROG}: ready in {time.monotonic() - started:.1f} s (cached for every later run)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
