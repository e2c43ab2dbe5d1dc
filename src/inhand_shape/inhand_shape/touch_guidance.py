"""From a map to where to touch next, in one call, and its files.

:func:`guide` runs the predicted surface (implicit_surface.py) and the ranked next touches
(next_touch.py) on a map's cells; :func:`write_guidance_files` writes ``NAME_predicted.ply``
(the predicted surface, a per-vertex ``std`` in m), ``NAME_completed.ply`` (its part near the
touched cells: the completed surface, the same property) and ``NAME_next_touch.yaml`` (a ranked list
``suggestions``: ``position`` and ``approach`` in the map's frame, ``gain``, ``std``), with the
picture if given, atomically (all or none). The picture is drawn by inhand_tools.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.atomic_file import write_file_set
from inhand_common.parameters import ParamSpec
from inhand_shape.implicit_surface import (
    PREDICTION_PARAMETERS,
    PredictedSurface,
    PredictionSettings,
    SurfacePrior,
    predict_map_surface,
)
from inhand_shape.next_touch import DEFAULT_SUGGESTIONS, Suggestion, next_touches
from inhand_shape.shape_extraction import MODE_ORIENTATION, mesh_bytes, yaml_document

__all__ = [
    'EXPLORATION_NODE_PARAMETERS',
    'GUIDANCE_PARAMETERS',
    'MODE_ORIENTATION',
    'Guidance',
    'guidance_file_names',
    'guide',
    'prediction_settings',
    'std_colours',
    'write_guidance_files',
]

# Viridis at five stops (dark blue, blue, teal, green, yellow): the standard deviation's colour
# scale of the node's surface marker, predict_surface's picture and the live page (view.js
# holds the same stops).
_STD_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]]) / 255.0


def std_colours(std: ArrayLike, top: float) -> np.ndarray:
    """RGB in 0-1 (N, 3) of standard deviations ``std`` (m) from 0 (dark blue: known) to
    ``top`` (yellow: a guess; the prediction's ``signal_std``, the spread where nothing was
    touched)."""
    x = np.clip(np.asarray(std, dtype=float).ravel() / max(top, 1e-12), 0.0, 1.0) * (len(_STD_STOPS) - 1)
    low = np.minimum(np.floor(x).astype(int), len(_STD_STOPS) - 2)
    t = (x - low)[:, None]
    return np.asarray(_STD_STOPS[low] * (1.0 - t) + _STD_STOPS[low + 1] * t)


# The exploration node's parameters (its section of a parameter file; predict_surface reads
# the same section): the process's, and these.
GUIDANCE_PARAMETERS = PREDICTION_PARAMETERS + (
    ParamSpec('suggestions', DEFAULT_SUGGESTIONS, 'Next touches suggested, best first',
              minimum=1, maximum=50),
    ParamSpec('occupied_threshold', 0.8, 'Cells at or above this occupancy probability are '
              'touched surface', minimum=0.51, maximum=0.999),
    ParamSpec('support_clearance', 0.01, 'An object on a support (static maps): no touch '
              'suggested within this height of its lowest cell (m)', minimum=0.0, maximum=0.1),
)
# ... and the node's own: when it runs.
EXPLORATION_NODE_PARAMETERS = (
    ParamSpec('enabled', True, 'Predict the surface and suggest next touches (false: the node '
              'idles)', read_only=False),
    ParamSpec('period', 1.0, 'Seconds between two predictions at most (one runs only when the '
              'map has changed)', minimum=0.2, maximum=60.0),
    ParamSpec('camera', True, "What the stereo node saw of the object (stereo/object: its latest "
              'pairs) is surface too, the space in front of it free (false: the touch map alone)',
              read_only=False),
) + GUIDANCE_PARAMETERS



def prediction_settings(parameters: dict[str, Any]) -> PredictionSettings:
    """The prediction settings among validated ``parameters`` (the others ignored)."""
    return replace(PredictionSettings(), **{f.name: parameters[f.name]
                                            for f in fields(PredictionSettings) if f.name in parameters})


@dataclass(frozen=True, eq=False)
class Guidance:
    """The predicted surface of a map and its ranked next touches; ``seconds`` per step."""

    surface: PredictedSurface
    suggestions: list[Suggestion]
    frame_id: str
    up: tuple[float, float, float]
    support: float | None
    seconds: dict[str, float] = field(default_factory=dict)

    @cached_property
    def completed(self) -> PredictedSurface:
        """The completed surface (:meth:`PredictedSurface.completed`), found once for the
        summary, the YAML and the file."""
        return self.surface.completed()

    def summary(self) -> str:
        """One line for people."""
        s = self.surface
        if s.empty:
            return 'no predicted surface: too few occupied cells'
        std = s.vertex_std * 1000
        best = (f'; best next touch at ({", ".join(f"{v * 100:.1f}" for v in self.suggestions[0].position)}) '
                f'cm, gain {100 * self.suggestions[0].gain:.1f} %' if self.suggestions else
                '; no reachable next touch')
        return (f'predicted surface {len(s.faces):,} triangles, std median {np.median(std):.1f} mm, '
                f'max {std.max():.1f} mm; completed surface {len(self.completed.faces):,} triangles{best}')

    def as_dict(self) -> dict[str, Any]:
        """The content of NAME_next_touch.yaml."""
        s = self.surface
        return {'frame_id': self.frame_id, 'up': [float(v) for v in self.up],
                'support': None if self.support is None else round(self.support, 5),
                'suggestions': [x.as_dict() for x in self.suggestions],
                'surface': {'triangles': int(len(s.faces)),
                            'completed_triangles': int(len(self.completed.faces)),
                            'std_median': round(float(np.median(s.vertex_std)), 5) if not s.empty else None,
                            'std_max': round(float(s.vertex_std.max()), 5) if not s.empty else None,
                            'observations': s.observations, 'inducing_points': s.inducing},
                'seconds': {k: round(v, 3) for k, v in self.seconds.items()}}


def guide(centres: ArrayLike, probabilities: ArrayLike, resolution: float, parameters: dict[str, Any],
          *, up: ArrayLike = (0.0, 0.0, 1.0), on_support: bool = False, frame_id: str = 'object',
          prior: SurfacePrior | None = None, seen: ArrayLike | None = None,
          seen_from: ArrayLike | None = None) -> Guidance:
    """The predicted surface and next touches of a map's cells (centres (N, 3) m, occupancy
    probabilities) with validated :data:`GUIDANCE_PARAMETERS` ``parameters``. ``up``: the map
    frame's up; ``on_support``: the object stands on a support below its lowest occupied cell
    (a static map), where no touch is suggested; ``prior``: an earlier prediction's prior;
    ``seen``, ``seen_from``: the object's surface points a camera measured (map frame) and
    where it was for each (:func:`~inhand_shape.implicit_surface.predict_map_surface`)."""
    up_vector = np.asarray(up, dtype=float) / np.linalg.norm(up)
    start = time.perf_counter()
    surface = predict_map_surface(centres, probabilities, resolution, prediction_settings(parameters),
                                  parameters['occupied_threshold'], prior=prior, seen=seen,
                                  seen_from=seen_from)
    seconds = {'prediction': time.perf_counter() - start}
    support = None
    p = np.asarray(probabilities, dtype=float).ravel()
    occupied = np.asarray(centres, dtype=float).reshape(-1, 3)[p >= parameters['occupied_threshold']]
    if on_support and len(occupied):
        support = float((occupied @ up_vector).min())
    start = time.perf_counter()
    suggestions = next_touches(surface, resolution, parameters['suggestions'], up=up_vector,
                               support=support, support_clearance=parameters['support_clearance'])
    seconds['next_touch'] = time.perf_counter() - start
    x, y, z = (float(v) for v in up_vector)
    return Guidance(surface, suggestions, frame_id, (x, y, z), support, seconds)


def guidance_file_names(output_dir: str | Path, name: str) -> dict[str, Path]:
    """What :func:`write_guidance_files` writes, by kind."""
    folder = Path(output_dir)
    return {'predicted': folder / f'{name}_predicted.ply',
            'completed': folder / f'{name}_completed.ply',
            'suggestions': folder / f'{name}_next_touch.yaml',
            'picture': folder / f'{name}_uncertainty.png'}


def write_guidance_files(guidance: Guidance, output_dir: str | Path, name: str,
                         picture: bytes | None = None) -> list[Path]:
    """Write the predicted and the completed surface (none when empty), the suggestions and
    the ``picture`` (PNG bytes) if given, all or none; the paths written."""
    files = guidance_file_names(output_dir, name)
    surface, completed = guidance.surface, guidance.completed
    contents: dict[Path, bytes | None] = {
        files['predicted']: None if surface.empty else mesh_bytes(surface.trimesh(), 'ply'),
        files['completed']: None if completed.empty else mesh_bytes(completed.trimesh(), 'ply'),
        files['suggestions']: yaml_document(f'Where to touch next (inhand_shape): {guidance.summary()}',
                                            guidance.as_dict())}
    if picture is not None:
        contents[files['picture']] = picture
    return write_file_set(contents)
