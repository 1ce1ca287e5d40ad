"""``district``: city-block's buildings over a large grid of blocks with three landmarks (a tower, a domed church
with a spire, a long low hall), captured as the paper's aerial datasets are (Mill19's drone grid) plus streets.

The drone flies a serpentine path at one altitude, shooting at each waypoint a nadir view and four obliques along
+x, +y, -x and -y (a penta camera); the street views walk some interior streets from a pedestrian's height to a
pole's, looking along them and at the facades.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.scenes.base import SCENES, SceneConfig, SceneEffects
from hico_plugin.scenes.buildings import block_buildings, block_centers
from hico_plugin.scenes.orbits import look_at
from hico_plugin.scenes.raycast import Ground, Primitive, Revolution, Sphere, box, prism, roof

OBLIQUE_YAWS = np.radians([0.0, 90.0, 180.0, 270.0])  # +x, +y, -x, -y: the rig's four obliques
STREET_YAWS = np.radians([0.0, 50.0, 0.0, -50.0])  # towards the street's middle, the left facades, the right


@dataclass
class DistrictEffects(SceneEffects):
    exposure: bool = False
    """Per-image exposure and white balance changes (a drone's auto exposure). Off by default, as for
    city-block: test views' unknown gains would otherwise cap every method's PSNR."""
    sky: bool = True
    """Gradient sky instead of black where rays miss the scene (the street views look up past the roofs)."""
    multi_distance: bool = True
    """Street-level passes beside the drone's grid (views from a few metres to the flight height, as
    Mill19's mixed captures); off: the drone's nadir and oblique grid alone."""


@SCENES.register("district")
@dataclass
class DistrictConfig(SceneConfig):
    """A district of city blocks with a tower, a domed church and a long hall among ordinary buildings,
    seen by a drone's nadir and oblique grid and from street level."""

    num_views: int = 1000
    """Views in all: the drone's, five per waypoint, then the street passes' (a street_share of them)."""
    sparse_points: int = 20000
    """Target number of SfM-like sparse points: a few hundred per block."""
    surface_spacing: float = 0.5
    """Spacing (metres) of the dense ground-truth surface samples: coarser than city-block's, over a
    surface many times larger."""
    effects: DistrictEffects = field(default_factory=DistrictEffects)
    blocks: int = 9
    """Blocks per side of the square grid; odd, so that the block centres sit on the street texture's
    grid, and at least 3, so that the landmarks have blocks of their own."""
    block_pitch: float = 30.0
    """Distance between neighbouring block centres (metres); streets run between blocks."""
    floor_height: float = 3.2
    """Storey height (window grid period, metres)."""
    max_floors: int = 7
    """Tallest ordinary building, in storeys."""
    tower_floors: int = 24
    """Storeys of the tower landmark on the central block."""
    altitude: float = 120.0
    """Flight height of the drone above the ground (metres); it must clear the tallest landmark."""
    oblique_pitch_deg: float = 45.0
    """Tilt of the four oblique cameras below the horizon (a penta camera's obliques)."""
    street_share: float = 0.2
    """Share of the views taken at street level; the rest are the drone's."""
    street_passes: int = 4
    """Interior streets walked at street level, alternately along x and along y."""
    street_heights: tuple[float, float] = (1.7, 10.0)
    """Lowest and highest street-level camera (metres): a pedestrian's to a pole's or a low drone's."""

    def _check(self) -> None:
        if self.blocks < 3 or self.blocks % 2 == 0:
            raise HicoError(f"scene 'district': blocks must be odd and >= 3, got {self.blocks}")
        if not 0.0 <= self.street_share < 1.0:
            raise HicoError(f"scene 'district': street_share must be in [0, 1), got {self.street_share}")
        if self.street_passes < 1:
            raise HicoError(f"scene 'district': street_passes must be >= 1, got {self.street_passes}")
        low, high = self.street_heights
        if not 0.0 < low <= high:
            raise HicoError(f"scene 'district': street_heights must be (low, high) with 0 < low <= high, "
                            f"got {self.street_heights}")
        if not 0.0 < self.oblique_pitch_deg < 90.0:
            raise HicoError(f"scene 'district': oblique_pitch_deg must be in (0, 90), got {self.oblique_pitch_deg}")

    def _landmark_blocks(self) -> dict[str, list[int]]:
        """Grid indices (iy * blocks + ix) of the landmarks: the tower in the middle, the church and
        the hall (two blocks side by side along x, across the street between them) off the diagonal."""
        b, middle, q = self.blocks, self.blocks // 2, max(1, self.blocks // 4)
        return {
            "tower": [middle * b + middle],
            "church": [(middle + q) * b + middle - q],
            "hall": [(middle - q) * b + middle + q - 1, (middle - q) * b + middle + q],
        }

    def build_primitives(self) -> list[Primitive]:
        self._check()
        rng = np.random.default_rng([self.seed, 3])
        pitch, floor = self.block_pitch, self.floor_height
        lot = 0.6 * pitch  # usable block size inside the pavements
        centers = block_centers(self.blocks, pitch)
        landmarks = self._landmark_blocks()
        prims = [Ground(material="street", color=(0.3, 0.3, 0.32), texture_scale=pitch,
                        half_extent=self.blocks * pitch / 2 + self._oblique_reach())]
        prims += _tower(*centers[landmarks["tower"][0]], lot, floor, self.tower_floors)
        prims += _church(*centers[landmarks["church"][0]])
        prims += _hall(*centers[landmarks["hall"]].mean(0), pitch + lot, 0.8 * lot)
        taken = {index for indices in landmarks.values() for index in indices}
        for index, (cx, cy) in enumerate(centers):
            if index not in taken:
                prims += block_buildings(rng, cx, cy, lot, floor, self.max_floors)
        top = max(p.hull_points()[:, 2].max() for p in prims)
        if self.altitude < top + 10.0:
            raise HicoError(f"scene 'district': altitude {self.altitude:g} m does not clear the tallest landmark "
                            f"({top:.1f} m); expected >= {top + 10.0:.1f}")
        return prims

    def _oblique_reach(self) -> float:
        """How far beyond the drone's path the ground must reach for the obliques to see ground up to
        their top corners, pitched up to 5 degrees less by the attitude noise (at most 10 altitudes: a
        top edge at or above the horizon shows sky)."""
        half_w = np.tan(np.radians(self.fov_x_deg) / 2)
        half_h = half_w * self.height / self.width
        pitch = np.radians(self.oblique_pitch_deg - 5.0)
        drop = np.sin(pitch) - half_h * np.cos(pitch)  # the top corners' fall per unit along the axis
        run = np.hypot(np.cos(pitch) + half_h * np.sin(pitch), half_w)
        return self.altitude * (run / drop if drop * 10 > run else 10.0)

    def capture(self) -> tuple[list[str], np.ndarray]:
        """The views' kinds ("nadir", "oblique", "street") and their world->camera [num_views, 4, 4]:
        the drone's first, in flight order, then the street passes."""
        self._check()
        rng = np.random.default_rng([self.seed, 7])
        street = int(round(self.street_share * self.num_views)) if self.effects.multi_distance else 0
        kinds, aerial = self._aerial(self.num_views - street, rng)
        return kinds + ["street"] * street, np.concatenate([aerial, self._street(street, rng)])

    def view_kinds(self) -> list[str]:
        return self.capture()[0]

    def build_viewmats(self) -> np.ndarray:
        return self.capture()[1]

    def _aerial(self, count: int, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
        """``count`` drone views: waypoints evenly spaced along a serpentine over the blocks, five views
        each (nadir, then the obliques), with a little position and attitude noise."""
        waypoints = int(np.ceil(count / 5))
        side = self.blocks * self.block_pitch
        rows = max(2, int(round(np.sqrt(waypoints + 1))))  # row gap ~ the spacing along the path
        ys = np.linspace(-side / 2, side / 2, rows)
        ends = np.array([-side / 2, side / 2])
        path = np.array([(x, y) for r, y in enumerate(ys) for x in (ends if r % 2 == 0 else ends[::-1])])
        lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
        along = (np.arange(waypoints) + 0.5) * lengths.sum() / waypoints
        segment = np.searchsorted(np.cumsum(lengths), along)
        heading = (path[segment + 1] - path[segment]) / lengths[segment, None]
        offset = along - np.concatenate([[0.0], np.cumsum(lengths)])[segment]
        xy = path[segment] + heading * offset[:, None] + rng.normal(0.0, 1.0, (waypoints, 2))
        eye = np.c_[xy, self.altitude * (1 + rng.normal(0.0, 0.01, waypoints))]
        eye = np.repeat(eye, 5, axis=0)[:count]
        # nadir: straight down within a few degrees, the image's top along the flight
        tilt = np.radians(rng.normal(0.0, 1.0, (waypoints, 2)))
        nadir = np.c_[np.tan(tilt), -np.ones(waypoints)]
        # obliques: the rig's yaws and pitch, each shot off by a degree or two
        yaw = OBLIQUE_YAWS[None] + np.radians(rng.normal(0.0, 2.0, (waypoints, 4)))
        pitch = np.radians(self.oblique_pitch_deg + rng.normal(0.0, 1.5, (waypoints, 4)))
        oblique = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)], -1)
        forward = np.concatenate([nadir[:, None], oblique], axis=1).reshape(-1, 3)[:count]
        up = np.c_[np.repeat(heading, 5, axis=0), np.zeros(5 * waypoints)][:count]
        up[np.arange(count) % 5 != 0] = [0.0, 0.0, 1.0]  # obliques keep the horizon level
        kinds = ["nadir" if i % 5 == 0 else "oblique" for i in range(count)]
        return kinds, look_at(eye, eye + forward, up)

    def _streets(self) -> list[tuple[int, float]]:
        """The walked streets as (axis the street runs along, 0 = x or 1 = y; its centre line's other
        coordinate): interior streets spread evenly over the grid (passing the landmarks' blocks on the
        default grid), none through the hall."""
        pitch = self.block_pitch
        lines = (np.arange(self.blocks - 1) - (self.blocks - 2) / 2) * pitch  # interior street centre lines
        hall = block_centers(self.blocks, pitch)[self._landmark_blocks()["hall"]][:, 0].mean()
        choices = [lines, lines[np.abs(lines - hall) > pitch / 4]]  # along x: any; along y: not through the hall
        picks = []
        for axis, candidates in enumerate(choices):
            n = (self.street_passes - axis + 1) // 2  # passes along this axis
            picks.append(candidates[np.round(np.linspace(0, len(candidates) - 1, n + 2)[1:-1]).astype(int)])
        return [(p % 2, float(picks[p % 2][p // 2])) for p in range(self.street_passes)]

    def _street(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """``count`` street-level views split over the passes: evenly along each street (within a metre
        of its centre line, at random heights), looking along it towards its middle, then at the facades
        ahead on the left, along it again, then at the facades ahead on the right."""
        if count == 0:
            return np.zeros((0, 4, 4))
        side = self.blocks * self.block_pitch
        low, high = self.street_heights
        viewmats = []
        for (axis, line), views in zip(self._streets(), np.array_split(np.arange(count), self.street_passes)):
            n = len(views)
            if n == 0:
                continue
            along = np.linspace(-side / 2, side / 2, n + 2)[1:-1] + rng.uniform(-1.0, 1.0, n)
            across = line + rng.uniform(-1.0, 1.0, n)
            xy = np.stack([along, across], 1) if axis == 0 else np.stack([across, along], 1)
            eye = np.c_[xy, rng.uniform(low, high, n)]
            inward = axis * np.pi / 2 + np.where(along < 0, 0.0, np.pi)
            yaw = inward + STREET_YAWS[np.arange(n) % 4] + np.radians(rng.normal(0.0, 5.0, n))
            facade = np.arange(n) % 2 == 1
            pitch = np.radians(np.where(facade, rng.uniform(0.0, 15.0, n), rng.uniform(-5.0, 5.0, n)))
            forward = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], -1)
            viewmats.append(look_at(eye, eye + forward))
        return np.concatenate(viewmats)


def _tower(cx: float, cy: float, lot: float, floor: float, floors: int) -> list[Primitive]:
    """A glass-blue office tower of ``floors`` storeys on a two-storey podium filling the lot, with a
    plant room and an antenna on top."""
    height = floors * floor
    glass = dict(material="facade", texture_scale=floor, top_material="roof_flat")
    return [
        box((cx, cy, floor), (lot, lot, 2 * floor), color=(0.62, 0.6, 0.58), **glass),
        box((cx, cy, height / 2), (0.6 * lot, 0.6 * lot, height), color=(0.55, 0.6, 0.66), **glass),
        box((cx, cy, height + 2.0), (0.4 * lot, 0.4 * lot, 4.0), material="plaster", color=(0.6, 0.6, 0.6),
            texture_scale=1.0),
        Revolution(material="plain", color=(0.7, 0.7, 0.72), base=(cx, cy, height + 4.0), height=14.0, r0=0.5,
                   r1=0.15),
    ]


def _church(cx: float, cy: float) -> list[Primitive]:
    """A cross-shaped church on its block: a nave along x and a transept under gable roofs, a drum and
    a copper dome with a lantern over the crossing, and a bell tower with a spire at the west front."""
    stone = dict(material="plaster", color=(0.85, 0.8, 0.68), texture_scale=2.0)
    tiles = dict(material="roof_tiles", color=(0.5, 0.22, 0.16), texture_scale=0.45)
    copper = dict(material="roof_tiles", color=(0.36, 0.56, 0.46), texture_scale=0.5)
    crossing = (cx + 2.0, cy)
    return [
        box((cx - 1.0, cy, 6.0), (16.0, 7.0, 12.0), **stone),
        roof((cx - 1.0, cy, 12.0), (16.0, 7.0), rise=3.5, hip=False, **tiles),
        box((*crossing, 6.0), (6.0, 16.0, 12.0), **stone),
        roof((*crossing, 12.0), (16.0, 6.0), rise=3.0, hip=False, yaw=np.pi / 2, **tiles),
        Revolution(base=(*crossing, 12.0), height=6.0, r0=3.6, r1=3.6, **stone),
        Sphere(center=(*crossing, 18.0), radius=3.6, **copper),  # its lower half hides in the drum
        Revolution(base=(*crossing, 21.4), height=2.5, r0=0.8, r1=0.6, **stone),
        Sphere(material="plain", color=(0.8, 0.66, 0.3), center=(*crossing, 24.3), radius=0.45),
        box((cx - 7.0, cy, 14.0), (4.0, 4.0, 28.0), **stone),
        prism((cx - 7.0, cy), 28.0, 38.0, 2.0 * np.sqrt(2.0), 0.1, 4, yaw=-np.pi / 4, material="roof_tiles",
              color=(0.3, 0.32, 0.36), texture_scale=0.4),
    ]


def _hall(cx: float, cy: float, length: float, width: float) -> list[Primitive]:
    """A long low hall (a market hall) along x: brick walls with tall windows under a shallow grey roof."""
    return [
        box((cx, cy, 4.0), (length, width, 8.0), material="facade", color=(0.66, 0.42, 0.32), texture_scale=4.0),
        roof((cx, cy, 8.0), (length, width), rise=2.5, hip=False, material="roof_tiles", color=(0.45, 0.47, 0.5),
             texture_scale=0.6),
    ]
