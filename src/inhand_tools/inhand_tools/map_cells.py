"""A map as cells: from a saved map (NPZ, PLY) or a map cloud recorded in a bag.

* :class:`Lattice`: the cubic cells a map is made of (edge, corner of cell (0, 0, 0)), and
  :func:`cell_indices` of points on it; :func:`infer_lattice` finds it from cell centres
  (a PLY or a recorded cloud carries none).
* :class:`MapCells` and :func:`load_map`: the cells of the map in any of the supported
  files, with their probabilities, hit counts and first touch:

  - an NPZ saved by the occupancy node (``occupancy/save``) or ``build_map``: every
    touched cell, so any threshold can be evaluated;
  - a PLY saved beside it: only the cells above the threshold it was saved with;
  - a bag holding a recorded ``occupancy/cloud`` (every touched cell) or
    ``occupancy/occupied`` cloud: the last message, read through
    :class:`~inhand_common.bag_source.BagSource` (so a truncated MCAP is read up to the
    cut, and :attr:`MapCells.problem` says so).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inhand_common.bag_source import BagSource
from inhand_common.cell_lattice import Lattice, cell_indices, infer_lattice
from inhand_common.log_odds import probability as probability_of

__all__ = ['CLOUD_TOPICS', 'FusedMaps', 'Lattice', 'LocalMaps', 'MapCells', 'cell_indices',
           'infer_lattice', 'is_bag', 'load_fused_maps', 'load_local_cells', 'load_map']

CLOUD_TOPICS = ('occupancy/cloud', 'occupancy/occupied')
POINT_CLOUD2 = 'sensor_msgs/msg/PointCloud2'

# What numpy raises for a file that is not an NPZ archive (or is a damaged one).
_NOT_AN_ARCHIVE = (OSError, ValueError, EOFError, zipfile.BadZipFile)


@dataclass
class MapCells:
    """Cells of a map from any of the supported files, in the map's frame."""

    centres: np.ndarray         # (n, 3) float64, m
    probabilities: np.ndarray   # (n,)
    hits: np.ndarray            # (n,) (zeros if the file has none)
    first_touch: np.ndarray     # (n,) seconds since the map's earliest touch, NaN if never hit
    lattice: Lattice
    kind: str                   # 'npz', 'ply', 'bag cloud'
    source: str                 # what was read, for people
    complete: bool              # every touched cell (True) or only those above a threshold
    frame_id: str = 'object'
    metadata: dict = field(default_factory=dict)
    problem: str | None = None  # a damaged bag: what stopped the reading early
    colours: np.ndarray | None = None   # (n, 3) uint8 RGB from the camera, 0 where untextured
    textured: np.ndarray | None = None  # (n,) bool: the camera saw the cell (None: no colours)
    contact_centroids: np.ndarray | None = None  # (n, 3): where in each cell its hits were
    # (their mean; the centre where none): an NPZ's, None for a PLY or a cloud, which keep none
    layer: np.ndarray | None = None  # (n,): the surface layer's probability, where the cell
    # judge overrode it too (OccupancyGrid.layer_probabilities): an NPZ's or a map cloud's,
    # None for a PLY

    @property
    def has_colours(self) -> bool:
        return self.colours is not None and self.textured is not None

    @property
    def registration_mode(self) -> str | None:
        """The graph's registration mode the map was made in ('static', 'tracked'), as
        build_map and occupancy_node record it; None for a map that does not say."""
        mode = ((self.metadata or {}).get('extra') or {}).get('registration_mode')
        return str(mode) if mode is not None else None

    def describe(self) -> str:
        which = 'every touched cell' if self.complete else 'only the cells it was saved with'
        return (f'{self.source}: {len(self.centres)} cells ({which}), cell '
                f'{self.lattice.resolution * 1000:g} mm, frame {self.frame_id}')


