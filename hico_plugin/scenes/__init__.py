"""Built-in scenes with exact geometry, rendered by an independent analytic ray caster.

``generate_scene("city-block")`` returns a COLMAP dataset directory (cached); ``SCENES`` maps scene
names to their config dataclasses.
"""

from hico_plugin.scenes.base import SCENES, Scene, SceneConfig, SceneEffects
from hico_plugin.scenes.city_block import CityBlockConfig, CityBlockEffects
from hico_plugin.scenes.district import DistrictConfig, DistrictEffects
from hico_plugin.scenes.pagoda import PagodaConfig, PagodaEffects
from hico_plugin.scenes.room import RoomConfig, RoomEffects
from hico_plugin.scenes.tiny import TinyConfig, TinyEffects

__all__ = [
    "SCENES",
    "Scene",
    "SceneConfig",
    "SceneEffects",
    "CityBlockConfig",
    "CityBlockEffects",
    "DistrictConfig",
    "DistrictEffects",
    "PagodaConfig",
    "PagodaEffects",
    "RoomConfig",
    "RoomEffects",
    "TinyConfig",
    "TinyEffects",
]
