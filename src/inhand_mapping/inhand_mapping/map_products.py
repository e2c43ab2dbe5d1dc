"""What is made from a map for people and other nodes: clouds, the object frame, files.

Shared by the occupancy node and ``build_map`` so both publish and save the same things.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from inhand_common.atomic_file import atomic_file_set
from inhand_mapping.cloud_layouts import MapClouds
from inhand_mapping.map_io import GridColours, load_local_maps, load_npz, save_npz, save_ply
from inhand_mapping.object_frame import ObjectFrame, object_frame
from inhand_mapping.occupancy import OccupancyGrid

__all__ = ['MapProducts', 'save_map']


class MapProducts:
    def __init__(self, grid: OccupancyGrid, threshold: float):
        self.grid = grid
        self.threshold = threshold
        self._clouds: MapClouds | None = None  # two grid-sized buffers: made on first use

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """(touched cells, occupied cells) in the clouds.MAP_CELL_DTYPE layout: views of
        buffers reused by the next call. "Occupied" compares the float64 probability with
        the threshold, as OccupancyGrid.cells (the saved PLY) does."""
        if self._clouds is None:
            self._clouds = MapClouds(self.grid)
        return self._clouds(self.threshold)

    def occupied_on_faces(self, occupied: np.ndarray) -> int:
        """How many of ``occupied`` (the second of :meth:`cells`) lie in the grid's
        outermost layer: a map that reaches it may be cut off by a workspace too small."""
        centres = np.stack([occupied['x'], occupied['y'], occupied['z']], axis=1)
        return int(np.count_nonzero(self.grid.spec.on_faces(centres)))

    def object_frame(self) -> ObjectFrame | None:
        centres, probabilities, _, _ = self.grid.cells(threshold=self.threshold)
        return object_frame(centres, probabilities, self.threshold)


def save_map(grid: OccupancyGrid, folder: Path, name: str, threshold: float,
             frame_id: str = 'object', extra: dict | None = None, colours=None,
             textured=None, local_maps: dict | None = None) -> tuple[Path, ...]:
    """``<folder>/<name>.npz`` (the whole grid), ``<name>.ply`` (occupied cells) and, when
    there are occupied cells, ``<name>_object_centric.ply`` (the same cells in
    ``object_centric``: origin at the centre of mass), written atomically as one set (all
    replaced or none; without occupied cells an old ``_object_centric.ply`` is removed).

    The NPZ metadata also records the threshold and the object-centric frame. ``colours``
    (M, 3) RGB and ``textured`` (M,), both or neither, colour the occupied cells, in the
    order of ``grid.cells(threshold=threshold)`` (the order of ``MapProducts.cells()``'s
    occupied cells too): the NPZ gets them as grid arrays, both PLYs as ``red green blue
    textured`` (map_io's module doc). Without them the files are what they always were.
    """
    frame = MapProducts(grid, threshold).object_frame()
    info = dict(extra or {}, occupied_threshold=threshold)
    if frame is not None:
        info['object_centric'] = {'centre_of_mass': frame.centre_of_mass.tolist(),
                                  'principal_axes': frame.principal_axes.tolist(),
                                  'principal_extents': frame.principal_extents.tolist(),
                                  'occupied_cells': frame.cells}
    if (colours is None) != (textured is None):
        raise ValueError('save_map: colours and textured go together')
    folder = Path(folder)
    centres, probabilities, hits, first_touch = grid.cells(threshold=threshold)
    cell_colours = None if colours is None else \
        GridColours.from_cells(grid.spec, centres, colours, textured)
    centric = folder / f'{name}_object_centric.ply'
    # One set: all of it replaces the old files, or (a full disk) none of it does; a map
    # without occupied cells removes the old set's object-centric PLY.
    with atomic_file_set() as files:
        npz = save_npz(grid, folder / f'{name}.npz', frame_id=frame_id, extra=info,
                       colours=cell_colours, local_maps=local_maps, write=files.write)
        ply = save_ply(folder / f'{name}.ply', centres, probabilities, hits, first_touch,
                       frame_id=frame_id, colours=colours, textured=textured, write=files.write)
        if frame is None:
            files.remove(centric)
        else:
            save_ply(centric, frame.to_object_centric(centres), probabilities, hits,
                     first_touch, frame_id='object_centric', colours=colours,
                     textured=textured, write=files.write)
    return (npz, ply) if frame is None else (npz, ply, centric)


def resume_from(grid: OccupancyGrid, path: Path) -> str:
    """Start ``grid`` from a map saved by :func:`save_map` (``initial_map``): the touch map
    (the saved grid, or its touch local map when it was fused), its hits and first touches.
    ValueError, naming the file and what differs, for a file that is not a map or a map of
    another grid. Returns a line saying what was taken."""
    saved, metadata = load_npz(path)
    if saved.spec != grid.spec:
        raise ValueError(f'{path} is a map of {saved.spec.cells_per_axis}^3 cells of '
                         f'{saved.spec.resolution * 1000:g} mm centred at '
                         f'{list(saved.spec.centre)}; this node maps '
                         f'{grid.spec.cells_per_axis}^3 cells of {grid.spec.resolution * 1000:g}'
                         f' mm centred at {list(grid.spec.centre)} (workspace_size, resolution, '
                         'workspace_centre must match)')
    local = load_local_maps(path)
    grid.show(local.get('touch', saved.log_odds), saved)
    if 'touch' not in local and saved.touch_evidence is not None:
        grid.restore_touch_evidence(saved.touch_evidence, saved.judged)
    return (f'{int(saved.hits.sum())} hits in {int(np.count_nonzero(saved.hits))} cells from '
            f'{path}')
