"""Names from dataset files stay inside their folder."""

import os

import pytest

from hico_plugin.data.paths import resolve_inside
from hico_plugin.errors import HicoError


def test_plain_and_nested_names_resolve_inside(tmp_path):
    assert resolve_inside(tmp_path, "a.png", "x") == tmp_path / "a.png"
    assert resolve_inside(tmp_path, "sub/b.jpg", "x") == tmp_path / "sub" / "b.jpg"
    assert resolve_inside(tmp_path, "sub\\c.jpg", "x") == tmp_path / "sub" / "c.jpg"


@pytest.mark.parametrize("name", ["/etc/passwd", "../outside.png", "sub/../../x.png", "C:\\x.png",
                                  "\\\\server\\share\\x.png", "", "a\x00b"])
def test_escaping_names_are_refused_naming_the_entry(tmp_path, name):
    with pytest.raises(HicoError, match="images.bin: image 3"):
        resolve_inside(tmp_path, name, "images.bin: image 3")


def test_symlink_that_leaves_the_folder_is_refused(tmp_path):
    folder, outside = tmp_path / "images", tmp_path / "secret"
    folder.mkdir()
    outside.mkdir()
    os.symlink(outside, folder / "link")
    with pytest.raises(HicoError, match="outside"):
        resolve_inside(folder, "link/x.png", "images.bin: image 0")
    os.symlink(folder / "a.png", folder / "inner.png")  # a link that stays inside is fine
    assert resolve_inside(folder, "inner.png", "x") == folder / "inner.png"
