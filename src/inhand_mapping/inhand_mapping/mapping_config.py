"""Parameters of the registration and occupancy nodes, shared with ``build_map``.

One table per node; ``build_map`` reads the same sections of the same YAML file and
builds the same objects through the same functions, so a bag processed offline gives the
map the nodes would have built.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from inhand_common.frame_names import FRAME_PARAMETERS, FrameNames
from inhand_common.machine_memory import available_memory, human_bytes
from inhand_common.parameters import (
    ParameterError,
    ParamSpec,
    load_yaml_parameters,
    unknown_parameter,
    validate,
)
from inhand_common.ros_names import DEFAULT_OBJECT_STATION, station_pose_topic
from inhand_mapping.fusion import ENTROPY_POOLING, ENTROPY_RADIUS, FUSIONS, POOLINGS
from inhand_mapping.occupancy import DISTANCES, TOUCH_MODELS, GridSpec, OccupancyGrid, SensorModel
from inhand_mapping.registration import Registrar
from inhand_mapping.tip_offsets import (
    MAX_PAD_RADIUS,
    MAX_TIP_OFFSET,
    TipOffsets,
    tip_offsets_problem,
)

__all__ = ['OCCUPANCY_PARAMETERS', 'REGISTRATION_PARAMETERS', 'OccupancyConfig',
           'RegistrationConfig', 'load_parameters', 'parse_overrides']

REGISTRATION_PARAMETERS = (
    ParamSpec('mode', 'tracked', 'tracked: an object sensor is present and the map frame '
              'is its frame; static: no object sensor, the map frame is the tracker frame',
              choices=('tracked', 'static')),
    ParamSpec('object_name', DEFAULT_OBJECT_STATION, 'Station name of the object sensor '
              '(subscribes polhemus/<object_name>/pose in tracked mode)'),
    ParamSpec('finger_names', ['thumb', 'index', 'middle'], 'Station names of the fingertip '
              'sensors (subscribes polhemus/<name>/pose)', min_length=1),
    ParamSpec('tip_offsets', [0.0, 0.0, 0.0], 'Finger pad centre in each fingertip '
              "sensor's own frame (m): x, y, z per finger in the order of finger_names, or one "
              'x, y, z for all (from calibrate_fingertips; 0: the sensor is the contact point)',
              minimum=-MAX_TIP_OFFSET, maximum=MAX_TIP_OFFSET, min_length=3),
    ParamSpec('pad_radius', 0.0, 'Radius of the finger pads (m): the contact is this far from '
              'the pad centre, along the normal of the surface the pad centres have traced '
              '(the way the pad faces where none is traced yet; 0: the pad centre is the '
              'contact point)',
              minimum=0.0, maximum=MAX_PAD_RADIUS),
    ParamSpec('max_gap', 0.05, 'Longest gap (s) between two object poses to interpolate '
              'across; fingertips in longer gaps are dropped, never extrapolated',
              minimum=0.001, maximum=5.0),
    ParamSpec('max_pending', 2.0, 'Seconds (wall clock) a fingertip may wait for an object '
              'pose at or after its stamp before it is dropped, and a silent finger stream '
              'may hold back the time-ordered output', minimum=0.01, maximum=60.0),
    ParamSpec('publish_period', 0.05, 'Seconds between registration/points messages '
              '(registered points are batched)', minimum=0.001, maximum=5.0),
    *FRAME_PARAMETERS,
)

OCCUPANCY_PARAMETERS = (
    ParamSpec('workspace_size', 0.35, 'Edge of the mapped cube (m); a whole number of cells',
              minimum=0.01, maximum=2.0),
    ParamSpec('resolution', 0.005, 'Cell edge (m)', minimum=0.0005, maximum=0.1),
    ParamSpec('workspace_centre', [0.0, 0.0, 0.0], 'Centre of the cube in the map frame (m)',
              minimum=-5.0, maximum=5.0, length=3),
    ParamSpec('sensor_sigma', 0.002, 'Standard deviation of the Gaussian sensor model, '
              'paper eq. 3 (m)', minimum=1e-5, maximum=0.05),
    ParamSpec('p_z_given_not_occupied', 0.45, 'P(Z given not O) of eq. 4: likelihood of a '
              'measurement in an empty cell', minimum=0.01, maximum=0.99),
    ParamSpec('prior', 0.5, 'Prior occupancy of every cell', minimum=0.01, maximum=0.99),
    ParamSpec('clamp_min', 0.12, 'Lowest occupancy a cell can reach (log-odds clamping)',
              minimum=0.001, maximum=0.99),
    ParamSpec('clamp_max', 0.97, 'Highest occupancy a cell can reach (log-odds clamping)',
              minimum=0.01, maximum=0.999),
    ParamSpec('neighbourhood', 1, 'samples model: 1 updates the containing cell (the paper); '
              '27 also its 26 neighbours, each with eq. 3 at its own distance',
              choices=(1, 27)),
    ParamSpec('distance_to', 'cell', "samples model: the distance in eq. 3, 'cell' (to the "
              "nearest point of the cell, 0 inside it) or 'centre' (to the cell centre, the "
              'paper literally)', choices=DISTANCES),
    ParamSpec('touch_model', 'path', "Evidence from touch: 'path' (the fingertip's path "
              "through the cells, per visit: touch_paths.py) or 'samples' (eq. 4 per sample, "
              'weighed by dwell and visits)', choices=TOUCH_MODELS),
    ParamSpec('evidence_rate', 15.0, "samples model: Hz, one measurement of evidence per "
              '1/evidence_rate s a fingertip spends in a cell (a sample weighs its dwell '
              'time); 0: every sample is one measurement', minimum=0.0, maximum=1000.0),
    ParamSpec('visit_gap', 3.0, 'Seconds: one finger back in a cell less than this after it '
              'was last there continues its visit (samples model: a visit is worth at most '
              'one measurement; 0: every sample)', minimum=0.0, maximum=600.0),
    ParamSpec('transit_speed', 0.2, "path model: m/s; a fingertip faster than this is taken "
              'to move through the air, its evidence scaled by (transit_speed / speed)^'
              'transit_falloff', minimum=0.01, maximum=10.0),
    ParamSpec('transit_falloff', 6.0, 'path model: the power of transit_speed / speed that '
              'scales the evidence of a fingertip faster than transit_speed (6: a carry at 1.5 '
              'times transit_speed keeps a tenth of a touch)', minimum=1.0, maximum=50.0),
    ParamSpec('speed_context', 0.25, 'path model: s; a moment is judged by the fastest speed '
              'within +- this, so the slow ends of a transit count as the transit',
              minimum=0.0, maximum=5.0),
    ParamSpec('pass_time', 0.15, 'path model: s; a slide that takes this long to cross a cell '
              '(3.3 cm/s at 5 mm cells) or longer is worth a second measurement',
              minimum=0.001, maximum=10.0),
    ParamSpec('layer_factor', 0.4, 'path model: the share of its evidence a cell keeps when '
              'a cell one step along the local surface normal has more (times its share of '
              'that cell), or it holds under 0.2 '
              'of the evidence around it (the layer above the surface: lift-offs, set-downs, '
              'hovers), and the touches a cell no neighbour continues counts at most '
              '(surface_layer.py); 1: off',
              minimum=0.0, maximum=1.0),
    ParamSpec('sheet_gain', 1.75, 'path model: how many times a cell of a flat sheet of '
              'evidence, with no stronger cell along its normal and at least 1 touch, counts '
              'its evidence (one pass over a surface the map confirms is enough; '
              'surface_layer.py); 1: off', minimum=1.0, maximum=4.0),
    ParamSpec('cell_judge', True, 'path model: a learned judge of each touched cell '
              '(cell_judge.py) sets the probability of the cells it is sure of: under 0.3 '
              '(a hover, a lift) or over 0.97 (a wall the rules held back); false: the '
              'surface layer\'s rules alone'),
    ParamSpec('occupied_threshold', 0.8, 'Cells above this probability are occupied '
              '(occupancy/occupied, centre of mass, PLY)', minimum=0.5, maximum=0.999),
    ParamSpec('publish_rate', 2.0, 'Map publications per second (only when it changed)',
              minimum=0.01, maximum=100.0),
    ParamSpec('update_rate', 20.0, 'occupancy/updates per second: the cells whose '
              'probability changed and the cells the fingertips are in now (provisional), '
              'for live views; 0: off', minimum=0.0, maximum=100.0),
    ParamSpec('fusion', 'none', 'Global map from the local maps (fusion.py): none (touch '
              'only), product (eq. 9) or entropy (eqs. 10-12) with the vision map of '
              'vision/cloud', choices=FUSIONS),
    # The entropy form's defaults are the one that measured best (fusion.py); eq. 12 as the
    # paper writes it is entropy_radius 0 with entropy_pooling linear.
    ParamSpec('entropy_radius', ENTROPY_RADIUS, 'entropy fusion: 0 weighs each sensor by '
              'its whole map\'s entropy (the paper); r > 0 by the entropy of the (2r+1)^3 '
              'cells around each cell', minimum=0, maximum=10),
    ParamSpec('entropy_pooling', ENTROPY_POOLING, 'entropy fusion: log (the weighted sum of '
              'log-odds, the stronger sensor at full weight) or linear (eq. 12 as written, '
              'the weighted sum of probabilities)', choices=POOLINGS),
    ParamSpec('output_dir', 'maps', 'Folder occupancy/save writes <map_name>.npz and .ply to'),
    ParamSpec('map_name', 'map', 'File name stem of saved maps'),
    ParamSpec('initial_map', '', 'A map saved before (NPZ) to start from, e.g. after a crash; '
              'it must be of this grid (workspace_size, resolution, workspace_centre); '
              'empty: start empty'),
    ParamSpec('autosave_period', 0.0, 'Seconds between saves of a changed map to output_dir '
              '(atomic, as occupancy/save); 0: only on request and at shutdown',
              minimum=0.0, maximum=86400.0),
    *FRAME_PARAMETERS,
)


# Bytes per cell the occupancy node holds at its peak (the grid's arrays, the path model's
# evidence, the map clouds' buffers, the live updates' copy, and during a save the settled
# copy of the map with its clouds), measured with tracemalloc on 100^3 cells: 158 without
# fusion, 241 with a vision map fused by product, 246 by entropy; then 24 more for each
# grid that keeps contact sums (OccupancyGrid.contact_sum): the map and its settled copy,
# and with fusion the touch map too; then 18 more for each grid's cell judge (cell_judge.py:
# its verdicts, their flags and two scratch arrays), the same grids.
BYTES_PER_CELL = {'none': 246, 'fusion': 379}


def memory_problem(cells_per_axis: int, fusion: str, available: int | None) -> str | None:
    """Why a grid of ``cells_per_axis``^3 cells does not fit in ``available`` bytes (None
    when it does, or when the machine does not say)."""
    need = cells_per_axis ** 3 * BYTES_PER_CELL['none' if fusion == 'none' else 'fusion']
    if available is None or need <= available:
        return None
    return (f"parameters 'workspace_size' and 'resolution' make {cells_per_axis}^3 cells, "
            f'about {human_bytes(need)} of memory; this machine has {human_bytes(available)} '
            "available: use a coarser 'resolution' or a smaller 'workspace_size'")


@dataclass(frozen=True)
class RegistrationConfig:
    """The registration node's parameters, checked and typed (``build_map`` uses the same)."""

    mode: str                       # 'tracked' or 'static'
    object_name: str                # station name of the object sensor (tracked mode)
    finger_names: tuple[str, ...]   # station names of the fingertips; index = finger id
    tip_offsets: tuple[float, ...]  # sensor -> pad centre, x, y, z per finger (m, sensor frame)
    pad_radius: float               # m
    max_gap: float                  # s
    max_pending: float              # s (wall clock)
    publish_period: float           # s
    frames: FrameNames = field(default_factory=FrameNames)

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any]) -> RegistrationConfig:
        """Build from validated parameter values; checks what spans several parameters."""
        names = list(values['finger_names'])
        problems = []
        if len(set(names)) != len(names):
            problems.append(f"parameter 'finger_names' = {names} repeats a name")
        if values['mode'] == 'tracked' and values['object_name'] in names:
            problems.append(f"parameter 'object_name' = {values['object_name']!r} is also in "
                            "'finger_names'")
        offsets_problem = tip_offsets_problem(values['tip_offsets'], names)
        if offsets_problem:
            problems.append(offsets_problem)
        frames = FrameNames.from_parameters(values, problems)
        if problems:
            raise ParameterError(problems)
        return cls(mode=values['mode'], object_name=values['object_name'],
                   finger_names=tuple(names),
                   tip_offsets=tuple(TipOffsets.from_parameter(values['tip_offsets'],
                                                               len(names)).as_parameter()),
                   pad_radius=float(values['pad_radius']),
                   max_gap=float(values['max_gap']),
                   max_pending=float(values['max_pending']),
                   publish_period=float(values['publish_period']), frames=frames)

    @property
    def tracked(self) -> bool:
        return self.mode == 'tracked'

    @property
    def finger_topics(self) -> dict[str, int]:
        """Pose topic of each fingertip -> its finger id."""
        return {station_pose_topic(name): index for index, name in enumerate(self.finger_names)}

    @property
    def object_topic(self) -> str | None:
        """Pose topic of the object sensor; None in static mode."""
        return station_pose_topic(self.object_name) if self.tracked else None

    def make_registrar(self) -> Registrar:
        return Registrar(self.mode, self.max_gap, self.max_pending,
                         fingers=range(len(self.finger_names)),
                         tip_offsets=TipOffsets(self.tip_offsets, self.pad_radius))


