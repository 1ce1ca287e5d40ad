"""Camera paths for rendering videos of a run: an orbit around the scene and a smooth path through
given cameras. Everything is in the frame of the input cameras (training works in the normalised
frame) and follows ``hico_plugin.cameras``: viewmat world->camera, OpenCV axes."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hico_plugin.cameras import Cameras
from hico_plugin.data.transform import scene_up
from hico_plugin.errors import HicoError


def rotmat_to_quat(rotmats: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] -> unit quaternions [..., 4] (w, x, y, z) with w >= 0.

    Each quaternion is built from the largest of its four squared components (Shepperd), so no
    branch divides by a small number.
    """
    m = rotmats
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = torch.stack([
        torch.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0],
                     m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22,
                     m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 - m00 - m11 + m22], -1),
    ], -2)  # [..., 4 candidates, 4]
    best = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                        1 - m00 - m11 + m22], -1).argmax(-1)
    quat = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quat_slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Spherical interpolation of unit quaternions q0, q1 [..., 4] at t [...] along the shorter arc."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    t = t[..., None]
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    # Nearly equal rotations: the sin ratio is 0/0, the normalised lerp is exact to first order.
    close = sin_theta < 1e-6
    safe = torch.where(close, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(close, 1 - t, torch.sin((1 - t) * theta) / safe)
    w1 = torch.where(close, t, torch.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / out.norm(dim=-1, keepdim=True)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Unit quaternions [..., 4] (w, x, y, z) -> rotation matrices [..., 3, 3]."""
    w, x, y, z = quats.unbind(-1)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, -1).reshape(*quats.shape[:-1], 3, 3)


def viewmats_from(rotations: Tensor, centres: Tensor) -> Tensor:
    """World->camera rotations [F, 3, 3] and camera centres [F, 3] -> viewmats [F, 4, 4]."""
    viewmats = torch.zeros(len(centres), 4, 4, dtype=centres.dtype, device=centres.device)
    viewmats[:, :3, :3] = rotations
    viewmats[:, :3, 3] = -(rotations @ centres[:, :, None])[:, :, 0]
    viewmats[:, 3, 3] = 1
    return viewmats


def look_at(eyes: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """Viewmats [F, 4, 4] of cameras at ``eyes`` [F, 3] looking at ``target`` [3] (or [F, 3]) with
    image-up along ``up`` [3]; OpenCV axes (x right, y down, z forward)."""
    forward = torch.nn.functional.normalize(target - eyes, dim=-1)
    right = torch.nn.functional.normalize(torch.cross(forward, up.expand_as(forward), dim=-1), dim=-1)
    down = torch.cross(forward, right, dim=-1)
    return viewmats_from(torch.stack([right, down, forward], -2), eyes)


def focus_point(cameras: Cameras) -> Tensor:
    """The point [3] nearest (least squares) to every camera's optical axis: what the cameras look at.
    Cameras that all look the same way have no such point; the mean centre pushed one mean
    camera-to-centre distance forward stands in."""
    rot = cameras.viewmats[:, :3, :3].to(torch.float64)
    centres = cameras.centers.to(torch.float64)
    axes = rot[:, 2, :]  # camera z (forward) in world coordinates
    projector = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]  # [C, 3, 3]
    system = projector.sum(0)
    if len(cameras) >= 2 and torch.linalg.eigvalsh(system)[0] > 1e-3 * len(cameras):
        return torch.linalg.solve(system, (projector @ centres[:, :, None]).sum(0))[:, 0]
    mean = centres.mean(0)
    spread = (centres - mean).norm(dim=-1).mean()
    return mean + axes.mean(0) * (spread if spread > 1e-9 else 1.0)


def orbit_path(cameras: Cameras, num_frames: int) -> Cameras:
    """``num_frames`` cameras on a circle around the scene centre, looking at it.

    The centre is ``focus_point``; the circle lies at the cameras' mean height above it (along
    ``data.transform.scene_up``) with their mean horizontal distance as radius, and starts at the bearing of the camera
    farthest from the up axis. Intrinsics and size are the first camera's. Returns Cameras in the input frame.
    """
    if num_frames < 1 or len(cameras) == 0:
        raise HicoError(f"orbit: expected >= 1 frame and >= 1 camera, got {num_frames} frames, {len(cameras)} cameras")
    up, centre = scene_up(cameras.viewmats), focus_point(cameras)
    # the vertical's sign is the side the cameras' image-up axes lean to; none when they cancel
    if abs(float(up @ -cameras.viewmats[:, 1, :3].to(torch.float64).mean(0))) < 1e-6:
        raise HicoError("orbit: the cameras share no up direction (their image-up axes cancel out)")
    offsets = cameras.centers.to(torch.float64) - centre
    heights = offsets @ up
    horizontal = offsets - heights[:, None] * up
    radius = horizontal.norm(dim=-1).mean()
    if radius < 1e-9:
        raise HicoError("orbit: the cameras all sit on the scene's up axis; there is no circle to follow")
    first = horizontal.norm(dim=-1).argmax()  # a bearing that is well defined
    e1 = horizontal[first] / horizontal[first].norm()
    e2 = torch.cross(up, e1, dim=0)
    angles = torch.arange(num_frames, dtype=torch.float64) * (2 * math.pi / num_frames)
    eyes = centre + heights.mean() * up + radius * (torch.cos(angles)[:, None] * e1 + torch.sin(angles)[:, None] * e2)
    viewmats = look_at(eyes, centre, up)
    return _with_intrinsics(viewmats, cameras, torch.zeros(num_frames, dtype=torch.long))


def interpolate_path(cameras: Cameras, num_frames: int) -> Cameras:
    """``num_frames`` cameras along the path through ``cameras`` in their order: centres lerped,
    rotations slerped, intrinsics lerped (all at the first camera's size); the first and last
    frames are the first and last cameras."""
    if num_frames < 1 or len(cameras) == 0:
        raise HicoError(f"interpolate: expected >= 1 frame and >= 1 camera, "
                        f"got {num_frames} frames, {len(cameras)} cameras")
    count = len(cameras)
    t = torch.linspace(0, count - 1, num_frames, dtype=torch.float64)  # key i sits at t = i
    start = t.floor().long().clamp(max=max(count - 2, 0))
    end = (start + 1).clamp(max=count - 1)
    u = t - start
    rot = cameras.viewmats[:, :3, :3].to(torch.float64)
    quats = rotmat_to_quat(rot)
    centres = cameras.centers.to(torch.float64)
    rotations = quat_to_rotmat(quat_slerp(quats[start], quats[end], u))
    positions = centres[start] + u[:, None] * (centres[end] - centres[start])
    viewmats = viewmats_from(rotations, positions)
    Ks = _Ks_at_first_size(cameras)
    K = Ks[start] + u[:, None, None] * (Ks[end] - Ks[start])
    return Cameras(viewmats.to(cameras.viewmats.dtype), K.to(cameras.Ks.dtype),
                   cameras.widths[:1].expand(num_frames).clone(), cameras.heights[:1].expand(num_frames).clone())


def keyframe_path(keyframes: Cameras, seconds: Tensor, fps: float, loop: bool = False, tension: float = 0.0) -> Cameras:
    """The cameras of a path through ``keyframes`` [K] at ``fps``: keyframe i is reached at the sum of
    ``seconds`` [K] before it (``seconds[i]``: time from keyframe i to the next; the last one's counts
    only when ``loop`` returns to the first). Centres follow a cardinal spline in time (Catmull-Rom at
    ``tension`` 0: through every keyframe, velocity continuous in m/s), rotations are slerped and the
    focal lengths lerped between neighbouring keyframes; every frame has the first keyframe's size."""
    count = len(keyframes)
    if count == 0 or fps <= 0 or bool((seconds[: count if loop else count - 1] <= 0).any()):
        raise HicoError(f"camera path: expected >= 1 keyframe, fps > 0 and every transition > 0 s, got "
                        f"{count} keyframes, fps {fps}, transitions {seconds.tolist()}")
    if count == 1:
        return _with_intrinsics(keyframes.viewmats[:1], keyframes, torch.zeros(1, dtype=torch.long))
    segments = count if loop else count - 1
    durations = seconds[:segments].to(torch.float64)
    starts = torch.cat([torch.zeros(1, dtype=torch.float64), durations.cumsum(0)])
    total = float(starts[-1])
    num_frames = max(int(round(total * fps)) + (0 if loop else 1), 2)
    t = torch.arange(num_frames, dtype=torch.float64) / fps
    t = t.clamp(max=total) if not loop else t
    segment = (torch.searchsorted(starts, t, right=True) - 1).clamp(0, segments - 1)
    u = ((t - starts[segment]) / durations[segment]).clamp(0, 1)
    keys = torch.arange(count)
    neighbour = (lambda i: i % count) if loop else (lambda i: i.clamp(0, count - 1))
    span = (lambda i: i % segments) if loop else (lambda i: i.clamp(0, segments - 1))
    centres = keyframes.centers.to(torch.float64)
    # velocity (per second) at each keyframe: the mean of its two neighbouring chords' velocities, so the
    # speed has no jump where a short transition meets a long one
    before = (centres[keys] - centres[neighbour(keys - 1)]) / durations[span(keys - 1)][:, None]
    after = (centres[neighbour(keys + 1)] - centres[keys]) / durations[span(keys)][:, None]
    velocity = (1 - tension) * (before + after) / 2
    following = (segment + 1) % count
    b, c, d = centres[segment], centres[following], durations[segment][:, None]
    m0, m1 = velocity[segment] * d, velocity[following] * d  # Hermite tangents in the segment's own unit
    u1 = u[:, None]
    h00, h10, h01, h11 = 2 * u1**3 - 3 * u1**2 + 1, u1**3 - 2 * u1**2 + u1, -2 * u1**3 + 3 * u1**2, u1**3 - u1**2
    positions = h00 * b + h10 * m0 + h01 * c + h11 * m1
    quats = rotmat_to_quat(keyframes.viewmats[:, :3, :3].to(torch.float64))
    rotations = quat_to_rotmat(quat_slerp(quats[segment], quats[following], u))
    Ks = _Ks_at_first_size(keyframes)
    K = Ks[segment] + u[:, None, None] * (Ks[following] - Ks[segment])
    return Cameras(viewmats_from(rotations, positions).to(keyframes.viewmats.dtype), K.to(keyframes.Ks.dtype),
                   keyframes.widths[:1].expand(num_frames).clone(), keyframes.heights[:1].expand(num_frames).clone())


def _Ks_at_first_size(cameras: Cameras) -> Tensor:
    """Every camera's K [C, 3, 3] rescaled to the first camera's width and height (float64)."""
    Ks = cameras.Ks.to(torch.float64).clone()
    sx = cameras.widths[0].double() / cameras.widths.double()
    sy = cameras.heights[0].double() / cameras.heights.double()
    Ks[:, 0] *= sx[:, None]
    Ks[:, 1] *= sy[:, None]
    return Ks


def _with_intrinsics(viewmats: Tensor, cameras: Cameras, which: Tensor) -> Cameras:
    return Cameras(viewmats.to(cameras.viewmats.dtype), cameras.Ks[which].clone(),
                   cameras.widths[which].clone(), cameras.heights[which].clone())
