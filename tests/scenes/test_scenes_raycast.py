"""The analytic ray caster against slow obvious references and hard cases."""

from __future__ import annotations

import numpy as np

from hico_plugin.scenes.raycast import Ground, RayCaster, Revolution, Sphere, box, prism, roof
from hico_plugin.scenes.render import render_view

MAT = dict(material="plain", color=(0.5, 0.5, 0.5))


def _random_rays(n, rng, spread=4.0):
    origins = rng.uniform(-spread, spread, (n, 3))
    targets = rng.uniform(-1.0, 1.0, (n, 3))
    dirs = targets - origins
    return origins, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _march(inside, origins, dirs, t_max=12.0, steps=6000):
    """Slow reference: first sample along each ray where ``inside`` is true (inf if none)."""
    ts = np.linspace(1e-3, t_max, steps)
    first = np.full(len(origins), np.inf)
    for t in ts[::-1]:  # reference loop, deliberately simple
        first[inside(origins + t * dirs)] = t
    return first, ts[1] - ts[0]


def test_box_matches_ray_marching_and_slabs():
    rng = np.random.default_rng(0)
    origins, dirs = _random_rays(400, rng)
    outside = np.abs(origins).max(1) > 1.2
    origins, dirs = origins[outside], dirs[outside]
    solid = box((0.1, -0.2, 0.3), (1.0, 1.6, 0.8), **MAT)
    t, face = solid.intersect(origins, dirs, 1e-9)
    # slab test reference for the axis-aligned box
    lo, hi = np.array([-0.4, -1.0, -0.1]), np.array([0.6, 0.6, 0.7])
    with np.errstate(divide="ignore"):
        t0, t1 = (lo - origins) / dirs, (hi - origins) / dirs
    t_near, t_far = np.minimum(t0, t1).max(1), np.maximum(t0, t1).min(1)
    expected = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
    np.testing.assert_allclose(t, expected, rtol=1e-12)
    hit = np.isfinite(t)
    assert 20 < hit.sum() < len(t)
    normals, _ = solid.surface(origins[hit] + t[hit, None] * dirs[hit], face[hit])
    assert ((normals * dirs[hit]).sum(1) < 0).all()  # entered through a face that faces the ray


def test_rotated_prism_and_roof_match_ray_marching():
    rng = np.random.default_rng(1)
    origins, dirs = _random_rays(150, rng, spread=3.0)
    for solid in (prism((0.1, 0.0), -0.5, 0.6, 1.1, 0.5, 8, yaw=0.2, **MAT),
                  roof((0, 0, -0.3), (1.8, 1.0), 0.7, hip=True, yaw=0.5, **MAT)):
        inside = lambda p: (p @ solid.normals.T - solid.offsets).max(1) <= 0
        keep = ~inside(origins)
        t, _ = solid.intersect(origins[keep], dirs[keep], 1e-9)
        reference, step = _march(inside, origins[keep], dirs[keep])
        hit = np.isfinite(reference)
        assert hit.sum() > 10
        np.testing.assert_array_equal(np.isfinite(t)[hit], True)
        assert (np.abs(t[hit] - reference[hit]) <= step + 1e-9).all()
        assert np.isinf(t[~hit & np.isinf(t)]).all()
        grazing = np.isfinite(t) & ~hit  # hits the march missed must be thin slivers only
        assert grazing.sum() <= 2


def test_cone_frustum_and_sphere_match_ray_marching():
    rng = np.random.default_rng(2)
    origins, dirs = _random_rays(200, rng, spread=3.0)
    cone = Revolution(base=(0.1, 0.0, -0.6), height=1.2, r0=0.9, r1=0.3, **MAT)
    sphere = Sphere(center=(0.2, -0.1, 0.1), radius=0.7, **MAT)

    def in_cone(p):
        q = p - np.array(cone.base)
        r = cone.r0 + (cone.r1 - cone.r0) * q[:, 2] / cone.height
        return (q[:, 2] >= 0) & (q[:, 2] <= cone.height) & (np.hypot(q[:, 0], q[:, 1]) <= r)

    in_sphere = lambda p: np.linalg.norm(p - np.array(sphere.center), axis=1) <= sphere.radius
    for solid, inside in ((cone, in_cone), (sphere, in_sphere)):
        keep = ~inside(origins)
        t, part = solid.intersect(origins[keep], dirs[keep], 1e-9)
        reference, step = _march(inside, origins[keep], dirs[keep])
        hit = np.isfinite(reference)
        assert hit.sum() > 20
        assert (np.abs(t[hit] - reference[hit]) <= step + 1e-9).all()
        assert (np.isfinite(t) & ~hit).sum() <= 2
        points = origins[keep][hit] + t[hit, None] * dirs[keep][hit]
        normals, _ = solid.surface(points, part[hit])
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
        assert ((normals * dirs[keep][hit]).sum(1) < 1e-9).all()


