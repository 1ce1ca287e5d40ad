"""Procedural materials: albedo in [0, 1] as a function of surface coordinates and world position.

Every material is a deterministic function of where the surface point is, so all views agree.
Signature: ``material(uv [n, 2], points [n, 3], color [3], scale) -> albedo [n, 3]``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from hico_plugin.registry import Registry

Material = Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]
MATERIALS: Registry[Material] = Registry("material")


def hash01(*coords: np.ndarray) -> np.ndarray:
    """A float in [0, 1) per integer lattice coordinate tuple (uint32 hashing, wraps on purpose)."""
    h = np.uint32(0x27D4EB2F)
    with np.errstate(over="ignore"):
        for c, prime in zip(coords, (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D)):
            h = (h ^ np.asarray(c).astype(np.int64).astype(np.uint32)) * np.uint32(prime)
            h = h ^ (h >> np.uint32(15))
        h = (h * np.uint32(0x2C1B3C6D)) ^ (h >> np.uint32(12))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise(coords: np.ndarray, frequency: float) -> np.ndarray:
    """Smooth 2D value noise in [0, 1]: coords [n, 2] (surface uv or ground xy) -> [n]."""
    q = coords * frequency
    cell = np.floor(q)
    f = q - cell
    f = f * f * (3 - 2 * f)  # smoothstep weights
    i = cell.astype(np.int64)
    h00, h10 = hash01(i[:, 0], i[:, 1]), hash01(i[:, 0] + 1, i[:, 1])
    h01, h11 = hash01(i[:, 0], i[:, 1] + 1), hash01(i[:, 0] + 1, i[:, 1] + 1)
    bottom = h00 + (h10 - h00) * f[:, 0]
    top = h01 + (h11 - h01) * f[:, 0]
    return bottom + (top - bottom) * f[:, 1]


def fbm(coords: np.ndarray, frequency: float, octaves: int = 2) -> np.ndarray:
    """Fractal sum of 2D value noise, normalised to [0, 1]."""
    total, amplitude, norm = np.zeros(len(coords)), 1.0, 0.0
    for _ in range(octaves):
        total += amplitude * value_noise(coords, frequency)
        norm += amplitude
        amplitude, frequency = amplitude * 0.5, frequency * 2.0
    return total / norm


def _tint(color: np.ndarray, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(color, np.float64), (n, 3)).copy()


@MATERIALS.register("plain")
def plain(uv, points, color, scale):
    return _tint(color, len(uv))


@MATERIALS.register("checker")
def checker(uv, points, color, scale):
    """Two-tone checkerboard of period ``scale`` in the surface's uv."""
    cells = np.floor(uv / scale).astype(np.int64)
    odd = (cells[:, 0] + cells[:, 1]) % 2 == 1
    return _tint(color, len(uv)) * np.where(odd, 0.45, 1.0)[:, None]


@MATERIALS.register("plaster")
def plaster(uv, points, color, scale):
    return _tint(color, len(uv)) * (0.85 + 0.3 * fbm(uv, 4.0 / scale))[:, None]


@MATERIALS.register("facade")
def facade(uv, points, color, scale):
    """Walls with a window grid: floors of height ``scale``, a glazed shop floor at street level."""
    n = len(uv)
    u, v = uv[:, 0], points[:, 2]  # v from world height, so floors line up around the building
    wall = _tint(color, n) * (0.88 + 0.24 * fbm(uv, 3.0 / scale))[:, None]
    floor = np.floor(v / scale)
    fu, fv = np.mod(u / (0.8 * scale), 1.0), np.mod(v / scale, 1.0)
    column = np.floor(u / (0.8 * scale))
    lit = hash01(column, floor, 5) > 0.85
    glass = np.where(lit[:, None], [[0.85, 0.78, 0.5]], [[0.16, 0.22, 0.3]])
    glass = glass * (0.8 + 0.4 * hash01(column, floor, 7))[:, None]
    window = (fu > 0.22) & (fu < 0.78) & (fv > 0.28) & (fv < 0.82) & (floor >= 1)
    frame = (fu > 0.17) & (fu < 0.83) & (fv > 0.23) & (fv < 0.87) & (floor >= 1) & ~window
    shop = (floor == 0) & (fv > 0.15) & (fv < 0.8) & (np.mod(u / (1.6 * scale), 1.0) > 0.08)
    sill = (fv > 0.95) | (fv < 0.04)  # horizontal band between floors
    out = np.where(sill[:, None], wall * 0.8, wall)
    out = np.where(frame[:, None], [[0.9, 0.9, 0.88]], out)
    out = np.where((window | shop)[:, None], glass, out)
    return out


@MATERIALS.register("roof_flat")
def roof_flat(uv, points, color, scale):
    """Gravel roof with a parapet-coloured grid of service hatches."""
    gravel = 0.75 + 0.25 * value_noise(uv, 20.0 / scale) + 0.15 * value_noise(uv, 2.0 / scale)
    hatch = (np.mod(uv[:, 0] / (2 * scale), 1.0) < 0.12) & (np.mod(uv[:, 1] / (2 * scale), 1.0) < 0.12)
    out = _tint(color, len(uv)) * gravel[:, None]
    return np.where(hatch[:, None], out * 0.55, out)


