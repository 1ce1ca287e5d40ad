"""Training engine: trainer, optimisers, checkpoints, callbacks; knows nothing about Gaussians.

Public API (see each module): ``TrainerConfig(...).setup(model=..., dataset=..., callbacks=[...]) -> Trainer``;
``load_run(config_path, checkpoint=None, device=None) -> LoadedRun``; ``Optimizers(param_groups, schedules)`` with
``resize_group(name, new_params, kept_rows, num_new)``; ``ParamGroupOptimizerConfig(...).schedule(max_steps,
extent) -> LRSchedule``; ``save_config`` / ``load_config``; ``distributed``: ``is_main_process``,
``all_reduce_sum_``, ``all_reduce_mean_``, ``get_rank``, ``get_world_size``.
"""

from hico_plugin.engine.callbacks import TrainerCallback
from hico_plugin.engine.config_io import load_config, save_config
from hico_plugin.engine.distributed import all_reduce_mean_, all_reduce_sum_, is_main_process
from hico_plugin.engine.evaluation import evaluate, write_eval_json
from hico_plugin.engine.optimizers import Optimizers, ParamGroupOptimizerConfig
from hico_plugin.engine.protocol import StepOutput, TrainableModel, TrainBatch, TrainDataset
from hico_plugin.engine.schedule import LRSchedule
from hico_plugin.engine.loading import LoadedRun, load_run
from hico_plugin.engine.trainer import Trainer, TrainerConfig, TrainResult

__all__ = [
    "LoadedRun",
    "LRSchedule",
    "Optimizers",
    "ParamGroupOptimizerConfig",
    "StepOutput",
    "TrainBatch",
    "TrainDataset",
    "TrainResult",
    "TrainableModel",
    "Trainer",
    "TrainerCallback",
    "TrainerConfig",
    "all_reduce_mean_",
    "all_reduce_sum_",
    "evaluate",
    "is_main_process",
    "load_config",
    "load_run",
    "save_config",
    "write_eval_json",
]
