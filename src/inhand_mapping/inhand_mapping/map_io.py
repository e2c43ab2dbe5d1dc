"""Map files: NPZ (the whole grid and how it was made) and PLY (the occupied cells).

* NPZ holds log-odds, hit counts and first-touch times of every cell, with the grid
  geometry, the frame, the sensor-model parameters and the integration counters, so
  ``load_npz`` gives back the same map, ready to keep integrating (the fingers' current
  visits are not saved: after loading, every finger starts a new visit). A path-model map
  also keeps ``touch_evidence``, its evidence before the surface layer (surface_layer.py),
  so that touches after loading go on from it exactly (an optional addition of format 2).
  ``contact_sum`` (n, n, n, 3) is the sum of the positions counted in each cell's hits
  (``OccupancyGrid.contact_centroids``: where in the cell the surface was touched; also
  optional: a map without it loads with its hits at their cells' centres).
  Version 1 files (before dwell and visits) load with the model they were built with.
* PLY (binary little-endian) holds one vertex per cell with ``x y z`` (cell centre, float),
  ``intensity`` (occupancy probability) and the ``hits`` and ``first_touch`` scalar fields:
  CloudCompare, MeshLab, Open3D and PCL open it.

Colour (the texture the stereo camera gives the occupied cells) is optional in both, and a
map without it is written exactly as before:

* NPZ: two more arrays of the grid's shape, ``rgb`` (n, n, n, 3) uint8 and ``textured``
  (n, n, n) bool (``GridColours``; 0 where not textured). Grid-sized rather than per
  occupied cell, so they need no cell list of their own and stay right whatever threshold
  a reader picks; compressed they cost next to nothing (mostly zeros). The format version
  stays 2: the arrays are an optional addition, a reader that predates them loads the map
  and ignores them, and ``load_colours`` gives None for a file without them.
* PLY: ``red green blue`` (uchar, the names MeshLab, CloudCompare and Open3D read as
  colour) and ``textured`` (uchar, 1 where the camera saw the cell; colour 0 elsewhere)
  after the other properties.

With fusion (``fusion.py``) the grid saved is the global map, and the NPZ also keeps the
local maps it was fused from: ``local_touch`` and ``local_vision`` (log-odds grids, the touch
map with the grid's prior, the vision map with 1/2), read by ``load_local_maps``; again an
optional addition of format 2.

Both are written atomically (temporary file, then rename).
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, BinaryIO, TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.array_types import Bools, Records
from inhand_common.atomic_file import atomic_write
from inhand_mapping.occupancy import GridSpec, IntegrationCounts, OccupancyGrid, SensorModel

__all__ = [
    'FORMAT_VERSION',
    'LOCAL_MAPS',
    'GridColours',
    'load_colours',
    'load_local_maps',
    'load_npz',
    'read_ply',
    'save_npz',
    'save_ply',
]

FilePath: TypeAlias = str | os.PathLike[str]
# Opens a file for writing as a context manager: atomic_write, or a FileSet's write.
Writer: TypeAlias = Callable[[FilePath], AbstractContextManager[BinaryIO]]

FORMAT_VERSION = 2
# What numpy, zipfile and zlib raise for a foreign or damaged file, or a missing key;
# RuntimeError: zipfile's "encrypted, password required" (a flipped flag bit) and its
# NotImplementedError for compression features it lacks.
_UNREADABLE = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error,
               RuntimeError)
# Version 1 maps were built with every sample a full measurement and eq. 3 at cell centres.
VERSION_1_MODEL = {'distance_to': 'centre', 'evidence_rate': 0.0, 'visit_gap': 0.0}
# Maps saved before the path model had samples as their only touch model.
BEFORE_PATH_MODEL = {'touch_model': 'samples'}
# Maps saved before the surface layer (surface_layer.py) were read without it, and their
# transits fell off with the square of the speed.
BEFORE_SURFACE_LAYER = {'layer_factor': 1.0, 'transit_falloff': 2.0, 'sheet_gain': 1.0}
# Maps saved before the cell judge (cell_judge.py) were read without it.
BEFORE_CELL_JUDGE = {'cell_judge': False}
Colours: TypeAlias = NDArray[np.uint8]     # (M, 3) RGB per cell
LOCAL_MAPS = ('touch', 'vision')            # the local maps an NPZ may keep beside the global


@dataclass(frozen=True, eq=False)
class GridColours:
    """Camera colour of every cell of a grid: ``rgb`` (n, n, n, 3) uint8 and ``textured``
    (n, n, n) bool, colour 0 where not textured."""

    rgb: NDArray[np.uint8]
    textured: Bools

    def __post_init__(self) -> None:
        shape = self.textured.shape
        if self.rgb.dtype != np.uint8 or self.textured.dtype != np.bool_ or \
                len(shape) != 3 or self.rgb.shape != (*shape, 3):
            raise ValueError(f'grid colours: rgb must be uint8 (n, n, n, 3) and textured bool '
                             f'(n, n, n), got {self.rgb.dtype} {self.rgb.shape} and '
                             f'{self.textured.dtype} {shape}')

    @classmethod
    def from_cells(cls, spec: GridSpec, centres: ArrayLike, colours: ArrayLike,
                   textured: ArrayLike) -> GridColours:
        """From per-cell colours (M, 3) and textured (M,) of the cells at ``centres``
        (M, 3, inside the grid); every other cell untextured. Colours where ``textured``
        is false are stored as 0."""
        ijk = _cell_indices(spec, centres)
        rgb_cells, mask = _cell_colours(colours, textured, len(ijk))
        rgb = np.zeros((*spec.shape, 3), dtype=np.uint8)
        seen = np.zeros(spec.shape, dtype=bool)
        rgb[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = rgb_cells
        seen[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = mask
        return cls(rgb, seen)

    def at(self, spec: GridSpec, centres: ArrayLike) -> tuple[Colours, Bools]:
        """(colours (M, 3) uint8, textured (M,)) of the cells at ``centres`` (M, 3)."""
        if self.textured.shape != spec.shape:
            raise ValueError(f'grid colours of shape {self.textured.shape} for a grid of '
                             f'{spec.shape}')
        ijk = _cell_indices(spec, centres)
        return (self.rgb[ijk[:, 0], ijk[:, 1], ijk[:, 2]],
                self.textured[ijk[:, 0], ijk[:, 1], ijk[:, 2]])


def _cell_indices(spec: GridSpec, centres: ArrayLike) -> NDArray[np.intp]:
    ijk = spec.cell_indices(centres)
    if not spec.holds(ijk).all():
        raise ValueError('cell centres outside the grid')
    return ijk


def _cell_colours(colours: ArrayLike, textured: ArrayLike, count: int
                  ) -> tuple[Colours, Bools]:
    """Per-cell colours (count, 3) uint8, 0 where not textured, and the mask (count,);
    ValueError when the sizes or the value range are wrong."""
    rgb = np.asarray(colours)
    mask = np.asarray(textured)
    if rgb.shape != (count, 3) or mask.shape != (count,):
        raise ValueError(f'colours must be ({count}, 3) and textured ({count},) for {count} '
                         f'cells, got {rgb.shape} and {mask.shape}')
    if rgb.size and (not np.issubdtype(rgb.dtype, np.integer) or rgb.min() < 0 or rgb.max() > 255):
        raise ValueError('colours must be integers in [0, 255]')
    seen = mask.astype(bool)
    return np.where(seen[:, None], rgb, 0).astype(np.uint8), seen


def save_npz(grid: OccupancyGrid, path: FilePath, frame_id: str = 'object',
             extra: dict[str, Any] | None = None, colours: GridColours | None = None,
             local_maps: dict[str, NDArray[np.float64]] | None = None,
             write: Writer = atomic_write) -> Path:
    """The grid, its model and metadata (module doc); ``colours`` adds the ``rgb`` and
    ``textured`` arrays, ``local_maps`` (names from LOCAL_MAPS -> log-odds grids) the local
    maps the grid was fused from. ``write`` opens the file (atomically; a FileSet's
    ``write`` makes it one of a set)."""
    spec, model = grid.spec, grid.model
    if colours is not None and colours.textured.shape != spec.shape:
        raise ValueError(f'grid colours of shape {colours.textured.shape} for a grid of '
                         f'{spec.shape}')
    for name, local in (local_maps or {}).items():
        if name not in LOCAL_MAPS or local.shape != spec.shape:
            raise ValueError(f'local map {name!r} of shape {local.shape}: expected one of '
                             f'{LOCAL_MAPS} of shape {spec.shape}')
    metadata = {
        'format_version': FORMAT_VERSION, 'frame_id': frame_id,
        'size': spec.size, 'resolution': spec.resolution, 'centre': list(spec.centre),
        'origin': spec.origin.tolist(),
        **asdict(model),
        'counts': vars(grid.counts), 'extra': extra or {},
    }
    encoded = np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8)
    target = Path(path)
    arrays: dict[str, NDArray[Any]] = {'log_odds': grid.log_odds, 'hits': grid.hits,
                                       'first_touch': grid.first_touch,
                                       'contact_sum': grid.contact_sum, 'metadata': encoded}
    if colours is not None:
        arrays.update(rgb=colours.rgb, textured=colours.textured)
    for name, local in (local_maps or {}).items():
        arrays[f'local_{name}'] = local
    # The path model's evidence before the surface layer, so that a map resumed from this
    # file goes on exactly (the layered log-odds would be layered again); a fused grid's
    # evidence is not the touch map's, and its file keeps the touch map's log-odds only.
    if grid.touch_evidence is not None and 'touch' not in (local_maps or {}):
        arrays['touch_evidence'] = grid.touch_evidence
    # and where the cell judge overrode the layer, with what it replaced: resumed, the
    # map goes on from the layer's values there (occupancy.OccupancyGrid.judged); a fused
    # map's are the fusion of the touch map's layer there (global_map.GlobalMap.grid)
    judged = grid.judged
    if judged is not None and ('touch_evidence' in arrays or len(judged[0])):
        arrays['judged_cells'], arrays['judged_rules'] = judged
    with write(target) as stream:
        np.savez_compressed(stream, **arrays)  # type: ignore[arg-type]
    return target


def load_npz(path: FilePath) -> tuple[OccupancyGrid, dict[str, Any]]:
    """The grid saved by :func:`save_npz` and its metadata; ValueError if it is not one."""
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError('a single array, not an NPZ archive')
        with data:
            metadata: dict[str, Any] = json.loads(bytes(data['metadata']).decode())
            arrays = {k: data[k] for k in ('log_odds', 'hits', 'first_touch')}
            for optional in ('touch_evidence', 'contact_sum', 'judged_cells', 'judged_rules'):
                # absent from earlier maps
                if optional in data.files:
                    arrays[optional] = data[optional]
    except _UNREADABLE as error:
        raise ValueError(f'{path}: not a map saved by this software '
                         f'({type(error).__name__}: {error})') from None
    if not isinstance(metadata, dict):
        raise ValueError(f'{path}: not a map saved by this software (its metadata is a '
                         f'{type(metadata).__name__}, not a mapping)')
    if metadata.get('format_version') == 1:
        metadata = {**VERSION_1_MODEL, **metadata, 'format_version': FORMAT_VERSION}
    if metadata.get('format_version') != FORMAT_VERSION:
        raise ValueError(f'{path}: map format {metadata.get("format_version")}, '
                         f'this software reads {FORMAT_VERSION}')
    try:
        grid = _grid_of(metadata, arrays)
    # what a damaged or foreign metadata entry makes the constructors raise (arithmetic:
    # a value that passes the checks and still breaks a formula)
    except (TypeError, ValueError, KeyError, ArithmeticError) as error:
        raise ValueError(f'{path}: damaged map ({error})') from None
    return grid, metadata


def _typed(name: str, value: Any, default: Any) -> Any:
    """A sensor-model value from a file, of its field's type (an int where a float goes)."""
    if isinstance(default, float) and type(value) is int:
        value = float(value)
    if type(value) is not type(default) or (isinstance(value, float) and not math.isfinite(value)):
        raise ValueError(f'{name} is {value!r}, expected a finite {type(default).__name__}')
    return value


