"""Datasets: COLMAP scenes through pycolmap, lazily cached images, cameras and sparse points."""
