"""HiCo-GS: octree-anchor Gaussian Splatting with Cross-Level Context Aggregation (CLCA) and
Depth-Normal Geometric Consistency (DNGC), as a nerfstudio-style plugin."""

__version__ = "0.1.0"