@dataclass
class FusedMaps:
    """A map saved with fusion: the global map and the local maps it was fused from, as
    log-odds grids, and where each sensor updated the grid."""

    spec: object                  # the grid's GridSpec
    touch: np.ndarray
    vision: np.ndarray
    global_: np.ndarray
    touch_observed: np.ndarray    # bool grids: the cells each local map updated
    vision_observed: np.ndarray


def load_fused_maps(path) -> FusedMaps | None:
    """The maps of an NPZ saved with fusion, None for any other map file."""
    from inhand_mapping.map_io import load_local_maps, load_npz
    path = Path(path)
    if path.suffix != '.npz' or _is_truth_file(path):
        return None
    local = load_local_maps(path)
    if set(local) != {'touch', 'vision'}:
        return None
    grid, _ = load_npz(path)
    return FusedMaps(grid.spec, local['touch'], local['vision'], grid.log_odds,
                     local['touch'] != grid.prior_log_odds, local['vision'] != 0.0)


@dataclass
class LocalMaps:
    """The maps a fused NPZ was made from, and the global map, as cells any sensor updated:
    ``centres`` (n, 3) and each map's probability there (``touch``, ``vision``,
    ``global_``); 1/2 (or the prior) where that map says nothing."""

    centres: np.ndarray
    touch: np.ndarray
    vision: np.ndarray
    global_: np.ndarray


def load_local_cells(path) -> LocalMaps | None:
    """The local maps of a map saved with fusion as cells, None for any other map file."""
    fused = load_fused_maps(path)
    if fused is None:
        return None
    updated = fused.touch_observed | fused.vision_observed

    return LocalMaps(fused.spec.cell_centres(np.argwhere(updated)),
                     probability_of(fused.touch[updated]), probability_of(fused.vision[updated]),
                     probability_of(fused.global_[updated]))


def is_bag(path: Path) -> bool:
    """A bag folder (metadata.yaml, or an .mcap/.db3 inside) or a bare .mcap/.db3 file."""
    path = Path(path)
    if path.is_dir():
        return (path / 'metadata.yaml').exists() or any(path.glob('*.mcap')) or \
            any(path.glob('*.db3'))
    return path.suffix in ('.mcap', '.db3')


