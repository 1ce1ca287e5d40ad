"""Photos as users hand them over -> files that SfM and training decode to the same pixels.

Each photo is normalised once: turned upright (the EXIF orientation, which COLMAP ignores, applied and cleared),
8-bit RGB, its transparency kept as a mask (white = scene), or copied byte for byte when it needs none of that; an
unreadable file is skipped with the reason. Other EXIF tags are kept: SfM starts from their focal length, and
photos with a GPS position are matched with their nearest (matching.py).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from hico_plugin.process.stages import Report

ORIENTATION_TAG = 0x0112
MAKE_TAG, MODEL_TAG = 0x010F, 0x0110
EXIF_IFD, FOCAL_LENGTH_TAG = 0x8769, 0x920A
GPS_IFD = 0x8825
GPS_LAT_REF, GPS_LAT, GPS_LON_REF, GPS_LON, GPS_ALT_REF, GPS_ALT = 1, 2, 3, 4, 5, 6  # tags of the GPS IFD
_ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")


@dataclass
class PhotoInfo:
    """What a normalised photo's file says about the camera that took it."""

    width: int
    height: int
    make: str
    model: str
    focal_mm: float | None
    gps: tuple[float, float, float] | None = None
    """(latitude, longitude in degrees, north and east positive; altitude in metres) from the GPS IFD."""

    def camera_key(self) -> tuple[Any, ...]:
        """Photos with equal keys come from one camera (COLMAP intrinsics are per size and lens)."""
        return self.width, self.height, self.make, self.model, self.focal_mm

    def describe(self) -> str:
        body = " ".join(part for part in (self.make, self.model) if part) or "no EXIF camera"
        focal = f", {self.focal_mm:g} mm" if self.focal_mm else ""
        return f"{self.width}x{self.height} ({body}{focal})"


def photo_info(path: Path) -> PhotoInfo:
    """Size and EXIF camera of ``path`` (from its header; pixels are not decoded)."""
    with Image.open(path) as image:
        exif = image.getexif()
        focal = exif.get_ifd(EXIF_IFD).get(FOCAL_LENGTH_TAG)
        try:
            focal_mm = round(float(focal), 2) if focal else None
        except (TypeError, ValueError, ZeroDivisionError):
            focal_mm = None
        return PhotoInfo(image.width, image.height, str(exif.get(MAKE_TAG, "")).strip("\x00 "),
                         str(exif.get(MODEL_TAG, "")).strip("\x00 "), focal_mm, _gps(exif.get_ifd(GPS_IFD)))


def _gps(ifd: dict) -> tuple[float, float, float] | None:
    """The position an EXIF GPS IFD holds (degrees, minutes, seconds and N/S, E/W references; altitude
    0 when absent, negative with reference 1, below sea level), or None without one. A fix at exactly
    0, 0 is a camera's placeholder, not a place (COLMAP's spatial matcher skips it too)."""
    try:
        lat, lon = (sum(float(part) / 60**i for i, part in enumerate(ifd[tag])) for tag in (GPS_LAT, GPS_LON))
        alt = float(ifd.get(GPS_ALT, 0.0))
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None
    lat = -lat if str(ifd.get(GPS_LAT_REF, "N")).upper().startswith("S") else lat
    lon = -lon if str(ifd.get(GPS_LON_REF, "E")).upper().startswith("W") else lon
    alt = -alt if ifd.get(GPS_ALT_REF) in (1, b"\x01") else alt
    if not (np.isfinite([lat, lon, alt]).all() and abs(lat) <= 90 and abs(lon) <= 180) or lat == lon == 0:
        return None
    return lat, lon, alt


def _why_unusable(path: Path) -> str | None:
    """Why ``path`` cannot be used as a photo, or None when it decodes completely."""
    if path.stat().st_size == 0:
        return "empty file (0 bytes)"
    try:
        with Image.open(path) as image:
            image.load()  # decodes every pixel: a truncated file raises here
    except UnidentifiedImageError:
        return "not an image (no known image format in its bytes)"
    except (OSError, SyntaxError, ValueError) as err:
        return f"truncated or damaged image ({err})"
    return None