@dataclass(frozen=True)
class OccupancyConfig:
    """The occupancy node's parameters, checked and typed (``build_map`` uses the same)."""

    grid: GridSpec
    model: SensorModel
    occupied_threshold: float
    publish_rate: float             # Hz
    output_dir: Path
    map_name: str
    fusion: str = 'none'
    entropy_radius: int = 0
    entropy_pooling: str = 'linear'
    update_rate: float = 20.0       # Hz, occupancy/updates; 0: off
    initial_map: Path | None = None  # NPZ to start from
    autosave_period: float = 0.0    # s; 0: off
    frames: FrameNames = field(default_factory=FrameNames)

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any]) -> OccupancyConfig:
        """Build from validated parameter values; checks what spans several parameters."""
        problems = []
        cells = values['workspace_size'] / values['resolution']
        if abs(cells - round(cells)) > 1e-6:
            problems.append(f"parameters 'workspace_size' = {values['workspace_size']} and "
                            f"'resolution' = {values['resolution']}: the size must be a whole "
                            f'number of cells (it is {cells:.3f})')
        elif round(cells) > 1000:
            problems.append(f'{round(cells)} cells per axis is more than 1000: use a coarser '
                            "'resolution' or a smaller 'workspace_size'")
        else:
            problem = memory_problem(round(cells), values['fusion'], available_memory())
            if problem:
                problems.append(problem)
        if not values['clamp_min'] < values['prior'] < values['clamp_max']:
            problems.append("parameters 'clamp_min' < 'prior' < 'clamp_max' must hold (got "
                            f"{values['clamp_min']}, {values['prior']}, {values['clamp_max']})")
        if values['touch_model'] == 'path' and values['neighbourhood'] != 1:
            problems.append("parameter 'neighbourhood' = 27 is for 'touch_model' samples: the "
                            'path model updates the cells the path crosses (use 1)')
        frames = FrameNames.from_parameters(values, problems)
        if problems:
            raise ParameterError(problems)
        grid = GridSpec(values['workspace_size'], values['resolution'],
                        tuple(values['workspace_centre']))
        model = SensorModel(values['sensor_sigma'], values['p_z_given_not_occupied'],
                            values['prior'], values['clamp_min'], values['clamp_max'],
                            values['neighbourhood'], values['distance_to'],
                            values['evidence_rate'], values['visit_gap'],
                            values['touch_model'], values['transit_speed'],
                            values['speed_context'], values['pass_time'],
                            values['layer_factor'], values['transit_falloff'],
                            values['sheet_gain'], values['cell_judge'])
        return cls(grid=grid, model=model,
                   occupied_threshold=float(values['occupied_threshold']),
                   publish_rate=float(values['publish_rate']),
                   update_rate=float(values['update_rate']),
                   initial_map=Path(values['initial_map']) if values['initial_map'] else None,
                   autosave_period=float(values['autosave_period']),
                   output_dir=Path(values['output_dir']), map_name=values['map_name'],
                   fusion=values['fusion'], entropy_radius=int(values['entropy_radius']),
                   entropy_pooling=values['entropy_pooling'], frames=frames)

    @property
    def log_odds_clamp(self) -> tuple[float, float]:
        """The clamps in log-odds (fusion clamps the global map like the touch map)."""
        low, high = self.model.clamp_min, self.model.clamp_max
        return math.log(low / (1 - low)), math.log(high / (1 - high))

    def make_grid(self) -> OccupancyGrid:
        return OccupancyGrid(self.grid, self.model)


