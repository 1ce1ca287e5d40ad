"""COLMAP cameras as plain data: what the loaders need of ``pycolmap.Camera``, without importing pycolmap
(a large resident import) into a training run.

``Camera`` holds a COLMAP camera (id, model name, size, parameters in COLMAP's per-model order) and
evaluates SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV itself, with COLMAP's formulas
(colmap/sensor/models.h) and pixel convention (pixel centres at +0.5). COLMAP's other models are
evaluated by pycolmap, imported then.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pycolmap

# COLMAP's camera models: the index is the model id (cameras.bin), the value the number of parameters.
MODEL_NAMES = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV",
               "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE",
               "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE", "EUCM", "EQUIRECTANGULAR")
NUM_PARAMS = dict(zip(MODEL_NAMES, (3, 4, 4, 5, 8, 8, 12, 5, 4, 5, 12, 16, 4, 5, 3, 4, 6, 2)))
INVALID_CAMERA_ID = 2**32 - 1  # COLMAP's kInvalidCameraId: a camera in no model

# Models whose parameters start f, cx, cy (one focal length); the other perspective models start
# fx, fy, cx, cy. EQUIRECTANGULAR has neither.
_ONE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
              "SIMPLE_DIVISION", "SIMPLE_FISHEYE"}
# The models evaluated here; the others go to pycolmap.
_EVALUATED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_UNDISTORTED = ("SIMPLE_PINHOLE", "PINHOLE")

# BasePerspectiveCameraModel::IterativeUndistortion: Newton steps in a trust region.
_NEWTON_ITERATIONS = 100
_MIN_STEP_SQUARED_NORM = 1e-10
_STEP_RADIUS = 0.1  # also relative to the point's norm


@dataclass(kw_only=True, eq=False)
class Camera:
    """A COLMAP camera: ``params`` [P] float64 in COLMAP's order for ``model`` (e.g. OPENCV:
    fx, fy, cx, cy, k1, k2, p1, p2); ``width`` x ``height`` pixels."""

    camera_id: int = INVALID_CAMERA_ID
    model: str  # COLMAP model name
    width: int
    height: int
    params: np.ndarray

    def __post_init__(self) -> None:
        if self.model not in NUM_PARAMS:
            raise ValueError(f"unknown COLMAP camera model {self.model!r}")
        self.params = np.array(self.params, dtype=np.float64)  # a copy: cameras never share parameters
        if self.params.shape != (NUM_PARAMS[self.model],):
            raise ValueError(f"{self.model} takes {NUM_PARAMS[self.model]} parameters, got {self.params.shape}")
        self.camera_id, self.width, self.height = int(self.camera_id), int(self.width), int(self.height)

    # ------------------------------------------------------------------ parameters
    @property
    def focal_length_x(self) -> float:
        return float(self.params[0])

    @property
    def focal_length_y(self) -> float:
        return float(self.params[self._first_pp() - 1])

    @property
    def principal_point_x(self) -> float:
        return float(self.params[self._first_pp()])

    @property
    def principal_point_y(self) -> float:
        return float(self.params[self._first_pp() + 1])

    def _first_pp(self) -> int:
        if self.model == "EQUIRECTANGULAR":
            raise ValueError("EQUIRECTANGULAR has no focal length or principal point")
        return 1 if self.model in _ONE_FOCAL else 2

    def rescale(self, width: int, height: int) -> None:
        """Resize in place to ``width`` x ``height`` (COLMAP's Camera::Rescale: a single focal length
        scales by the mean of the two factors; the principal point follows the image)."""
        scale_x, scale_y = width / self.width, height / self.height
        first_pp = self._first_pp()
        if first_pp == 1:
            self.params[0] *= 0.5 * (scale_x + scale_y)
        else:
            self.params[0] *= scale_x
            self.params[1] *= scale_y
        self.params[first_pp] *= scale_x
        self.params[first_pp + 1] *= scale_y
        self.width, self.height = int(width), int(height)

    # ------------------------------------------------------------------ projection
    def img_from_cam(self, points: np.ndarray) -> np.ndarray:
        """points: [N, 3] camera-frame points, or [N, 2] normalised coordinates (z = 1) -> [N, 2]
        pixels; NaN for points not in front of the camera (z below machine epsilon, as COLMAP)."""
        points = np.asarray(points, dtype=np.float64)
        if points.shape[1] == 2:
            points = np.concatenate([points, np.ones((len(points), 1))], axis=1)
        if self.model not in _EVALUATED:
            return self.to_pycolmap().img_from_cam(points)
        u, v, w = points[:, 0], points[:, 1], points[:, 2]
        fx, fy, cx, cy = self._pinhole()
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.model in _UNDISTORTED:
                x, y = fx * u / w + cx, fy * v / w + cy
            else:
                uu, vv = u / w, v / w
                du, dv = self._distortion(uu, vv)
                x, y = fx * (uu + du) + cx, fy * (vv + dv) + cy
        pixels = np.stack([x, y], axis=-1)
        pixels[~(w >= np.finfo(np.float64).eps)] = np.nan
        return pixels

    def cam_from_img(self, pixels: np.ndarray) -> np.ndarray:
        """pixels: [N, 2] -> [N, 2] normalised camera coordinates (z = 1), the distortion inverted by
        COLMAP's Newton iteration; NaN where it does not converge."""
        pixels = np.asarray(pixels, dtype=np.float64)
        if self.model not in _EVALUATED:
            return self.to_pycolmap().cam_from_img(pixels)
        fx, fy, cx, cy = self._pinhole()
        with np.errstate(divide="ignore", invalid="ignore"):
            lifted = np.stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy], axis=-1)
        if self.model in _UNDISTORTED:
            return lifted
        return self._undistort(lifted)

    def _pinhole(self) -> tuple[float, float, float, float]:
        return self.focal_length_x, self.focal_length_y, self.principal_point_x, self.principal_point_y

    def _coefficients(self) -> tuple[float, float, float, float]:
        """(k1, k2, p1, p2) of COLMAP's OpenCV distortion: SIMPLE_RADIAL's (k) and RADIAL's (k1, k2)
        distortions are OpenCV's with the other terms zero, to the bit."""
        extra = self.params[self._first_pp() + 2:]
        return tuple(float(value) for value in (*extra, 0.0, 0.0, 0.0, 0.0)[:4])

    def _distortion(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """COLMAP's OpenCVCameraModel::Distortion: the offsets (du, dv) [N] of normalised points."""
        k1, k2, p1, p2 = self._coefficients()
        u2, uv, v2 = u * u, u * v, v * v
        r2 = u2 + v2
        radial = k1 * r2 + k2 * r2 * r2
        return (u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2),
                v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2))

    def _jacobian(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
        """d(point + distortion) / d(point) at [N] points, the Jacobian COLMAP's Newton step takes by
        automatic differentiation, in closed form: its entries (a, b, c, d) = [[a, b], [c, d]]."""
        k1, k2, p1, p2 = self._coefficients()
        r2 = u * u + v * v
        radial = k1 * r2 + k2 * r2 * r2
        slope = k1 + 2.0 * k2 * r2  # d radial / d (r2)
        cross = 2.0 * u * v * slope + 2.0 * p1 * u + 2.0 * p2 * v
        return (1.0 + radial + 2.0 * u * u * slope + 2.0 * p1 * v + 6.0 * p2 * u, cross,
                cross, 1.0 + radial + 2.0 * v * v * slope + 2.0 * p2 * u + 6.0 * p1 * v)

    def _undistort(self, distorted: np.ndarray) -> np.ndarray:
        """[N, 2] distorted normalised points -> the points the distortion moves there [N, 2]
        (BasePerspectiveCameraModel::IterativeUndistortion, every point stepped until its step is
        small; NaN for points that do not get there in its 100 iterations)."""
        out = np.full_like(distorted, np.nan)
        active = np.arange(len(distorted))
        x = distorted.copy()
        with np.errstate(all="ignore"):
            for _ in range(_NEWTON_ITERATIONS):
                if not len(active):
                    break
                u, v = x[active, 0], x[active, 1]
                du, dv = self._distortion(u, v)
                a, b, c, d = self._jacobian(u, v)
                ru, rv = u + du - distorted[active, 0], v + dv - distorted[active, 1]
                det = a * d - b * c
                step_u, step_v = (d * ru - b * rv) / det, (a * rv - c * ru) / det
                radius2 = np.maximum((u * u + v * v) * _STEP_RADIUS * _STEP_RADIUS, _STEP_RADIUS * _STEP_RADIUS)
                norm2 = step_u * step_u + step_v * step_v
                shrink = np.where(norm2 > radius2, np.sqrt(radius2 / norm2), 1.0)  # the trust region
                step_u, step_v = step_u * shrink, step_v * shrink
                x[active, 0], x[active, 1] = u - step_u, v - step_v
                done = step_u * step_u + step_v * step_v < _MIN_STEP_SQUARED_NORM
                out[active[done]] = x[active[done]]
                active = active[~done]
        return out

    # ------------------------------------------------------------------ pycolmap
    def todict(self) -> dict:
        """``pycolmap.Camera.todict()``'s keys and values (the model by name)."""
        return {"camera_id": self.camera_id, "model": self.model, "width": self.width, "height": self.height,
                "params": self.params.copy(), "has_prior_focal_length": False}

    def to_pycolmap(self) -> pycolmap.Camera:
        """The same camera as pycolmap's (for the places that hand cameras to COLMAP; imports pycolmap)."""
        import pycolmap

        return pycolmap.Camera(self.todict())

    @classmethod
    def from_pycolmap(cls, camera: pycolmap.Camera) -> Camera:
        """The plain copy of a camera pycolmap made (its undistorter's, for the models only it evaluates)."""
        return cls(camera_id=camera.camera_id, model=camera.model.name, width=camera.width, height=camera.height,
                   params=camera.params)


def camera_centres(viewmats: np.ndarray) -> np.ndarray:
    """[N, 4, 4] world->camera -> [N, 3] camera centres in the world."""
    rotations, translations = viewmats[:, :3, :3], viewmats[:, :3, 3:]
    return -(np.transpose(rotations, (0, 2, 1)) @ translations)[..., 0]
