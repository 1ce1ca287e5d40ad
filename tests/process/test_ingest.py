"""GPS positions are read from the photos' EXIF, kept when a photo is normalised, and left out when absent."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import ExifTags, Image

from hico_plugin.process.ingest import ingest_photos, photo_info
from hico_plugin.scenes.geotagged import gps_exif

PLACES = [(47.3769, 8.5417, 408.0), (-33.8568, 151.2153, 12.5), (40.7128, -74.006, 3.0), (31.5, 35.5, -430.0)]


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_gps_is_read_from_exif_in_every_hemisphere(tmp_path, suffix):
    pixels = Image.fromarray(np.full((24, 32, 3), 90, np.uint8))
    for i, place in enumerate(PLACES):
        pixels.save(tmp_path / f"{i}{suffix}", exif=gps_exif(*place).tobytes())
        assert photo_info(tmp_path / f"{i}{suffix}").gps == pytest.approx(place, abs=1e-7)


def test_no_gps_and_a_placeholder_fix_are_no_position(tmp_path):
    pixels = Image.fromarray(np.full((24, 32, 3), 90, np.uint8))
    pixels.save(tmp_path / "plain.jpg")
    pixels.save(tmp_path / "zero.jpg", exif=gps_exif(0.0, 0.0, 0.0).tobytes())
    broken = Image.Exif()
    broken.get_ifd(ExifTags.IFD.GPSInfo)[ExifTags.GPS.GPSLatitudeRef] = "N"  # a reference without its value
    pixels.save(tmp_path / "broken.jpg", exif=broken.tobytes())
    assert [photo_info(tmp_path / name).gps for name in ("plain.jpg", "zero.jpg", "broken.jpg")] == [None] * 3


def test_a_turned_photo_keeps_its_gps_when_written_upright(tmp_path):
    exif = gps_exif(*PLACES[1])
    exif[0x0112] = 6  # stored turned: ingest rewrites it upright
    (tmp_path / "in").mkdir()
    Image.fromarray(np.full((24, 32, 3), 90, np.uint8)).save(tmp_path / "in" / "a.jpg", exif=exif.tobytes())
    done = ingest_photos(tmp_path / "in", ["a.jpg"], tmp_path / "out", tmp_path / "masks", lambda done, total: None)
    assert "a.jpg" in done["rewritten"]
    assert photo_info(tmp_path / "out" / "a.jpg").gps == pytest.approx(PLACES[1], abs=1e-7)
