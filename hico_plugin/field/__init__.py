"""The anchor octree field: LOD selection, cross-level context aggregation (CLCA), Gaussian decoding."""