def parse_overrides(pairs: list[str]) -> dict:
    """``--set NAME=VALUE`` arguments as a dict, each value read as YAML (lists, numbers)."""
    values = {}
    for pair in pairs:
        name, sep, text = pair.partition('=')
        if not sep or not name:
            raise ParameterError([f'--set {pair!r}: expected NAME=VALUE'])
        values[name.strip()] = yaml.safe_load(text)
    return values


def load_parameters(config: str | Sequence[str] | None, overrides: dict,
                    also_known: Iterable[str] = ()
                    ) -> tuple[RegistrationConfig, OccupancyConfig]:
    """The registration and occupancy configurations the nodes would get from the
    ``registration_node`` and ``occupancy_node`` sections of ``config`` (one ROS parameter
    file or several, later ones overriding earlier ones as repeated ``--params-file``), then
    ``overrides``. ``also_known``: further names ``overrides`` may hold (another node's
    parameters, taken by its caller); any other unknown name is refused."""
    configs = [config] if isinstance(config, str) else list(config or [])
    registration: dict[str, Any] = {}
    occupancy: dict[str, Any] = {}
    for path in configs:
        registration.update(load_yaml_parameters(path, 'registration_node'))
        occupancy.update(load_yaml_parameters(path, 'occupancy_node'))
    registration_names = {s.name for s in REGISTRATION_PARAMETERS}
    occupancy_names = {s.name for s in OCCUPANCY_PARAMETERS}
    unknown = sorted(set(overrides) - registration_names - occupancy_names - set(also_known))
    if unknown:
        known = registration_names | occupancy_names | set(also_known)
        raise ParameterError([f'--set: {unknown_parameter(name, known)}' for name in unknown])
    registration.update({k: v for k, v in overrides.items() if k in registration_names})
    occupancy.update({k: v for k, v in overrides.items() if k in occupancy_names})
    return (RegistrationConfig.from_parameters(validate(REGISTRATION_PARAMETERS, registration)),
            OccupancyConfig.from_parameters(validate(OCCUPANCY_PARAMETERS, occupancy)))
