import pytest

from hico_plugin.errors import HicoError
from hico_plugin.registry import Registry


def test_register_and_get():
    reg = Registry("widget")

    @reg.register("a")
    class A:
        pass

    assert reg.get("a") is A
    assert "a" in reg and "b" not in reg
    assert reg.names() == ["a"]


def test_unknown_name_lists_registered():
    reg = Registry("widget")
    reg.register("x")(object)
    with pytest.raises(HicoError, match=r"unknown widget 'y'; registered: x"):
        reg.get("y")


def test_duplicate_registration_rejected():
    reg = Registry("widget")
    reg.register("x")(int)
    with pytest.raises(ValueError):
        reg.register("x")(float)
