"""The HiCo model: owns field, renderer and losses; decides what each step renders."""

from hico_plugin.model.hico import HiCoModel, HiCoModelConfig

__all__ = ["HiCoModel", "HiCoModelConfig"]
