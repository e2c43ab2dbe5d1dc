"""The map the occupancy node publishes and saves: the touch map, or the global map fused
from the touch map and the vision map (``fusion.py``).

:class:`GlobalMap` keeps the touch grid (integrated by the node or ``build_map``), the latest
vision map (log-odds from ``vision/cloud``) and a grid that shows their fusion; the fusion
is redone only when either has changed since. Shared by the node and ``build_map`` so both
publish and save the same map.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from inhand_mapping.fusion import ENTROPY_POOLING, ENTROPY_RADIUS, fuse
from inhand_mapping.occupancy import OccupancyGrid

if TYPE_CHECKING:     # mapping_config builds on the maps, not the other way round
    from inhand_mapping.mapping_config import OccupancyConfig

__all__ = ['GlobalMap']


class GlobalMap:
    @classmethod
    def for_config(cls, touch: OccupancyGrid, config: OccupancyConfig) -> GlobalMap:
        """With the fusion settings of an OccupancyConfig."""
        return cls(touch, config.fusion, config.entropy_radius, config.log_odds_clamp,
                   config.entropy_pooling)

    def __init__(self, touch: OccupancyGrid, fusion: str = 'none',
                 entropy_radius: int = ENTROPY_RADIUS,
                 clamp: tuple[float, float] = (-np.inf, np.inf),
                 entropy_pooling: str = ENTROPY_POOLING):
        self.touch = touch
        self.fusion, self.entropy_radius, self.clamp = fusion, entropy_radius, clamp
        self.entropy_pooling = entropy_pooling
        self.vision: NDArray[np.float64] | None = None
        self._fused: OccupancyGrid | None = None
        self._stale = True

    @property
    def fusing(self) -> bool:
        """Whether the published map is a fusion (fusion on and a vision map there)."""
        return self.fusion != 'none' and self.vision is not None

    def set_vision(self, log_odds: NDArray[np.float64] | None) -> None:
        """The vision map (log-odds on the touch grid, prior 0), or None to drop it."""
        if log_odds is not None and log_odds.shape != self.touch.spec.shape:
            raise ValueError(f'vision map of shape {log_odds.shape} for a grid of '
                             f'{self.touch.spec.shape}')
        self.vision = log_odds
        self._stale = True

    def settled(self) -> GlobalMap:
        """This map with what the touch grid holds back applied, on a copy
        (OccupancyGrid.settled_copy): what a save writes and a pause shows, while this map
        goes on taking the stream as if neither had happened."""
        view = GlobalMap(self.touch.settled_copy(), self.fusion, self.entropy_radius,
                         self.clamp, self.entropy_pooling)
        view.vision = self.vision
        return view

    def touch_changed(self) -> None:
        self._stale = True

    def grid(self) -> OccupancyGrid:
        """The map to publish and save: the touch grid itself, or the fused view of it."""
        if not self.fusing:
            return self.touch
        if self._fused is None:
            self._fused = OccupancyGrid(self.touch.spec, self.touch.model)
        if self._stale:
            fused = fuse(self.fusion, self.touch.log_odds, self.vision, self.clamp,
                         self.entropy_radius, self.entropy_pooling)
            self._fused.show(fused.log_odds, self.touch, self._fused_layer())
            self._stale = False
        return self._fused

    def _fused_layer(self) -> tuple[NDArray[np.intp], NDArray[np.float64]] | None:
        """(the cells the touch map's cell judge overrode, the fusion there of the touch
        map's surface layer instead): what the shape's parts take of the fused map
        (OccupancyGrid.layer_overrides). A second fusion, only while the judge overrides."""
        judged = self.touch.judged
        if judged is None or len(judged[0]) == 0:
            return None
        cells, rules = judged
        layer = self.touch.log_odds.copy()
        layer.reshape(-1)[cells] = rules
        without = fuse(self.fusion, layer, self.vision, self.clamp, self.entropy_radius,
                       self.entropy_pooling)
        return cells, without.log_odds.reshape(-1)[cells]

    def local_maps(self) -> dict[str, NDArray[np.float64]] | None:
        """The local maps to save beside a fused map (None when not fusing)."""
        if not self.fusing or self.vision is None:
            return None
        return {'touch': self.touch.log_odds, 'vision': self.vision}