def _to_rgb(image: Image.Image) -> tuple[Image.Image, np.ndarray | None]:
    """8-bit RGB and, for a photo with transparency, its alpha as a bool mask (True = scene)."""
    if image.mode == "P" and "transparency" in image.info:
        image = image.convert("RGBA")
    alpha = None
    if image.mode in _ALPHA_MODES:
        alpha = np.asarray(image.getchannel("A")) > 127
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        # 16-bit / 32-bit grey: scale the value range to 8 bits instead of clipping at 255.
        values = np.asarray(image, dtype=np.float64)
        top = 65535.0 if image.mode.startswith("I;16") or values.max() > 255 else 255.0
        image = Image.fromarray(np.clip(values / top * 255.0 + 0.5, 0, 255).astype(np.uint8), "L")
    return image.convert("RGB"), alpha


def _needs_rewrite(image: Image.Image) -> bool:
    return image.getexif().get(ORIENTATION_TAG, 1) != 1 or image.mode != "RGB"


def ingest_photos(source: Path, names: list[str], target: Path, masks: Path, report: Report) -> dict[str, Any]:
    """Normalise ``source/<name>`` into ``target/<name>`` (alpha into ``masks/<name>.png``, COLMAP's
    mask naming: features are extracted only where it is white); returns
    ``{"kept": [...], "skipped": {name: reason}, "rewritten": {name: what}, "masked": [...]}``."""
    for folder in (target, masks):
        if folder.exists():
            shutil.rmtree(folder)
    kept: list[str] = []
    skipped: dict[str, str] = {}
    rewritten: dict[str, str] = {}
    masked: list[str] = []
    for done, name in enumerate(names, start=1):
        report(done - 1, len(names))
        path, out = source / name, target / name
        reason = _why_unusable(path)
        if reason is not None:
            skipped[name] = reason
            continue
        out.parent.mkdir(parents=True, exist_ok=True)
        with Image.open(path) as image:
            if not _needs_rewrite(image):
                shutil.copy2(path, out)
                kept.append(name)
                continue
            what = []
            orientation = image.getexif().get(ORIENTATION_TAG, 1)
            if orientation != 1:
                what.append(f"turned upright (EXIF orientation {orientation})")
            if image.mode != "RGB":
                what.append(f"{image.mode} -> RGB")
            exif = image.getexif()
            upright = ImageOps.exif_transpose(image)
            rgb, alpha = _to_rgb(upright)
        exif[ORIENTATION_TAG] = 1
        _save_like(rgb, out, exif)
        if alpha is not None:
            mask_path = masks / f"{name}.png"
            mask_path.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(alpha.astype(np.uint8) * 255, "L").save(mask_path)
            masked.append(name)
            what.append("transparency kept as a mask")
        rewritten[name] = ", ".join(what)
        kept.append(name)
    if masked:  # COLMAP skips a photo whose mask is missing once a mask folder is given: all white
        for name in sorted(set(kept) - set(masked)):
            with Image.open(target / name) as image:
                size = image.size
            Image.new("L", size, 255).save(masks / f"{name}.png")
    report(len(names), len(names))
    return {"kept": kept, "skipped": skipped, "rewritten": rewritten, "masked": masked}


def _save_like(image: Image.Image, out: Path, exif: Image.Exif) -> None:
    """Save in the format the name says; JPEG at quality 95 without chroma subsampling, so the
    re-encoding of a turned photo changes its pixels by about one grey level."""
    suffix = out.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        image.save(out, "JPEG", quality=95, subsampling=0, exif=exif.tobytes())
    elif suffix in (".png", ".webp", ".tif", ".tiff"):
        image.save(out, exif=exif.tobytes())
    else:  # .bmp has no EXIF
        image.save(out)