def load_map(path, resolution: float | None = None) -> MapCells:
    """The cells of the map at ``path`` (NPZ, PLY or a bag with a map cloud).

    ``resolution`` overrides the cell size inferred from a PLY or a cloud. ValueError with
    the reason for anything else.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f'{path}: no such map file or bag')
    if is_bag(path):
        return _read_bag_cloud(path, resolution)
    with open(path, 'rb') as stream:
        head = stream.read(4)
    if head[:3] == b'ply':
        return _read_ply(path, resolution)
    if head == b'PK\x03\x04' or path.suffix == '.npz':
        return _read_npz(path)
    raise ValueError(f'{path}: not a map: expected an NPZ saved by occupancy/save or '
                     'build_map, a PLY, or a bag with an occupancy cloud')


def _relative(first_touch) -> np.ndarray:
    first_touch = np.asarray(first_touch, dtype=float)
    finite = first_touch[np.isfinite(first_touch)]
    return first_touch - finite.min() if finite.size else first_touch


def _structured_cells(cells: np.ndarray, source: str, kind: str, complete: bool,
                      resolution: float | None, frame_id: str) -> MapCells:
    """MapCells of a structured array with x, y, z, intensity (and maybe hits and
    first_touch) fields: a PLY's vertices or a map cloud's points."""
    names = cells.dtype.names or ()
    missing = [name for name in ('x', 'y', 'z', 'intensity') if name not in names]
    if missing:
        raise ValueError(f'{source}: not a map cloud: no {", ".join(missing)} field(s) '
                         f'(has {", ".join(names) or "none"})')
    centres = np.stack([cells[a] for a in 'xyz'], axis=1).astype(np.float64)
    if len(centres) == 0:
        raise ValueError(f'{source}: the map has no cells')
    lattice = infer_lattice(centres, resolution)
    hits = cells['hits'].astype(np.int64) if 'hits' in names else np.zeros(len(cells), np.int64)
    first = cells['first_touch'] if 'first_touch' in names else np.full(len(cells), np.nan)
    colours = textured = None
    if all(name in names for name in ('red', 'green', 'blue', 'textured')):
        colours = np.stack([cells[c] for c in ('red', 'green', 'blue')], axis=1).astype(np.uint8)
        textured = cells['textured'].astype(bool)
    layer = cells['layer'].astype(np.float64) if 'layer' in names else None
    return MapCells(centres, cells['intensity'].astype(np.float64), hits, _relative(first),
                    lattice, kind, source, complete, frame_id, colours=colours,
                    textured=textured, layer=layer)


def _read_ply(path: Path, resolution: float | None) -> MapCells:
    from inhand_mapping.map_io import read_ply
    cells = read_ply(path)
    return _structured_cells(np.array(cells), str(path), 'ply', False, resolution, 'object')


def _is_truth_file(path: Path) -> bool:
    """Whether ``path`` is a ground-truth NPZ rather than a map (False for anything that
    is not an NPZ archive at all: ``load_npz`` says what it is)."""
    try:
        data = np.load(path, allow_pickle=False)
    except _NOT_AN_ARCHIVE:
        return False
    if not isinstance(data, np.lib.npyio.NpzFile):
        return False
    with data:
        return 'surface_points' in data.files and 'log_odds' not in data.files


def _read_npz(path: Path) -> MapCells:
    from inhand_mapping.map_io import load_colours, load_npz
    if _is_truth_file(path):
        raise ValueError(f'{path}: this is a ground-truth file, not a map: give it with '
                         '--truth')
    grid, metadata = load_npz(path)
    centres, probabilities, hits, first_touch = grid.cells()
    if len(centres) == 0:
        raise ValueError(f'{path}: the map has no touched cells')
    lattice = grid.spec.lattice()
    grid_colours = load_colours(path)
    colours, textured = (None, None) if grid_colours is None else \
        grid_colours.at(grid.spec, centres)
    return MapCells(centres, np.asarray(probabilities, dtype=float),
                    hits.astype(np.int64), _relative(first_touch), lattice, 'npz',
                    str(path), True, metadata.get('frame_id', 'object'), metadata,
                    colours=colours, textured=textured,
                    contact_centroids=grid.contact_centroids(),
                    layer=grid.layer_probabilities())


def _read_bag_cloud(bag: Path, resolution: float | None) -> MapCells:
    """The last map cloud of a bag (``occupancy/cloud`` if it has one, else
    ``occupancy/occupied``)."""
    with BagSource(bag) as source:
        topic = next((t for t in CLOUD_TOPICS if t in source.topics), None)
        if topic is None:
            raise ValueError(f'{bag}: no map cloud ({" or ".join(CLOUD_TOPICS)}) in this bag; '
                             f'it has {sorted(source.topics) or "no topics"}')
        msgtype = source.topics[topic].msgtype
        if msgtype != POINT_CLOUD2:
            raise ValueError(f'{bag}: {topic} is {msgtype}, expected {POINT_CLOUD2}')
        last = None
        for _, _, raw in source.messages({topic}):
            last = raw
        problem = source.problem
    if last is None:
        raise ValueError(f'{bag}: {topic} has no messages')
    cells, frame_id = _decode_cloud(last)
    map_cells = _structured_cells(cells, f'{bag} [{topic}, last message]', 'bag cloud',
                                  topic == 'occupancy/cloud', resolution, frame_id)
    map_cells.problem = problem
    return map_cells


def _decode_cloud(raw: bytes) -> tuple[np.ndarray, str]:
    """The points (a structured array) and frame id of a serialized PointCloud2."""
    from inhand_common.point_cloud import decode_point_cloud2
    cloud = decode_point_cloud2(raw)
    return np.array(cloud.points), cloud.frame_id or 'object'  # a copy: the bag's buffer goes away
