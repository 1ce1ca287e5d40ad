"""hico-process: photos or a video -> a dataset hico-train reads (pycolmap SfM, undistortion, images_N).

    hico-process images photos/ --output data/site
    hico-process video walk.mp4 --output data/walk --num-frames 200
    hico-train hico-gs-lite --data data/site

Re-running the same command after a crash reuses the stages that finished.
"""

from __future__ import annotations

from typing import Annotated, Any, Union

import tyro

from hico_plugin.cli import run_cli
from hico_plugin.process import ProcessImagesConfig, ProcessVideoConfig

Command = Union[
    Annotated[ProcessImagesConfig, tyro.conf.subcommand("images")],
    Annotated[ProcessVideoConfig, tyro.conf.subcommand("video")],
]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    config = tyro.cli(Command, args=argv, config=(tyro.conf.OmitArgPrefixes,))
    return config.setup()


def entrypoint() -> None:
    run_cli(main)


if __name__ == "__main__":
    entrypoint()