def test_hard_cases():
    cube = box((0, 0, 0), (2, 2, 2), **MAT)
    # axis-parallel rays: one just inside a face plane (hits), one just outside (misses)
    origins = np.array([[-5.0, 0.999, 0.0], [-5.0, 1.001, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    dirs = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    t, _ = cube.intersect(origins, dirs, 1e-9)
    np.testing.assert_allclose(t[:1], [4.0])
    assert np.isinf(t[1]) and np.isinf(t[2]) and np.isinf(t[3])  # miss, inside, pointing away
    # a vertical ray down a cylinder's axis meets the top cap; one beside it misses
    cylinder = Revolution(base=(0, 0, 0), height=2.0, r0=1.0, r1=1.0, **MAT)
    t, part = cylinder.intersect(np.array([[0.0, 0, 5], [1.5, 0, 5]]), np.array([[0, 0, -1.0], [0, 0, -1.0]]), 1e-9)
    np.testing.assert_allclose(t[0], 3.0) and np.isinf(t[1])
    assert part[0] == 2
    # ground: only from above
    ground = Ground(half_extent=10.0, **MAT)
    t, _ = ground.intersect(np.array([[0.0, 0, 1], [0.0, 0, -1], [20.0, 0, 1]]), np.array([[0, 0, -1.0]] * 3), 1e-9)
    np.testing.assert_allclose(t[0], 1.0) and np.isinf(t[1]) and np.isinf(t[2])


def test_caster_culling_changes_nothing():
    """Nearest hits with screen-rectangle culling equal brute force over all primitives."""
    rng = np.random.default_rng(3)
    prims = [Ground(half_extent=20.0, **MAT)]
    for _ in range(12):
        c = rng.uniform(-6, 6, 3) * [1, 1, 0] + [0, 0, 1]
        prims.append(box(c, rng.uniform(0.5, 2.0, 3), yaw=rng.uniform(0, 1), **MAT))
        prims.append(Sphere(center=tuple(c + [0, 0, 2.0]), radius=0.6, **MAT))
    caster = RayCaster(prims, eps=1e-9)
    from hico_plugin.scenes.orbits import intrinsics, look_at

    K = intrinsics(40, 30, 70)
    viewmat = look_at(np.array([[9.0, 7.0, 6.0]]), np.zeros((1, 3)))[0]
    view = render_view(caster, viewmat, K, 40, 30, np.array([0.0, 0.0, 1.0]), 0.3, True)
    origin = -viewmat[:3, :3].T @ viewmat[:3, 3]
    dirs = view.dirs_world.reshape(-1, 3)
    brute = np.full(len(dirs), np.inf)
    for prim in prims:
        brute = np.minimum(brute, prim.intersect(np.broadcast_to(origin, dirs.shape), dirs, 1e-9)[0])
    dir_z = (dirs @ viewmat[:3, :3].T)[:, 2]
    np.testing.assert_allclose(view.depth.ravel(), np.where(np.isfinite(brute), brute * dir_z, 0.0), rtol=1e-12)
    # shadow rays: the parallel-ray culling agrees with testing every primitive
    points = view.points.reshape(-1, 3)[view.hit.ravel()]
    sun = np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9])
    blocked = caster.occluded(points + 1e-6 * sun, sun)
    brute_blocked = np.zeros(len(points), bool)
    for prim in prims:
        brute_blocked |= np.isfinite(prim.intersect(points + 1e-6 * sun, np.broadcast_to(sun, points.shape), 1e-9)[0])
    np.testing.assert_array_equal(blocked, brute_blocked)
    assert 0 < blocked.sum() < len(blocked)
