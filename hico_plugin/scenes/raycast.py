"""Analytic ray caster: convex polyhedra, solids of revolution (cylinders, cones, frusta) and spheres.

Independent of the Gaussian rasterizer on purpose: the built-in scenes are the ground truth it is measured
against. numpy float64, vectorised over rays; each primitive is tested only against the rays that can reach it
(camera rays inside its projected hull's pixel rectangle, shadow rays inside its silhouette rectangle from the
sun). Shapes: ``origins``/``dirs``: [R, 3] (dirs unit length), ``t``: [R] (``inf`` = miss).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MISS = np.inf


@dataclass
class Primitive:
    """A solid with a material. ``top_material`` / ``bottom_material`` replace ``material`` on faces
    whose outward normal points up / down (flat roofs, soffits under eaves)."""

    material: str
    color: tuple[float, float, float]
    texture_scale: float = 1.0
    top_material: str | None = None
    bottom_material: str | None = None

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        raise NotImplementedError

    def may_block(self, direction: np.ndarray) -> bool:
        """False when no ray along ``direction`` [3] can hit the solid (skips shadow tests)."""
        return True

    def hull_points(self) -> np.ndarray:
        """[V, 3] points whose convex hull contains the solid (default: its bounding box corners)."""
        center, radius = self.bounding_sphere()
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        return center + radius * signs

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
        """Entry distance ``t`` [R] (> eps, inf if missed) and a face/part index [R] int.
        origins: [R, 3] or [1, 3] (one origin for all rays)."""
        raise NotImplementedError

    def surface(self, points: np.ndarray, part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normals [n, 3] and surface coordinates uv [n, 2] at hit points [n, 3]."""
        raise NotImplementedError


