"""Make the README's pictures with the commands themselves: ``python docs/make_pictures.py [--run RUN]``.

- ``docs/images/render_depth_normals.png``: a test view of a city-block run (``hico-render test``), its
  colour, depth and normals side by side;
- ``docs/images/viewer.png``: that run in ``hico-view``, shot in headless Chromium;
- ``docs/images/psnr_vs_time.png``: the time-to-quality plot of a small ``hico-bench`` run.

Without ``--run`` it first trains ``hico-gs-lite`` on city-block for ``--steps`` steps. Work files go
to ``--work`` (default ``outputs/docs-pictures``). Needs Chromium (``apt-get install chromium``) and
matplotlib (the ``[bench]`` extra).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
IMAGES = ROOT / "docs" / "images"
MAX_BYTES = 300_000
sys.path.insert(0, str(ROOT / "tests"))  # the tests' headless Chromium driver


def run(*command: str) -> None:
    print("$", " ".join(command), flush=True)
    subprocess.run(command, check=True, cwd=ROOT)


def write_small_png(path: Path, image: np.ndarray) -> None:
    """RGB ``image`` as a PNG under MAX_BYTES: shrunk by a fifth at a time until it fits."""
    while True:
        ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if ok and len(data) <= MAX_BYTES:
            path.write_bytes(data.tobytes())
            print(f"wrote {path.relative_to(ROOT)} ({image.shape[1]}x{image.shape[0]}, {len(data) // 1000} KB)")
            return
        size = (round(image.shape[1] * 0.8), round(image.shape[0] * 0.8))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def render_depth_normals(run_dir: Path, work: Path, view: int) -> None:
    out = work / "render"
    run("hico-render", "test", "--load-config", str(run_dir / "config.yml"), "--outputs", "rgb", "depth", "normal",
        "--output-dir", str(out))
    panels = [read_rgb(out / name / f"{view:05d}.png") for name in ("rgb", "depth", "normal")]
    gap = np.full((panels[0].shape[0], 4, 3), 255, np.uint8)
    write_small_png(IMAGES / "render_depth_normals.png",
                    np.hstack([panels[0], gap, panels[1], gap, panels[2]]))


def viewer_screenshot(run_dir: Path, work: Path, port: int) -> None:
    from helpers_browser import CHROMIUM, DevToolsPage

    if CHROMIUM is None:
        raise SystemExit("viewer.png needs Chromium: apt-get install -y chromium")
    server = subprocess.Popen(["hico-view", "--load-config", str(run_dir / "config.yml"), "--viewer.port", str(port),
                               "--viewer.max-resolution", "1280"],
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = None
        for line in server.stdout:  # the viewer prints its URL once it serves
            print(line, end="")
            found = re.search(r"viewer: (http://\S+)", line)
            if found:
                url = found.group(1)
            if "Ctrl-C to stop" in line:
                break
        if url is None:
            raise SystemExit("hico-view did not start")
        page = DevToolsPage(str(work / "chromium-profile"), width=1280, height=800)
        try:
            page.call("Page.navigate", url=url)
            _wait_for_render(page)
            for label in ("Anchors", "Training cameras"):  # the render itself, unobstructed
                if not page.click_text(label):
                    raise SystemExit(f"the viewer's page has no {label!r} checkbox")
            if not page.evaluate(_DROP_NOTICE):
                print("note: no software-WebGL notice to close")
            shot = _wait_for_render(page)
        finally:
            page.close()
        write_small_png(IMAGES / "viewer.png", shot)
    finally:
        server.terminate()
        server.wait(timeout=30)


# Headless Chromium renders WebGL in software, and viser says so in a notice over the scene: close it
# (the button of the smallest box around its text).
_DROP_NOTICE = """(() => {
  let box = [...document.querySelectorAll('body *')].find(e => [...e.childNodes].some(
    n => n.nodeType === 3 && n.textContent.includes('Software WebGL')));
  while (box && !box.querySelector('button')) box = box.parentElement;
  if (!box) return false;
  box.querySelector('button').click();
  return true;
})()"""


def _wait_for_render(page, timeout: float = 120.0) -> np.ndarray:
    """A screenshot once the render fills the middle of the page (the empty canvas is one flat colour)
    and two shots a few seconds apart agree (the full-resolution render has replaced the previews)."""
    deadline, last = time.monotonic() + timeout, None
    while time.monotonic() < deadline:
        time.sleep(3.0)
        shot = page.screenshot()
        h, w = shot.shape[:2]
        middle = shot[h // 3: 2 * h // 3, w // 4: w // 2].astype(np.float32)
        if middle.std() > 10.0 and last is not None and np.abs(shot.astype(np.float32) - last).mean() < 1.0:
            return shot
        last = shot.astype(np.float32)
    raise SystemExit("the viewer's page showed no render")


def bench_plot(work: Path) -> None:
    out = work / "bench"
    run("hico-bench", "quick", "--budgets", "25", "50", "100", "200", "--no-mesh", "--output-dir", str(out))
    write_small_png(IMAGES / "psnr_vs_time.png", read_rgb(out / "psnr_vs_time.png"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="a trained city-block run folder (default: train one)")
    parser.add_argument("--steps", type=int, default=1500, help="training steps when no --run is given")
    parser.add_argument("--work", type=Path, default=ROOT / "outputs" / "docs-pictures")
    parser.add_argument("--view", type=int, default=2, help="the test view of render_depth_normals.png")
    parser.add_argument("--port", type=int, default=7031)
    args = parser.parse_args()
    IMAGES.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    run_dir = args.run
    if run_dir is None:
        run_dir = args.work / "run"
        if not (run_dir / "eval.json").is_file():
            shutil.rmtree(run_dir, ignore_errors=True)
            run("hico-train", "hico-gs-lite", "--max-steps", str(args.steps), "--vis", "none",
                "--output-dir", str(run_dir))
    render_depth_normals(run_dir, args.work, args.view)
    viewer_screenshot(run_dir, args.work, args.port)
    bench_plot(args.work)


if __name__ == "__main__":
    main()