def _grid_of(metadata: dict[str, Any], arrays: dict[str, NDArray[Any]]) -> OccupancyGrid:
    """The grid the metadata and arrays of a map file describe; ValueError, TypeError or
    KeyError when they do not fit together. Shapes and kinds are checked before the grid
    is allocated, so a damaged size cannot ask for more memory than the file holds."""
    centre = [float(v) for v in metadata['centre']]
    if len(centre) != 3:
        raise ValueError(f'centre {centre} is not 3 coordinates')
    spec = GridSpec(float(metadata['size']), float(metadata['resolution']),
                    (centre[0], centre[1], centre[2]))
    kinds = {'log_odds': 'f', 'hits': 'ui', 'first_touch': 'f', 'touch_evidence': 'f',
             'contact_sum': 'f', 'judged_cells': 'ui', 'judged_rules': 'f'}
    judged = [arrays.pop(name) for name in ('judged_cells', 'judged_rules') if name in arrays]
    if len(judged) == 2:
        for name, array in zip(('judged_cells', 'judged_rules'), judged):
            if array.ndim != 1 or array.dtype.kind not in kinds[name]:
                raise ValueError(f'{name} is {array.dtype} {array.shape}, not a list')
    else:
        judged = []       # a half: the verdicts are made again, from the evidence
    for name, array in arrays.items():
        shape = (*spec.shape, 3) if name == 'contact_sum' else spec.shape
        if array.shape != shape or array.dtype.kind not in kinds[name]:
            raise ValueError(f'{name} is {array.dtype} {array.shape}, the metadata says a '
                             f'{spec.shape} grid')
    if np.isnan(arrays['log_odds']).any():
        raise ValueError('log_odds holds NaN')
    for name in ('touch_evidence', 'contact_sum'):
        if name in arrays and not np.isfinite(arrays[name]).all():
            raise ValueError(f'{name} holds NaN or infinity')
    if arrays['hits'].size and (arrays['hits'].min() < 0 or
                                arrays['hits'].max() > np.iinfo(np.uint32).max):
        raise ValueError('hits outside 0..2^32-1')
    # The path model's parameters, absent from earlier maps, take their defaults.
    known = {**BEFORE_PATH_MODEL, **BEFORE_SURFACE_LAYER, **BEFORE_CELL_JUDGE, **metadata}
    model = SensorModel(**{field.name: _typed(field.name, known[field.name], field.default)
                           for field in fields(SensorModel) if field.name in known})
    counts = IntegrationCounts(**metadata['counts'])
    if not all(isinstance(v, int) and v >= 0 for v in vars(counts).values()):
        raise ValueError(f'counts {vars(counts)} are not counts')
    grid = OccupancyGrid(spec, model)
    grid.log_odds[...] = arrays['log_odds']
    grid.hits[...] = arrays['hits']
    grid.first_touch[...] = arrays['first_touch']
    if 'contact_sum' in arrays:
        grid.contact_sum[...] = arrays['contact_sum']
    else:       # a map from before the sums: its hits count at their cells' centres
        hit = np.argwhere(grid.hits > 0)
        grid.contact_sum[tuple(hit.T)] = spec.cell_centres(hit) * grid.hits[tuple(hit.T)][:, None]
    grid.refresh()
    if 'touch_evidence' in arrays:
        grid.restore_touch_evidence(arrays['touch_evidence'],
                                    (judged[0], judged[1]) if judged else None)
    elif judged:        # a fused map: its layer where the touch map's judge overrode
        grid.hold_layer(judged[0], judged[1])
    grid.counts = counts
    return grid