def _face_tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-face texture axes: u horizontal along the face, v up the face (world z for walls)."""
    up = np.array([0.0, 0.0, 1.0])
    u = np.cross(up, normals)
    flat = np.linalg.norm(u, axis=1) < 1e-6  # horizontal faces: u = world x
    u[flat] = [1.0, 0.0, 0.0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    return u, v


@dataclass
class ConvexPolyhedron(Primitive):
    """Intersection of half-spaces ``normals @ x <= offsets`` (boxes, prisms, pyramid frusta, roofs)."""

    normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [F, 3] unit, outward
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [F]
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [V, 3] for bounds

    def __post_init__(self) -> None:
        self.normals = np.asarray(self.normals, np.float64)
        self.offsets = np.asarray(self.offsets, np.float64)
        self._u, self._v = _face_tangents(self.normals)

    def hull_points(self):
        return self.vertices

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        center = 0.5 * (self.vertices.min(0) + self.vertices.max(0))
        return center, float(np.linalg.norm(self.vertices - center, axis=1).max())

    def intersect(self, origins, dirs, eps):
        denom = dirs @ self.normals.T  # [R, F]
        num = self.offsets[None] - origins @ self.normals.T  # [R, F]; > 0 means inside this plane
        # a ray parallel to a plane gets a huge finite t: +big if inside (never the exit), -big if
        # outside (an exit before any entry, so a miss)
        denom[denom == 0] = 1e-300
        t_plane = num / denom
        face = np.where(denom < 0, t_plane, -np.inf).argmax(1)
        t_enter = np.take_along_axis(t_plane, face[:, None], 1)[:, 0]
        t_exit = np.where(denom > 0, t_plane, np.inf).min(1)
        hit = (t_enter <= t_exit) & (t_enter > eps) & (np.take_along_axis(denom, face[:, None], 1)[:, 0] < 0)
        return np.where(hit, t_enter, MISS), face

    def surface(self, points, part):
        return self.normals[part], np.stack(
            [(points * self._u[part]).sum(1), (points * self._v[part]).sum(1)], 1
        )


@dataclass
class Revolution(Primitive):
    """Solid frustum of a cone around a vertical axis (cylinder when r0 == r1), capped at both ends.

    Base centre ``base``, height ``height``, radius ``r0`` at the base and ``r1`` at the top.
    """

    base: tuple[float, float, float] = (0.0, 0.0, 0.0)
    height: float = 1.0
    r0: float = 1.0
    r1: float = 1.0

    def hull_points(self):
        r = max(self.r0, self.r1)
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [0, 1])).reshape(3, -1).T
        return np.asarray(self.base, np.float64) + signs * [r, r, self.height]

    def bounding_sphere(self):
        center = np.asarray(self.base, np.float64) + [0, 0, self.height / 2]
        return center, float(np.hypot(max(self.r0, self.r1), self.height / 2))

    def intersect(self, origins, dirs, eps):
        p = origins - np.asarray(self.base)
        k = (self.r1 - self.r0) / self.height
        px, py, pz = p.T
        dx, dy, dz = dirs.T
        rz = self.r0 + k * pz
        a = dx * dx + dy * dy - k * k * dz * dz
        b = 2.0 * (px * dx + py * dy - k * dz * rz)
        c = px * px + py * py - rz * rz
        with np.errstate(divide="ignore", invalid="ignore"):
            disc = b * b - 4 * a * c
            sq = np.sqrt(np.maximum(disc, 0.0))
            degenerate = np.abs(a) < 1e-12  # ray parallel to a cone generator: one linear root
            t1 = np.where(degenerate, -c / b, (-b - sq) / (2 * a))
            t2 = np.where(degenerate, np.inf, (-b + sq) / (2 * a))
            candidates = []
            for t in (t1, t2):
                z = pz + t * dz
                ok = (disc >= 0) & (t > eps) & (z >= 0) & (z <= self.height)
                candidates.append(np.where(ok, t, MISS))
            for z_cap, r_cap in ((0.0, self.r0), (self.height, self.r1)):
                t = (z_cap - pz) / dz
                x, y = px + t * dx, py + t * dy
                ok = (t > eps) & (x * x + y * y <= r_cap * r_cap)
                candidates.append(np.where(ok, t, MISS))
        stack = np.stack(candidates, 1)  # [R, 4]: side, side, bottom cap, top cap
        part = stack.argmin(1)
        t = np.take_along_axis(stack, part[:, None], 1)[:, 0]
        return t, np.select([part < 2, part == 2], [0, 1], 2)

    def surface(self, points, part):
        p = points - np.asarray(self.base)
        k = (self.r1 - self.r0) / self.height
        side = np.stack([p[:, 0], p[:, 1], -k * (self.r0 + k * p[:, 2])], 1)
        normals = np.where(
            (part == 0)[:, None], side, np.where((part == 1)[:, None], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0])
        )
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        arc = np.arctan2(p[:, 1], p[:, 0]) * 0.5 * (self.r0 + self.r1)
        slant = p[:, 2] * np.sqrt(1 + k * k)
        uv = np.where((part == 0)[:, None], np.stack([arc, slant], 1), p[:, :2])
        return normals, uv


@dataclass
class Sphere(Primitive):
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 1.0

    def bounding_sphere(self):
        return np.asarray(self.center, np.float64), self.radius

    def intersect(self, origins, dirs, eps):
        p = origins - np.asarray(self.center)
        b = (p * dirs).sum(1)
        c = (p * p).sum(1) - self.radius**2
        disc = b * b - c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t_near, t_far = -b - sq, -b + sq
        t = np.where(t_near > eps, t_near, np.where(t_far > eps, t_far, MISS))
        return np.where(disc >= 0, t, MISS), np.zeros(len(dirs), np.int64)

    def surface(self, points, part):
        p = points - np.asarray(self.center)
        normals = p / np.linalg.norm(p, axis=1, keepdims=True)
        return normals, np.stack([np.arctan2(p[:, 1], p[:, 0]) * self.radius, p[:, 2]], 1)


@dataclass
class Ground(Primitive):
    """The square ``|x|, |y| <= half_extent`` at height ``z``, seen from above (its underside is
    never visible from cameras above ground)."""

    z: float = 0.0
    half_extent: float = 100.0

    def may_block(self, direction):
        return direction[2] < 0  # seen from above only

    def hull_points(self):
        h = self.half_extent
        return np.array([[-h, -h, self.z], [h, -h, self.z], [-h, h, self.z], [h, h, self.z]])

    def bounding_sphere(self):
        return np.array([0.0, 0.0, self.z]), self.half_extent * np.sqrt(2)

    def intersect(self, origins, dirs, eps):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.z - origins[:, 2]) / dirs[:, 2]
        x, y = origins[:, 0] + t * dirs[:, 0], origins[:, 1] + t * dirs[:, 1]
        ok = (dirs[:, 2] < 0) & (t > eps) & (np.abs(x) <= self.half_extent) & (np.abs(y) <= self.half_extent)
        return np.where(ok, t, MISS), np.zeros(len(dirs), np.int64)

    def surface(self, points, part):
        return np.broadcast_to([0.0, 0.0, 1.0], points.shape).copy(), points[:, :2].copy()


# --------------------------------------------------------------------------------------------------
# Constructors
# --------------------------------------------------------------------------------------------------


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _from_local_planes(normals, offsets, vertices, center, rotation, **material) -> ConvexPolyhedron:
    """Planes and vertices given in a local frame, placed at ``center`` with ``rotation`` [3, 3]."""
    normals = np.asarray(normals, np.float64)
    norm = np.linalg.norm(normals, axis=1)
    normals, offsets = normals / norm[:, None], np.asarray(offsets, np.float64) / norm
    world_normals = normals @ rotation.T
    center = np.asarray(center, np.float64)
    return ConvexPolyhedron(
        normals=world_normals,
        offsets=offsets + world_normals @ center,
        vertices=np.asarray(vertices, np.float64) @ rotation.T + center,
        **material,
    )


def box(center, size, rotation=None, yaw: float = 0.0, **material) -> ConvexPolyhedron:
    """An oriented box: ``size`` full extents (x, y, z) in its frame; ``rotation`` [3, 3] or ``yaw``."""
    half = np.asarray(size, np.float64) / 2
    rotation = _yaw_matrix(yaw) if rotation is None else np.asarray(rotation, np.float64)
    eye = np.eye(3)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    return _from_local_planes(
        np.concatenate([eye, -eye]), np.concatenate([half, half]), signs * half, center, rotation, **material
    )


def prism(center_xy, z0: float, z1: float, r0: float, r1: float, sides: int, yaw: float = 0.0, **material):
    """A regular ``sides``-gon pyramid frustum between heights z0 and z1 (prism when r0 == r1);
    ``r0``/``r1`` are circumradii at the bottom/top."""
    angles = yaw + (np.arange(sides) + 0.5) * 2 * np.pi / sides  # face directions
    apothem0, apothem1 = r0 * np.cos(np.pi / sides), r1 * np.cos(np.pi / sides)
    slope = (apothem0 - apothem1) / (z1 - z0)
    side_normals = np.stack([np.cos(angles), np.sin(angles), np.full(sides, slope)], 1)
    normals = np.concatenate([side_normals, [[0, 0, 1.0], [0, 0, -1.0]]])
    offsets = np.concatenate([np.full(sides, apothem0 + slope * z0), [z1, -z0]])
    corner = yaw + np.arange(sides) * 2 * np.pi / sides
    ring = np.stack([np.cos(corner), np.sin(corner)], 1)
    vertices = np.concatenate(
        [np.c_[ring * r0, np.full(sides, z0)], np.c_[ring * r1, np.full(sides, z1)]]
    )
    center = np.array([center_xy[0], center_xy[1], 0.0])
    return _from_local_planes(normals, offsets, vertices, center, np.eye(3), **material)


def roof(center, size_xy, rise: float, hip: bool, yaw: float = 0.0, **material) -> ConvexPolyhedron:
    """A gable (``hip=False``) or hip roof over a ``size_xy`` footprint whose eaves sit at
    ``center[2]``; the ridge runs along local x and reaches ``rise`` above the eaves."""
    hx, hy = size_xy[0] / 2, size_xy[1] / 2
    run_x = hy if hip else 0.0
    # slope planes through the eave line (a.x = e, z = 0) and the ridge (a.x = e - run, z = rise)
    normals = [[0, rise, hy], [0, -rise, hy], [rise, 0, run_x], [-rise, 0, run_x], [0, 0, -1.0]]
    offsets = [rise * hy, rise * hy, rise * hx, rise * hx, 0.0]
    ridge = hx - run_x
    vertices = [[sx * hx, sy * hy, 0] for sx in (-1, 1) for sy in (-1, 1)] + [
        [-ridge, 0, rise], [ridge, 0, rise]
    ]
    return _from_local_planes(normals, offsets, vertices, center, _yaw_matrix(yaw), **material)


# --------------------------------------------------------------------------------------------------
# Casting
# --------------------------------------------------------------------------------------------------


@dataclass
class Hits:
    """Nearest hits of R rays: ``t`` [R] (inf = miss), ``primitive`` [R] (-1 = miss), ``part`` [R]."""

    t: np.ndarray
    primitive: np.ndarray
    part: np.ndarray


class RayCaster:
    """Nearest-hit / any-hit queries against a fixed list of primitives."""

    def __init__(self, primitives: list[Primitive], eps: float = 1e-6):
        self.primitives = primitives
        self.eps = eps
        bounds = [p.bounding_sphere() for p in primitives]
        self._centers = np.array([b[0] for b in bounds], np.float64)  # [P, 3]
        self._radii = np.array([b[1] for b in bounds], np.float64) * (1 + 1e-6) + eps  # [P]
        self._hulls = [p.hull_points() for p in primitives]  # [V, 3] each, fixed like the bounds

    def screen_candidates(self, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> list[np.ndarray]:
        """Per primitive, the flat pixel indices (row-major, [H*W]) whose rays may hit it: the pixel
        rectangle covering its bounding sphere's projection. viewmat: [4, 4] world->camera."""
        centers = self._centers @ viewmat[:3, :3].T + viewmat[:3, 3]  # [P, 3] camera frame
        outside = _outside_frustum(centers, self._radii, K, width, height)
        everything = np.arange(width * height)
        out = []
        for hull, (x, y, z), r, culled in zip(self._hulls, centers, self._radii, outside):
            if culled:  # no ray of the view can reach its bounding sphere
                out.append(everything[:0])
                continue
            hull = hull @ viewmat[:3, :3].T + viewmat[:3, 3]
            if (hull[:, 2] > 1e-9).all():  # in front: the projected hull's bounding box is exact
                u = K[0, 0] * hull[:, 0] / hull[:, 2] + K[0, 2]
                v = K[1, 1] * hull[:, 1] / hull[:, 2] + K[1, 2]
                u0, u1 = _clamp(np.floor(u.min()), width), _clamp(np.ceil(u.max()) + 1, width)
                v0, v1 = _clamp(np.floor(v.min()), height), _clamp(np.ceil(v.max()) + 1, height)
                out.append(
                    (np.arange(v0, v1)[:, None] * width + np.arange(u0, u1)[None]).ravel()
                    if u0 < u1 and v0 < v1 else everything[:0]
                )
                continue
            ranges = []
            for lateral, focal, principal, size in ((x, K[0, 0], K[0, 2], width), (y, K[1, 1], K[1, 2], height)):
                # the sphere seen in the (lateral, z) plane is a disc: bound its tangent angles exactly
                dist = np.hypot(lateral, z)
                if dist <= r:
                    ranges.append((0, size))
                    continue
                centre_angle, half_angle = np.arctan2(lateral, z), np.arcsin(r / dist)
                lo, hi = centre_angle - half_angle, centre_angle + half_angle
                if hi <= -np.pi / 2 or lo >= np.pi / 2:
                    ranges.append((0, 0))
                    continue
                lo_px = -np.inf if lo <= -np.pi / 2 else focal * np.tan(lo) + principal
                hi_px = np.inf if hi >= np.pi / 2 else focal * np.tan(hi) + principal
                ranges.append((int(np.clip(np.floor(lo_px), 0, size)), int(np.clip(np.ceil(hi_px) + 1, 0, size))))
            (u0, u1), (v0, v1) = ranges
            if z + r <= 0 or u0 >= u1 or v0 >= v1:
                out.append(everything[:0])
            elif (u0, u1, v0, v1) == (0, width, 0, height):
                out.append(everything)
            else:
                out.append((np.arange(v0, v1)[:, None] * width + np.arange(u0, u1)[None]).ravel())
        return out

    def cast(self, origin: np.ndarray, dirs: np.ndarray, candidates: list[np.ndarray]) -> Hits:
        """Nearest hit per ray from one camera centre. origin: [3], dirs: [R, 3] unit,
        candidates: per primitive the ray indices that may hit it (``screen_candidates``)."""
        n = len(dirs)
        best_t = np.full(n, MISS)
        best_prim = np.full(n, -1, np.int64)
        best_part = np.zeros(n, np.int64)
        for index, (prim, rays) in enumerate(zip(self.primitives, candidates)):
            if rays.size == 0:
                continue
            t, part = prim.intersect(origin[None], dirs[rays], self.eps)  # origin broadcasts
            closer = t < best_t[rays]
            rays, t, part = rays[closer], t[closer], part[closer]
            best_t[rays], best_prim[rays], best_part[rays] = t, index, part
        return Hits(best_t, best_prim, best_part)

    def occluded(self, origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """[R] bool: the ray from each of ``origins`` [R, 3] along ``direction`` [3] hits anything.

        Parallel rays: in a frame (a, b, direction), a primitive can only block rays whose (a, b)
        fall in its projected bounding rectangle and that start below its far end; rays sorted by
        a give each primitive its candidates by binary search."""
        a = np.cross(direction, [1.0, 0.0, 0.0] if abs(direction[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        basis = np.stack([a, np.cross(direction, a), direction])
        coords = origins @ basis.T  # [R, 3]
        order = np.argsort(coords[:, 0])
        sorted_a = coords[order, 0]
        blocked = np.zeros(len(origins), bool)
        for prim, hull in zip(self.primitives, self._hulls):
            if not prim.may_block(direction):
                continue
            corners = hull @ basis.T
            lo, hi = corners.min(0), corners.max(0)
            first, last = np.searchsorted(sorted_a, [lo[0] - self.eps, hi[0] + self.eps])
            rays = order[first:last]
            b, along = coords[rays, 1], coords[rays, 2]
            rays = rays[(b >= lo[1] - self.eps) & (b <= hi[1] + self.eps) & (along < hi[2]) & ~blocked[rays]]
            if rays.size:
                t, _ = prim.intersect(origins[rays], np.broadcast_to(direction, (rays.size, 3)), self.eps)
                blocked[rays[np.isfinite(t)]] = True
        return blocked

    def surface(self, points: np.ndarray, hits: Hits) -> tuple[np.ndarray, np.ndarray]:
        """Outward normals [R, 3] and uv [R, 2] at hit points (zeros for misses)."""
        normals = np.zeros((len(points), 3))
        uv = np.zeros((len(points), 2))
        for index, rays in group_by_primitive(hits.primitive):
            normals[rays], uv[rays] = self.primitives[index].surface(points[rays], hits.part[rays])
        return normals, uv


def _clamp(value: float, size: int) -> int:
    return int(min(max(value, 0), size))


def _outside_frustum(centers: np.ndarray, radii: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """[P] bool: the sphere (camera-frame ``centers`` [P, 3], ``radii`` [P]) lies wholly behind the
    camera or beyond one of the four planes through its centre and the image's edges."""
    x, y, z = centers.T
    outside = z + radii <= 0
    for lateral, focal, principal, size in ((x, K[0, 0], K[0, 2], width), (y, K[1, 1], K[1, 2], height)):
        for slope, sign in ((-principal / focal, -1.0), ((size - principal) / focal, 1.0)):
            # signed distance beyond the plane lateral = slope * z, positive outside the image
            outside |= sign * (lateral - slope * z) / np.hypot(1.0, slope) > radii
    return outside


def group_by_primitive(primitive: np.ndarray):
    """Yield (primitive index, ray indices) for every primitive hit at least once; primitive: [R]."""
    order = np.argsort(primitive, kind="stable")
    values, starts = np.unique(primitive[order], return_index=True)
    for value, rays in zip(values, np.split(order, starts[1:])):
        if value >= 0:
            yield int(value), rays
