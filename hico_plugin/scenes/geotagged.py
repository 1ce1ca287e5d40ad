"""A generated scene's views as a drone hands them over: JPEGs with a GPS position in their EXIF.

The position is the camera centre (scene frame: metres, x east, y north, z up) as east, north and up
of ``origin`` (latitude, longitude in degrees, altitude in metres on the WGS84 ellipsoid), converted
by COLMAP's own GPS transform. hico-process's spatial matching reads it back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
from PIL import ExifTags, Image

ORIGIN = (47.3769, 8.5417, 408.0)
"""Where a scene's origin is placed (a city centre in the northern and eastern hemispheres)."""


def gps_exif(lat: float, lon: float, alt: float) -> Image.Exif:
    """An EXIF block holding a GPS IFD at (lat, lon, alt) as cameras write it: degrees, minutes and
    seconds with N/S and E/W references, the altitude with its above / below sea level reference."""
    exif = Image.Exif()
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    for value, ref_tag, tag, refs in ((lat, ExifTags.GPS.GPSLatitudeRef, ExifTags.GPS.GPSLatitude, "NS"),
                                      (lon, ExifTags.GPS.GPSLongitudeRef, ExifTags.GPS.GPSLongitude, "EW")):
        degrees, rest = divmod(abs(float(value)), 1.0)
        minutes, rest = divmod(rest * 60.0, 1.0)
        gps[ref_tag] = refs[int(value < 0)]
        gps[tag] = (degrees, minutes, rest * 60.0)
    gps[ExifTags.GPS.GPSAltitudeRef] = b"\x01" if alt < 0 else b"\x00"
    gps[ExifTags.GPS.GPSAltitude] = abs(float(alt))
    return exif


def write_geotagged_photos(scene: Path, target: Path, origin: tuple[float, float, float] = ORIGIN,
                           noise_m: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """``scene/images/<stem>.png`` (a generated scene) -> ``target/<stem>.jpg`` with its camera centre in
    ``scene/sparse/0``, plus Gaussian noise of ``noise_m`` metres per axis (a GPS fix's error), as GPS
    in its EXIF; returns {photo name: true camera centre [3]}."""
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    images = sorted(model.images.values(), key=lambda image: image.name)
    centres = np.array([image.projection_center() for image in images])
    measured = centres + np.random.default_rng(seed).normal(0.0, noise_m, centres.shape) if noise_m else centres
    positions = pycolmap.GPSTransform().enu_to_ellipsoid(measured, *origin)
    target.mkdir(parents=True, exist_ok=True)
    known = {}
    for image, centre, position in zip(images, centres, positions):
        name = f"{Path(image.name).stem}.jpg"
        with Image.open(scene / "images" / image.name) as photo:
            photo.convert("RGB").save(target / name, quality=95, exif=gps_exif(*position).tobytes())
        known[name] = centre
    return known
