"""The viewer's camera-path panel (as nerfstudio's render panel): keyframes taken at the browser
camera, edited, reordered and deleted; the smooth path through them (``export.camera_paths.keyframe_path``)
drawn in the scene and played in the browser; saved and loaded as nerfstudio's camera_path.json, which
``hico-render camera-path`` renders.

Keyframes live in the viewer's frame (the run's normalised frame); the file holds the dataset's source
frame (``SceneTransform``), so a path saved here renders in nerfstudio and the other way round.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import viser

from hico_plugin.cameras import Cameras
from hico_plugin.data.transform import SceneTransform
from hico_plugin.errors import HicoError
from hico_plugin.export.camera_path_file import keyframe_entries, read_keyframes, write_camera_path
from hico_plugin.export.camera_paths import keyframe_path
from hico_plugin.viewer.conversions import camera_to_viser, viser_to_camera

DEFAULT_SECONDS = 2.0
"""Transition time of a new keyframe to the next (nerfstudio's default)."""


@dataclass
class Keyframe:
    """One keyframe: the browser camera's pose (camera->world, OpenCV axes, viewer frame), its
    vertical field of view in degrees and the seconds from it to the next keyframe."""

    wxyz: np.ndarray
    position: np.ndarray
    fov_deg: float
    seconds: float = DEFAULT_SECONDS


class CameraPathPanel:
    """The "Camera path" folder of ``server``'s GUI and the keyframes it edits.

    ``transform`` maps the viewer's frame to the dataset's source frame (files are written there);
    ``save_dir`` is where paths are saved and loaded (None: saving is off); ``extent`` scales the drawn
    frustums; ``size`` is the initial render size (width, height).
    """

    def __init__(self, server: viser.ViserServer, transform: SceneTransform, save_dir: Path | None,
                 extent: float, size: tuple[int, int]):
        self.server, self.transform, self.save_dir, self.extent = server, transform, save_dir, extent
        self.keyframes: list[Keyframe] = []
        self.selected = -1
        self._lock = threading.RLock()
        self._playing = threading.Event()
        self._drawn = 0  # keyframe frustums in the scene
        gui = server.gui
        with gui.add_folder("Camera path", expand_by_default=False):
            self.add_button = gui.add_button("Add keyframe", hint="A keyframe at your current view")
            self.choice = gui.add_dropdown("Keyframe", ["none"], initial_value="none", hint="The keyframe edited below")
            self.fov = gui.add_slider("FOV (deg)", min=5.0, max=150.0, step=1.0, initial_value=50.0,
                                      hint="Vertical field of view of the selected keyframe")
            self.seconds = gui.add_number("Seconds to next", DEFAULT_SECONDS, min=0.05, max=600.0, step=0.05,
                                          hint="Time from the selected keyframe to the next one")
            self.move_button = gui.add_button("Move to current view", hint="Put the selected keyframe where you are")
            self.order = gui.add_button_group("Order", ["Earlier", "Later"])
            self.delete_button = gui.add_button("Delete keyframe", color="red")
            self.fps = gui.add_number("FPS", 30, min=1, max=240, step=1)
            self.size = gui.add_vector2("Resolution", (max(16, size[0]), max(16, size[1])), min=(16, 16), step=1,
                                        hint="Width and height of the video")
            self.loop = gui.add_checkbox("Loop", False, hint="Return to the first keyframe at the end")
            self.show = gui.add_checkbox("Show path", True)
            self.play_button = gui.add_button("Play", hint="Fly your view along the path")
            self.file_name = gui.add_text("File", "camera_path.json",
                                          hint="Name in the run's camera_paths/ folder (nerfstudio's camera_path.json)")
            self.save_button = gui.add_button("Save", disabled=save_dir is None)
            self.load_button = gui.add_button("Load", disabled=save_dir is None)
            self.status = gui.add_markdown("_no keyframes_")
        self.add_button.on_click(lambda event: self.add(event.client))
        self.move_button.on_click(lambda event: self.move_selected(event.client))
        self.delete_button.on_click(lambda _: self.delete_selected())
        self.order.on_click(lambda event: self.shift_selected(-1 if event.target.value == "Earlier" else 1))
        self.choice.on_update(lambda _: self._select_from_gui())
        self.fov.on_update(lambda _: self._edit_selected())
        self.seconds.on_update(lambda _: self._edit_selected())
        for handle in (self.fps, self.size, self.loop, self.show):
            handle.on_update(lambda _: self.redraw())
        self.play_button.on_click(lambda event: self.play(event.client))
        self.save_button.on_click(lambda event: self._report(event.client, "Saved", self.save))
        self.load_button.on_click(lambda event: self._report(event.client, "Loaded", self.load))

    # ----- editing ---------------------------------------------------------------------------------
    def add(self, client: viser.ClientHandle | None) -> None:
        """A keyframe at ``client``'s camera, after the selected one (at the end when none is)."""
        if client is None:
            return
        camera = client.camera
        keyframe = Keyframe(np.asarray(camera.wxyz, np.float64), np.asarray(camera.position, np.float64),
                            math.degrees(camera.fov), float(self.seconds.value))
        with self._lock:
            at = self.selected + 1 if 0 <= self.selected < len(self.keyframes) - 1 else len(self.keyframes)
            self.keyframes.insert(at, keyframe)
            self.selected = at
        self.redraw()

    def move_selected(self, client: viser.ClientHandle | None) -> None:
        with self._lock:
            if client is None or not 0 <= self.selected < len(self.keyframes):
                return
            keyframe = self.keyframes[self.selected]
            keyframe.wxyz = np.asarray(client.camera.wxyz, np.float64)
            keyframe.position = np.asarray(client.camera.position, np.float64)
        self.redraw()

    def delete_selected(self) -> None:
        with self._lock:
            if not 0 <= self.selected < len(self.keyframes):
                return
            del self.keyframes[self.selected]
            self.selected = min(self.selected, len(self.keyframes) - 1)
        self.redraw()

    def shift_selected(self, offset: int) -> None:
        """Move the selected keyframe ``offset`` places along the path."""
        with self._lock:
            new = self.selected + offset
            if not 0 <= self.selected < len(self.keyframes) or not 0 <= new < len(self.keyframes):
                return
            self.keyframes.insert(new, self.keyframes.pop(self.selected))
            self.selected = new
        self.redraw()

    def _select_from_gui(self) -> None:
        value = self.choice.value
        with self._lock:
            index = int(value) - 1 if value.isdigit() else -1
            if index == self.selected or not 0 <= index < len(self.keyframes):
                return
            self.selected = index
            keyframe = self.keyframes[index]
        self.fov.value, self.seconds.value = keyframe.fov_deg, keyframe.seconds

    def _edit_selected(self) -> None:
        with self._lock:
            if not 0 <= self.selected < len(self.keyframes):
                return
            keyframe = self.keyframes[self.selected]
            if (keyframe.fov_deg, keyframe.seconds) == (float(self.fov.value), float(self.seconds.value)):
                return
            keyframe.fov_deg, keyframe.seconds = float(self.fov.value), float(self.seconds.value)
        self.redraw()

    # ----- the path --------------------------------------------------------------------------------
    def keyframe_cameras(self) -> tuple[Cameras, torch.Tensor]:
        """The keyframes as cameras [K] at the panel's resolution (viewer frame) and their seconds [K]."""
        width, height = (max(16, int(round(v))) for v in self.size.value)
        with self._lock:
            cameras = [viser_to_camera(k.wxyz, k.position, math.radians(k.fov_deg), width, height) for k in self.keyframes]
            seconds = torch.tensor([k.seconds for k in self.keyframes], dtype=torch.float64)
        if not cameras:
            raise HicoError("camera path: add a keyframe first")
        return (Cameras(torch.stack([c.viewmat for c in cameras]), torch.stack([c.K for c in cameras]),
                        torch.full((len(cameras),), width), torch.full((len(cameras),), height)), seconds)

    def frames(self) -> Cameras:
        """Every frame of the path at the panel's fps (viewer frame)."""
        keyframes, seconds = self.keyframe_cameras()
        return keyframe_path(keyframes, seconds, float(self.fps.value), loop=bool(self.loop.value))

    def redraw(self) -> None:
        """Refresh the keyframe list, the keyframe frustums and the path line."""
        with self._lock:
            keyframes, selected = list(self.keyframes), self.selected
        options = [str(i + 1) for i in range(len(keyframes))] or ["none"]
        self.choice.options = options
        self.choice.value = options[selected] if 0 <= selected < len(keyframes) else options[0]
        scene = self.server.scene
        aspect = float(self.size.value[0]) / float(self.size.value[1])
        for i, keyframe in enumerate(keyframes):
            scene.add_camera_frustum(
                f"/camera_path/keyframe_{i:03d}", fov=math.radians(keyframe.fov_deg), aspect=aspect,
                scale=0.1 * self.extent, thickness=2.0, thickness_units="screen", wxyz=keyframe.wxyz,
                position=keyframe.position, color=(230, 120, 20) if i == selected else (200, 160, 40),
                visible=bool(self.show.value))
        for stale in range(len(keyframes), self._drawn):
            scene.remove_by_name(f"/camera_path/keyframe_{stale:03d}")
        self._drawn = len(keyframes)
        total = 0.0
        if len(keyframes) >= 2:
            centres = self.frames().centers.double().numpy()
            segments = np.stack([centres[:-1], centres[1:]], axis=1)
            scene.add_line_segments("/camera_path/spline", segments, colors=(230, 120, 20), thickness=2.0,
                                    thickness_units="screen", visible=bool(self.show.value))
            total = sum(k.seconds for k in (keyframes if self.loop.value else keyframes[:-1]))
        else:
            scene.remove_by_name("/camera_path/spline")
        self.status.content = (f"{len(keyframes)} keyframes, {total:.1f} s" if keyframes else "_no keyframes_")

    def play(self, client: viser.ClientHandle | None) -> None:
        """Fly ``client``'s camera along the path at its fps (in the background; a second press stops)."""
        if client is None:
            return
        if self._playing.is_set():
            self._playing.clear()
            return
        try:
            frames = self.frames()
        except HicoError as err:
            client.add_notification("Camera path", str(err), auto_close_seconds=4.0)
            return
        period = 1.0 / float(self.fps.value)
        self._playing.set()

        def fly() -> None:
            start = time.monotonic()
            for i in range(len(frames)):
                if not self._playing.is_set():
                    break
                wxyz, position, fov, _ = camera_to_viser(frames[i])
                with client.atomic():
                    client.camera.fov, client.camera.wxyz, client.camera.position = fov, wxyz, position
                time.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))
            self._playing.clear()

        threading.Thread(target=fly, name="camera-path-play", daemon=True).start()

    # ----- files -----------------------------------------------------------------------------------
    def _path(self) -> Path:
        name = str(self.file_name.value).strip()
        if self.save_dir is None:
            raise HicoError("camera path: this viewer has no run folder to save into")
        if not name or Path(name).name != name or name.startswith("."):
            raise HicoError(f"camera path: '{name}' is not a plain file name (it is saved in {self.save_dir})")
        return self.save_dir / (name if name.endswith(".json") else f"{name}.json")

    def save(self) -> Path:
        """Write the path (frames and keyframes) as camera_path.json in ``save_dir``; returns its path."""
        keyframes, seconds = self.keyframe_cameras()
        path = self._path()
        path.parent.mkdir(parents=True, exist_ok=True)
        return write_camera_path(path, self.frames(), self.transform, float(self.fps.value),
                                 keyframes=keyframe_entries(keyframes, seconds, self.transform),
                                 is_cycle=bool(self.loop.value), default_transition_sec=DEFAULT_SECONDS,
                                 default_fov=float(self.fov.value), smoothness_value=0.0)

    def load(self) -> Path:
        """Replace the keyframes by those of the file named in the panel."""
        path = self._path()
        cameras, seconds, fps, loop = read_keyframes(path, self.transform)
        keyframes = []
        for i in range(len(cameras)):
            wxyz, position, fov, _ = camera_to_viser(cameras[i])
            keyframes.append(Keyframe(np.asarray(wxyz), np.asarray(position), math.degrees(fov), float(seconds[i])))
        with self._lock:
            self.keyframes, self.selected = keyframes, len(keyframes) - 1
        self.fps.value, self.loop.value = fps, loop
        self.size.value = (int(cameras.widths[0]), int(cameras.heights[0]))
        self.redraw()
        return path

    def _report(self, client: viser.ClientHandle | None, done: str, action: Any) -> None:
        try:
            message = f"{done} {action()}"
        except HicoError as err:
            message = str(err)
        self.status.content = message
        if client is not None:
            client.add_notification("Camera path", message, auto_close_seconds=4.0)
