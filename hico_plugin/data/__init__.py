"""Datasets: COLMAP scenes through pycolmap, lazily cached images, cameras and sparse points."""

from hico_plugin.data.dataset import Dataset
from hico_plugin.data.parser import DATAPARSERS, ColmapDataParserConfig
from hico_plugin.data.transform import SceneTransform
from hico_plugin.data.undistort import SUPPORTED_MODELS

__all__ = ["DATAPARSERS", "SUPPORTED_MODELS", "ColmapDataParserConfig", "Dataset", "SceneTransform"]
