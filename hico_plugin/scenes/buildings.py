"""Ordinary city buildings: one block's houses, slabs and towers with their roofs and street trees,
shared by the ``city-block`` and ``district`` scenes."""

from __future__ import annotations

import numpy as np

from hico_plugin.scenes.raycast import Primitive, Revolution, Sphere, box, roof

WALL_COLORS = [(0.78, 0.72, 0.62), (0.62, 0.6, 0.58), (0.72, 0.55, 0.45), (0.85, 0.82, 0.75), (0.55, 0.6, 0.66)]


def block_centers(blocks: int, pitch: float) -> np.ndarray:
    """[blocks^2, 2] xy centres of a square grid of blocks ``pitch`` apart around the origin, row by row
    (x fastest)."""
    offsets = (np.arange(blocks) - (blocks - 1) / 2) * pitch
    return np.stack(np.meshgrid(offsets, offsets), -1).reshape(-1, 2)


def block_buildings(rng: np.random.Generator, cx: float, cy: float, lot: float, floor: float,
                    max_floors: int) -> list[Primitive]:
    """The buildings and street trees of the block centred on (cx, cy): one of three layouts (a large
    building, two slabs, a tower and two houses) on the square ``lot`` inside the pavements, 2 to
    ``max_floors`` storeys of height ``floor`` each, topped by a pitched roof, setback storeys or a
    plant room; up to two trees on the pavement."""
    layout = rng.integers(0, 3)
    if layout == 0:  # one large building, maybe with a setback tower
        footprints = [(cx, cy, lot, lot * rng.uniform(0.7, 1.0))]
    elif layout == 1:  # two slabs
        w = lot / 2 - 0.6
        footprints = [(cx - lot / 4, cy, w, lot), (cx + lot / 4, cy, w, lot * rng.uniform(0.6, 1.0))]
    else:  # a tower and two houses
        footprints = [
            (cx - lot / 4, cy, lot / 2 - 0.6, lot),
            (cx + lot / 4, cy - lot / 4, lot / 2 - 0.6, lot / 2 - 0.6),
            (cx + lot / 4, cy + lot / 4, lot / 2 - 0.6, lot / 2 - 0.6),
        ]
    prims: list[Primitive] = []
    for x, y, sx, sy in footprints:
        floors = int(rng.integers(2, max_floors + 1))
        height = floors * floor
        yaw = 0.0 if rng.uniform() > 0.2 else rng.uniform(-0.35, 0.35)
        if yaw:  # rotated buildings must still fit on their lot
            scale = 1.0 / (abs(np.cos(yaw)) + abs(np.sin(yaw)))
            sx, sy = sx * scale, sy * scale
        wall = WALL_COLORS[rng.integers(len(WALL_COLORS))]
        prims.append(
            box((x, y, height / 2), (sx, sy, height), yaw=yaw, material="facade", color=wall,
                texture_scale=floor, top_material="roof_flat")
        )
        if floors <= 4 and rng.uniform() < 0.7:  # pitched roof, ridge along the long side
            along_x = sx >= sy
            size = (sx, sy) if along_x else (sy, sx)
            prims.append(
                roof((x, y, height), size, rise=0.35 * min(sx, sy), hip=bool(rng.uniform() < 0.5),
                     yaw=yaw + (0 if along_x else np.pi / 2), material="roof_tiles",
                     color=(0.55, 0.25, 0.18), texture_scale=0.45)
            )
        elif floors >= 6 and rng.uniform() < 0.6:  # setback upper storeys
            extra = int(rng.integers(2, 4)) * floor
            prims.append(
                box((x, y, height + extra / 2), (0.6 * sx, 0.6 * sy, extra), yaw=yaw, material="facade",
                    color=wall, texture_scale=floor, top_material="roof_flat")
            )
        else:  # rooftop plant room
            prims.append(
                box((x + 0.15 * sx, y, height + 1.2), (0.25 * sx, 0.3 * sy, 2.4), yaw=yaw,
                    material="plaster", color=(0.6, 0.6, 0.6), texture_scale=1.0)
            )
    for _ in range(int(rng.integers(0, 3))):  # street trees on the pavement corners
        prims += street_tree(cx + rng.choice([-1, 1]) * (lot / 2 + 1.5), cy + rng.uniform(-lot / 2, lot / 2),
                             rng.uniform(1.8, 2.8))
    return prims


def street_tree(x: float, y: float, radius: float) -> list[Primitive]:
    """A trunk and a round crown of ``radius`` standing at (x, y) on the ground."""
    return [
        Revolution(material="wood", color=(0.35, 0.25, 0.18), base=(x, y, 0), height=3.0, r0=0.25, r1=0.18),
        Sphere(material="foliage", color=(0.25, 0.45, 0.2), texture_scale=1.0, center=(x, y, 3.0 + radius * 0.8),
               radius=radius),
    ]
