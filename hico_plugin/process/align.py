"""Similarity alignment of point sets (Umeyama 1991): how far recovered cameras are from known ones."""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R [3, 3], t [3]) minimising sum |scale * R @ src_i + t - dst_i|^2 (src, dst: [N, 3], N >= 3)."""
    src_mean, dst_mean = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - src_mean, dst - dst_mean
    covariance = dst_c.T @ src_c / len(src)
    u, singular, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection is no rotation
        sign[2, 2] = -1.0
    rotation = u @ sign @ vt
    variance = (src_c**2).sum() / len(src)
    scale = float(np.trace(np.diag(singular) @ sign) / variance)
    return scale, rotation, dst_mean - scale * rotation @ src_mean


def aligned_errors(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[N] distances between ``dst`` and ``src`` after the best similarity maps ``src`` onto ``dst``."""
    scale, rotation, translation = umeyama(src, dst)
    return np.linalg.norm(scale * src @ rotation.T + translation - dst, axis=1)
