"""Map files: NPZ (the whole grid and how it was made) and PLY (the occupied cells).

* NPZ holds log-odds, hit counts and first-touch times of every cell, with the grid
  geometry, the frame, the sensor-model parameters and the integration counters, so
  ``load_npz`` gives back the same map, ready to keep integrating (the fingers' current
  visits are not saved: after loading, every finger starts a new visit).
  Version 1 files (before dwell and visits) load with the model they were built with.
* PLY (binary little-endian) holds one vertex per cell with ``x y z`` (cell centre, float),
  ``intensity`` (occupancy probability) and the ``hits`` and ``first_touch`` scalar fields:
  CloudCompare, MeshLab, Open3D and PCL open it.

Both are written atomically (temporary file, then rename).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Records
from inhand_common.atomic_file import atomic_write
from inhand_mapping.occupancy import GridSpec, IntegrationCounts, OccupancyGrid, SensorModel

__all__ = ['FORMAT_VERSION', 'load_npz', 'read_ply', 'save_npz', 'save_ply']

FilePath: TypeAlias = str | os.PathLike[str]

FORMAT_VERSION = 2
SENSOR_MODEL_FIELDS = tuple(f.name for f in fields(SensorModel))
# Version 1 maps were built with every sample a full measurement and eq. 3 at cell centres.
VERSION_1_MODEL = {'distance_to': 'centre', 'evidence_rate': 0.0, 'visit_gap': 0.0}


def save_npz(grid: OccupancyGrid, path: FilePath, frame_id: str = 'object',
             extra: dict[str, Any] | None = None) -> Path:
    spec, model = grid.spec, grid.model
    metadata = {
        'format_version': FORMAT_VERSION, 'frame_id': frame_id,
        'size': spec.size, 'resolution': spec.resolution, 'centre': list(spec.centre),
        'origin': spec.origin.tolist(),
        **asdict(model),
        'counts': vars(grid.counts), 'extra': extra or {},
    }
    target = Path(path)
    with atomic_write(target) as stream:
        np.savez_compressed(stream, log_odds=grid.log_odds, hits=grid.hits,
                            first_touch=grid.first_touch,
                            metadata=np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8))
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
    # what numpy and zipfile raise for a foreign or damaged file, a missing key
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as error:
        raise ValueError(f'{path}: not a map saved by this software '
                         f'({type(error).__name__}: {error})') from None
    if metadata.get('format_version') == 1:
        metadata = {**VERSION_1_MODEL, **metadata, 'format_version': FORMAT_VERSION}
    if metadata.get('format_version') != FORMAT_VERSION:
        raise ValueError(f'{path}: map format {metadata.get("format_version")}, '
                         f'this software reads {FORMAT_VERSION}')
    spec = GridSpec(metadata['size'], metadata['resolution'], tuple(metadata['centre']))
    model = SensorModel(**{name: metadata[name] for name in SENSOR_MODEL_FIELDS})
    grid = OccupancyGrid(spec, model)
    if arrays['log_odds'].shape != spec.shape:
        raise ValueError(f'{path}: grid shape {arrays["log_odds"].shape} does not match '
                         f'its metadata {spec.shape}')
    grid.log_odds[...] = arrays['log_odds']
    grid.hits[...] = arrays['hits']
    grid.first_touch[...] = arrays['first_touch']
    grid.refresh()
    grid.counts = IntegrationCounts(**metadata['counts'])
    return grid, metadata


_PLY_FIELDS = [('x', '<f4', 'float'), ('y', '<f4', 'float'), ('z', '<f4', 'float'),
               ('intensity', '<f4', 'float'), ('hits', '<u4', 'uint'),
               ('first_touch', '<f8', 'double')]


def save_ply(path: FilePath, centres: ArrayLike, probabilities: ArrayLike, hits: ArrayLike,
             first_touch: ArrayLike, frame_id: str = 'object') -> Path:
    """Occupied cells as a binary PLY point cloud (see the module doc for the fields): centres
    (M, 3) and the three (M,) fields."""
    count = len(np.asarray(probabilities))
    vertices = np.empty(count, dtype=[(name, dtype) for name, dtype, _ in _PLY_FIELDS])
    xyz = np.asarray(centres).reshape(-1, 3)
    vertices['x'], vertices['y'], vertices['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertices['intensity'] = probabilities
    vertices['hits'] = hits
    vertices['first_touch'] = first_touch
    header = ['ply', 'format binary_little_endian 1.0',
              f'comment frame_id {frame_id}',
              'comment intensity = occupancy probability; first_touch in seconds (nan = none)',
              f'element vertex {count}']
    header += [f'property {ply_type} {name}' for name, _, ply_type in _PLY_FIELDS]
    header.append('end_header')
    target = Path(path)
    with atomic_write(target) as stream:
        stream.write(('\n'.join(header) + '\n').encode('ascii'))
        stream.write(vertices.tobytes())
    return target


_PLY_TYPES = {'float': '<f4', 'float32': '<f4', 'double': '<f8', 'float64': '<f8',
              'uchar': 'u1', 'uint8': 'u1', 'char': 'i1', 'int8': 'i1', 'ushort': '<u2',
              'uint16': '<u2', 'short': '<i2', 'int16': '<i2', 'uint': '<u4', 'uint32': '<u4',
              'int': '<i4', 'int32': '<i4'}


def read_ply(path: FilePath) -> Records:
    """Vertices of a binary little-endian PLY file with scalar properties (structured array)."""
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
            words = line.decode('ascii', 'replace').split()
            if not words:
                continue
            if words[0] == 'format':
                fmt = words[1]
            elif words[0] == 'element':
                if words[1] != 'vertex' or count is not None:
                    raise ValueError(f'{path}: only a single vertex element is supported')
                count = int(words[2])
            elif words[0] == 'property':
                if words[1] == 'list' or words[1] not in _PLY_TYPES:
                    raise ValueError(f'{path}: unsupported property {" ".join(words[1:])}')
                properties.append((words[2], _PLY_TYPES[words[1]]))
            elif words[0] == 'end_header':
                break
        if fmt != 'binary_little_endian':
            raise ValueError(f'{path}: PLY format {fmt}; only binary_little_endian is read')
        if count is None:
            raise ValueError(f'{path}: PLY header has no vertex element')
        dtype = np.dtype(properties)
        data = stream.read()
    if len(data) < count * dtype.itemsize:
        raise ValueError(f'{path}: truncated: {len(data) // dtype.itemsize} of {count} vertices')
    return np.frombuffer(data[:count * dtype.itemsize], dtype=dtype)