def load_local_maps(path: FilePath) -> dict[str, NDArray[np.float64]]:
    """The local maps saved beside the global one (LOCAL_MAPS names -> log-odds grids);
    empty for a map saved without fusion. ValueError if it is not a map."""
    grid, _ = load_npz(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            local = {name: np.asarray(data[f'local_{name}'], dtype=np.float64)
                     for name in LOCAL_MAPS if f'local_{name}' in data.files}
    except _UNREADABLE as error:
        raise ValueError(f'{path}: its local maps cannot be read '
                         f'({type(error).__name__}: {error})') from None
    for name, values in local.items():
        if values.shape != grid.spec.shape:
            raise ValueError(f'{path}: local map {name} of shape {values.shape} for a grid '
                             f'of {grid.spec.shape}')
    return local


def load_colours(path: FilePath) -> GridColours | None:
    """The cell colours saved with the map at ``path``, None when it has none; ValueError
    if it is not a map or its colours do not fit its grid."""
    grid, _ = load_npz(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            if 'rgb' not in data.files:
                return None
            rgb, textured = data['rgb'], data['textured']
    except _UNREADABLE as error:
        raise ValueError(f'{path}: its colours cannot be read '
                         f'({type(error).__name__}: {error})') from None
    try:
        colours = GridColours(rgb, textured)
    except ValueError as error:
        raise ValueError(f'{path}: {error}') from None
    if textured.shape != grid.spec.shape:
        raise ValueError(f'{path}: colours of shape {textured.shape} for a grid of '
                         f'{grid.spec.shape}')
    return colours


_PLY_FIELDS = [('x', '<f4', 'float'), ('y', '<f4', 'float'), ('z', '<f4', 'float'),
               ('intensity', '<f4', 'float'), ('hits', '<u4', 'uint'),
               ('first_touch', '<f8', 'double')]
_PLY_COLOUR_FIELDS = [('red', 'u1', 'uchar'), ('green', 'u1', 'uchar'), ('blue', 'u1', 'uchar'),
                      ('textured', 'u1', 'uchar')]


def save_ply(path: FilePath, centres: ArrayLike, probabilities: ArrayLike, hits: ArrayLike,
             first_touch: ArrayLike, frame_id: str = 'object', colours: ArrayLike | None = None,
             textured: ArrayLike | None = None, write: Writer = atomic_write) -> Path:
    """Occupied cells as a binary PLY point cloud (see the module doc for the fields): centres
    (M, 3) and the three (M,) fields; with ``colours`` (M, 3) RGB and ``textured`` (M,)
    (both or neither) also ``red green blue textured``."""
    count = len(np.asarray(probabilities))
    if (colours is None) != (textured is None):
        raise ValueError('save_ply: colours and textured go together')
    properties = _PLY_FIELDS + (_PLY_COLOUR_FIELDS if colours is not None else [])
    vertices = np.empty(count, dtype=[(name, dtype) for name, dtype, _ in properties])
    xyz = np.asarray(centres).reshape(-1, 3)
    vertices['x'], vertices['y'], vertices['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertices['intensity'] = probabilities
    vertices['hits'] = hits
    vertices['first_touch'] = first_touch
    comments = ['comment intensity = occupancy probability; first_touch in seconds (nan = none)']
    if colours is not None and textured is not None:
        rgb, seen = _cell_colours(colours, textured, count)
        vertices['red'], vertices['green'], vertices['blue'] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        vertices['textured'] = seen
        comments.append('comment red green blue = camera colour where textured = 1, else 0')
    header = ['ply', 'format binary_little_endian 1.0', f'comment frame_id {frame_id}',
              *comments, f'element vertex {count}']
    header += [f'property {ply_type} {name}' for name, _, ply_type in properties]
    header.append('end_header')
    target = Path(path)
    with write(target) as stream:
        stream.write(('\n'.join(header) + '\n').encode('ascii'))
        stream.write(vertices.tobytes())
    return target


_PLY_TYPES = {'float': '<f4', 'float32': '<f4', 'double': '<f8', 'float64': '<f8',
              'uchar': 'u1', 'uint8': 'u1', 'char': 'i1', 'int8': 'i1', 'ushort': '<u2',
              'uint16': '<u2', 'short': '<i2', 'int16': '<i2', 'uint': '<u4', 'uint32': '<u4',
              'int': '<i4', 'int32': '<i4'}


def read_ply(path: FilePath) -> Records:
    """Vertices of a binary little-endian PLY file with scalar properties (structured array).

    ValueError naming the file and what is wrong for anything else: another format, a list
    property, a damaged header line, fewer vertices than the header promises.
    """
    with open(path, 'rb') as stream:
        if stream.readline().strip() != b'ply':
            raise ValueError(f'{path}: not a PLY file')
        properties: list[tuple[str, str]] = []
        count: int | None = None
        fmt: str | None = None
        while True:
            line = stream.readline()
            if not line:
                raise ValueError(f'{path}: PLY header has no end_header')
            raw_words = line.split()
            if not raw_words or raw_words[0] in (b'comment', b'obj_info'):
                continue  # free text (other writers put UTF-8 there)
            try:
                words = [word.decode('ascii') for word in raw_words]
            except UnicodeDecodeError:
                words = []
            # Control characters inside a word: damage (other readers split at some).
            if not words or not all(word.isprintable() for word in words):
                raise ValueError(f'{path}: damaged PLY header line {line[:60]!r}')
            if words[0] == 'end_header':
                break
            if words[0] == 'format' and len(words) == 3 and words[2] == '1.0' and \
                    fmt is None and count is None:
                fmt = words[1]
            elif words[0] == 'element' and len(words) == 3 and fmt is not None:
                if words[1] != 'vertex' or count is not None:
                    raise ValueError(f'{path}: only a single vertex element is supported')
                count = int(words[2]) if words[2].isdigit() else -1
                if count < 0:
                    raise ValueError(f'{path}: vertex count {words[2]!r} is not a number')
            elif words[0] == 'property' and len(words) >= 3 and count is not None:
                name = words[-1]
                if words[1] == 'list' or words[1] not in _PLY_TYPES or len(words) != 3:
                    raise ValueError(f'{path}: unsupported property {" ".join(words[1:])}')
                if name in (known for known, _ in properties):
                    raise ValueError(f'{path}: property {name} appears twice')
                properties.append((name, _PLY_TYPES[words[1]]))
            else:
                raise ValueError(f'{path}: damaged PLY header line {line[:60]!r}')
        if fmt != 'binary_little_endian':
            raise ValueError(f'{path}: PLY format {fmt}; only binary_little_endian is read')
        if count is None or not properties:
            raise ValueError(f'{path}: PLY header has no vertex element with properties')
        dtype = np.dtype(properties)
        data = stream.read()
    if len(data) < count * dtype.itemsize:
        raise ValueError(f'{path}: truncated: {len(data) // dtype.itemsize} of {count} vertices')
    return np.frombuffer(data[:count * dtype.itemsize], dtype=dtype)
