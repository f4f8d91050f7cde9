"""What every runtime derives from a store, a scene and the render settings before it traces:
shading inputs, the camera, the domain boxes, the AO distance and the number of paths."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vastray.render.camera import Camera
from vastray.render.colormaps import scalar_map
from vastray.render.driver import (
    default_ao_distance,
    path_context,
    shading_inputs,
    store_camera,
    with_camera_clip,
    with_seen_pixels,
)
from vastray.render.integrators import RenderSettings, Shading
from vastray.render.materials import ScalarMap
from vastray.render.scene_config import SceneConfig
from vastray.scene.bvh_choice import fast_builds
from vastray.scene.store import Store
from vastray.schedule.geometry import DomainGeometry
from vastray.schedule.image import ImageSchedule


@dataclass
class RenderSetup:
    """What every runtime derives from a store, scene and settings before tracing."""

    shading: Shading
    keep: frozenset[str]  # attributes loaded domains keep for shading
    color_source: str | None
    scalar_range: ScalarMap  # the scalars' range and colour table (``colormaps.scalar_map``)
    camera: Camera
    geometry: DomainGeometry
    ao_distance: float
    total_paths: int
    fast_builds: bool  # Embree's fast (Morton) BVH for every domain (``scene.bvh_choice``)

    @staticmethod
    def of(store: Store, config: SceneConfig, settings: RenderSettings) -> RenderSetup:
        shading, keep, color_source = shading_inputs(store, config, settings.integrator)
        camera = store_camera(config, store, settings.width, settings.height)
        shading = with_seen_pixels(with_camera_clip(shading, store, camera), store, camera)
        lo, hi = store.domain_boxes()
        nonempty = np.array([d.n_triangles > 0 for d in store.domains], dtype=bool)
        return RenderSetup(
            shading, keep, color_source,
            scalar_map(store.scalar_range, settings.colormap, settings.color_range), camera,
            DomainGeometry(lo, hi, nonempty, float(np.abs(camera.position).max()),
                           store.occupancy()),
            settings.ao_distance or default_ao_distance(store),
            settings.paths, fast_builds(settings.bvh, store.n_triangles))

    def without_masks(self) -> RenderSetup:
        """The same set-up, its domain queries without the occupancy masks."""
        return replace(self, geometry=self.geometry.without_masks())

    def tile_schedule(self, settings: RenderSettings, first: int, tile: int,
                      owner: np.ndarray, rank: int, simple=None) -> ImageSchedule:
        """The ``image`` schedule of the tile of paths ``first`` .. ``first + tile`` (cut at
        the frame's paths) on node ``rank``: its path keys and the partial radiance gathered
        here; ``owner`` (D,): each domain's node; ``simple``: simplified-model routing."""
        ctx = path_context(self.shading, settings, first, min(first + tile, self.total_paths),
                           self.ao_distance)
        return ImageSchedule(ctx, self.geometry, self.color_source, self.scalar_range,
                             owner=owner, rank=rank, simple=simple)