@MATERIALS.register("roof_tiles")
def roof_tiles(uv, points, color, scale):
    """Overlapping tile rows along the slope (period ``scale``), staggered, darker under each row."""
    row = np.floor(uv[:, 1] / scale)
    fv = np.mod(uv[:, 1] / scale, 1.0)
    offset = 0.5 * np.mod(row, 2)
    fu = np.mod(uv[:, 0] / (1.2 * scale) + offset, 1.0)
    tile = np.floor(uv[:, 0] / (1.2 * scale) + offset)
    shade = 0.55 + 0.45 * fv  # tile overlap: the lower edge of each row is in its neighbour's shadow
    shade = shade * (1.0 - 0.35 * (np.abs(fu - 0.5) > 0.44))
    shade = shade * (0.85 + 0.3 * hash01(tile, row, 3))
    return _tint(color, len(uv)) * shade[:, None]


@MATERIALS.register("brick")
def brick(uv, points, color, scale):
    """Running-bond bricks of height ``scale`` and length 2 x ``scale`` with light mortar."""
    row = np.floor(uv[:, 1] / scale)
    fv = np.mod(uv[:, 1] / scale, 1.0)
    x = uv[:, 0] / (2 * scale) + 0.5 * np.mod(row, 2)
    fu, column = np.mod(x, 1.0), np.floor(x)
    mortar = (fv < 0.12) | (fu < 0.06)
    variation = 0.75 + 0.5 * hash01(column, row, 11)
    out = _tint(color, len(uv)) * variation[:, None]
    return np.where(mortar[:, None], [[0.78, 0.76, 0.7]], out)


@MATERIALS.register("wood")
def wood(uv, points, color, scale):
    """Painted timber: vertical grain streaks."""
    grain = value_noise(uv * [8.0 / scale, 0.5 / scale], 1.0)
    return _tint(color, len(uv)) * (0.8 + 0.35 * grain)[:, None]


@MATERIALS.register("foliage")
def foliage(uv, points, color, scale):
    return _tint(color, len(uv)) * (0.55 + 0.7 * fbm(uv, 6.0 / scale))[:, None]


@MATERIALS.register("wallpaper")
def wallpaper(uv, points, color, scale):
    """Papered wall: round flowers (a red bloom ringed by green leaves) on a half-drop grid of period
    ``scale``, on a plain ground of ``color`` that changes only slowly (a faint mottle): features where
    the flowers are, smooth paper between them, like the rose paper behind the fox of instant-ngp's
    capture."""
    row = np.floor(uv[:, 1] / scale)
    local = np.stack([np.mod(uv[:, 0] / scale + 0.5 * np.mod(row, 2), 1.0), np.mod(uv[:, 1] / scale, 1.0)], 1)
    radius = np.linalg.norm(local - 0.5, axis=1)  # in periods, from the motif's centre
    petals = 0.05 * np.cos(5 * np.arctan2(local[:, 1] - 0.5, local[:, 0] - 0.5))
    out = _tint(color, len(uv)) * (0.88 + 0.24 * value_noise(uv, 0.8 / scale))[:, None]
    out = np.where((radius < 0.2 + petals)[:, None], [[0.35, 0.5, 0.3]], out)  # leaves
    return np.where((radius < 0.13 + petals)[:, None], [[0.7, 0.18, 0.22]], out)  # bloom


@MATERIALS.register("street")
def street(uv, points, color, scale):
    """City ground on a grid of pitch ``scale``: roads centred on x, y = (k + 1/2) * scale with dashed
    centre lines and zebra crossings, pavements, and blocks centred on x, y = k * scale."""
    x, y = points[:, 0], points[:, 1]
    # distance to the nearest road centre line in x and in y
    dx = np.abs(np.mod(x / scale, 1.0) - 0.5) * scale
    dy = np.abs(np.mod(y / scale, 1.0) - 0.5) * scale
    road_half, walk = 0.14 * scale, 0.05 * scale
    on_road_x, on_road_y = dx < road_half, dy < road_half  # on a road running along y / along x
    road = on_road_x | on_road_y
    crossing = on_road_x & on_road_y
    noise = value_noise(points[:, :2], 40.0 / scale)
    asphalt = _tint(color, len(x)) * (0.8 + 0.4 * noise)[:, None]
    paving = np.array([0.62, 0.6, 0.55]) * (0.85 + 0.3 * noise)[:, None]
    block = np.array([0.55, 0.58, 0.48]) * (0.8 + 0.4 * value_noise(points[:, :2], 8.0 / scale))[:, None]
    dash_y = on_road_x & ~on_road_y & (dx < 0.006 * scale) & (np.mod(y / (0.08 * scale), 1.0) < 0.5)
    dash_x = on_road_y & ~on_road_x & (dy < 0.006 * scale) & (np.mod(x / (0.08 * scale), 1.0) < 0.5)
    # zebra stripes just outside each intersection
    near_x = on_road_x & (dy > road_half) & (dy < road_half + 0.05 * scale)
    near_y = on_road_y & (dx > road_half) & (dx < road_half + 0.05 * scale)
    zebra = (near_x & (np.mod(x / (0.025 * scale), 1.0) < 0.5)) | (
        near_y & (np.mod(y / (0.025 * scale), 1.0) < 0.5)
    )
    pavement = ~road & ((dx < road_half + walk) | (dy < road_half + walk))
    out = np.where(road[:, None], asphalt, np.where(pavement[:, None], paving, block))
    white = (dash_x | dash_y | zebra) & ~crossing
    return np.where(white[:, None], [[0.92, 0.92, 0.9]], out)
