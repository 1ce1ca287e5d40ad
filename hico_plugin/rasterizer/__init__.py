"""Gaussian rasterization: one functional entry point, a pure-torch tiled backend and a gsplat backend."""
