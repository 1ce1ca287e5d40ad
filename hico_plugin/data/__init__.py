"""Datasets in any registered format (COLMAP, transforms.json, ...), lazily cached images, cameras and sparse points."""

from hico_plugin.data.dataset import Dataset
from hico_plugin.data.formats import DATA_FORMATS
from hico_plugin.data.parser import DataParserConfig
from hico_plugin.data.transform import SceneTransform
from hico_plugin.data.undistort import SUPPORTED_MODELS

__all__ = ["DATA_FORMATS", "SUPPORTED_MODELS", "DataParserConfig", "Dataset", "SceneTransform"]
