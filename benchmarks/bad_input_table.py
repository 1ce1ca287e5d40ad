"""Re-runs the bad-input table: each case as a user would meet it, printing the exit code,
the last stderr line and the time to fail. ``python benchmarks/bad_input_table.py [WORKDIR]``.

Trains one tiny run first (hico-gs-lite on the built-in tiny scene, 4 steps) for the run cases.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hico_plugin.rasterizer.fused import EXTENSION
from hico_plugin.scenes.ring_dataset import write_ring_dataset

ENV = {**os.environ, "HICO_NO_FUSED": os.environ.get("HICO_NO_FUSED", "1")}
BIN = Path(sys.executable).parent


def run(args, cwd=None, env=None, timeout=900, pick=""):
    """Exit code, the last stderr line (the last one holding ``pick``), seconds, the finished process."""
    start = time.perf_counter()
    done = subprocess.run(args, capture_output=True, text=True, cwd=cwd, env=env or ENV, timeout=timeout)
    lines = [line for line in done.stderr.splitlines() if line.strip() and pick in line]
    if not lines:
        lines = [line for line in done.stdout.splitlines() if line.strip()] or [""]
    return done.returncode, lines[-1], time.perf_counter() - start, done


def row(case, result, extra=""):
    code, line, seconds, _ = result
    print(f"| {case} | exit {code} | {line[:300]} | {seconds:.1f} s{extra} |", flush=True)


def main(work: Path) -> None:
    work.mkdir(parents=True, exist_ok=True)
    run_dir = work / "run"
    if not (run_dir / "config.yml").is_file():
        code, line, seconds, done = run([BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "4",
                                         "--save-every", "2", "--vis", "none", "--progress", "none",
                                         "--output-dir", str(run_dir)])
        assert code == 0, done.stderr[-3000:]
    config = run_dir / "config.yml"
    print("| case | exit | the one line | time to fail |\n|---|---|---|---|")

    evil = work / "evil.ckpt"
    marker = work / "pwned"
    marker.unlink(missing_ok=True)
    subprocess.run([sys.executable, "-c", f"import torch, pathlib\nclass E:\n    def __reduce__(self): return (pathlib.Path.touch, (pathlib.Path({str(marker)!r}),))\n"
                    f"torch.save({{'step': 1, 'model': E()}}, {str(evil)!r})"], check=True)
    row("crafted pickle checkpoint, hico-eval --checkpoint", run([BIN / "hico-eval", "--load-config", str(config), "--checkpoint", str(evil)]),
        f"; file created: {marker.exists()}")

    tagged = work / "tagged" / "config.yml"
    tagged.parent.mkdir(exist_ok=True)
    tagged.write_text(config.read_text().replace("!dataclass:hico_plugin.presets.HiCoTrainerConfig", "!dataclass:this.Something", 1))
    row("YAML tag !dataclass:this.Something", run([BIN / "hico-eval", "--load-config", str(tagged)]))

    for label, name in (("absolute image name", "/etc/hostname"), ("'../' image name", "../escape.png")):
        data = work / f"names_{name.count('.')}"
        shutil.rmtree(data, ignore_errors=True)
        write_ring_dataset(data, text=True)
        images_txt = data / "sparse" / "0" / "images.txt"
        images_txt.write_text(images_txt.read_text().replace("view_001.png", name))
        row(f"{label} in sparse/0, hico-inspect", run([BIN / "hico-inspect", str(data)]))

    kernels = work / "kernels"
    shutil.rmtree(kernels, ignore_errors=True)
    stale = kernels / EXTENSION.build_dir().name  # the compositor's build folder under $HICO_CACHE_DIR/kernels
    stale.mkdir(parents=True)
    (stale / "lock").write_text("")
    render = ("import torch\nfrom hico_plugin.rasterizer import rasterize\n"
              "out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),"
              " torch.ones(1), torch.ones(1, 3), torch.eye(4), torch.tensor([[60.0, 0, 33], [0, 60, 25], [0, 0, 1]]),"
              " 64, 48, compositor='fused', use_compile=False)\nprint('rendered')\n")
    env = {k: v for k, v in ENV.items() if k != "HICO_NO_FUSED"}
    env["HICO_CACHE_DIR"] = str(work)
    result = run([sys.executable, "-c", render], env=env, pick="stale")
    row("stale kernel build lock (killed build), then a render", result, f"; rendered: {'rendered' in result[3].stdout}")

    compiler = work / "hung-c++"
    compiler.write_text("#!/bin/sh\nexec sleep 600\n")
    compiler.chmod(0o755)
    shutil.rmtree(kernels, ignore_errors=True)
    env.update(CXX=str(compiler), HICO_KERNEL_BUILD_TIMEOUT="10")
    result = run([sys.executable, "-c", render.replace("compositor='fused', ", "")], env=env)
    row("compiler hangs during the first-use build (timeout set to 10 s), then a render", result,
        f"; rendered: {'rendered' in result[3].stdout}")

    sig_dir = work / "sigterm"
    shutil.rmtree(sig_dir, ignore_errors=True)
    proc = subprocess.Popen([BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "400", "--vis", "none",
                             "--progress", "none", "--log-every", "1", "--output-dir", str(sig_dir)],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=ENV)
    while not (sig_dir / "metrics.jsonl").is_file() or len((sig_dir / "metrics.jsonl").read_text().splitlines()) < 3:
        time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    sent = time.perf_counter()
    _, err = proc.communicate(timeout=600)
    lines = [line for line in err.splitlines() if line.strip()]
    print(f"| SIGTERM during training | exit {proc.returncode} | {lines[-1][:300]} | {time.perf_counter() - sent:.1f} s after the signal |")
    code, line, seconds, done = run([BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "8", "--vis", "none",
                                     "--progress", "none", "--log-every", "1", "--resume", "--output-dir", str(sig_dir)])
    import json
    steps = [json.loads(x)["step"] for x in (sig_dir / "metrics.jsonl").read_text().splitlines() if '"eval/' not in x]
    print(f"| ... then --resume (max-steps 8) | exit {code} | duplicate steps in metrics.jsonl: {len(steps) - len(set(steps))} | {seconds:.1f} s |")

    newest = sorted((run_dir / "checkpoints").iterdir())[-1]
    bad = newest.with_name("step-000009999.ckpt")
    bad.write_bytes(newest.read_bytes()[:1000])
    row("newest checkpoint truncated, hico-eval", run([BIN / "hico-eval", "--load-config", str(config), "--output-path", str(work / "eval_t.json")]),
        "; eval ran on the older one")
    bad.write_bytes(os.urandom(4096))
    row("newest checkpoint random bytes, hico-eval", run([BIN / "hico-eval", "--load-config", str(config), "--output-path", str(work / "eval_r.json")]))
    bad.unlink()

    disk_full_rows(work, run_dir)

    two = work / "two"
    shutil.rmtree(two, ignore_errors=True)
    first = subprocess.Popen([BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "400", "--vis", "none",
                              "--progress", "none", "--output-dir", str(two)], stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=ENV)
    while not (two / "config.yml").is_file():
        time.sleep(0.5)
    row("second hico-train on the same output dir", run([BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "4",
                                                         "--vis", "none", "--progress", "none", "--output-dir", str(two)]))
    first.send_signal(signal.SIGINT)
    first.wait(timeout=600)

    for label, params, size in (("camera focal 0", [0.0, 0.0, 20.0, 15.0], (40, 30)), ("camera focal -50", [-50.0, -50.0, 20.0, 15.0], (40, 30)),
                                ("principal point far outside", [32.0, 32.0, 900.0, 15.0], (40, 30)), ("1x1-pixel images", None, (1, 1))):
        data = work / f"cam_{label.replace(' ', '_')}"
        shutil.rmtree(data, ignore_errors=True)
        write_ring_dataset(data, params=params, size=size)
        row(f"{label}, hico-train", run([BIN / "hico-train", "hico-gs-lite", "--data", str(data), "--max-steps", "4", "--vis", "none",
                                         "--progress", "none", "--output-dir", str(work / "r_cam")]))

    data = work / "trunc_test"
    shutil.rmtree(data, ignore_errors=True)
    written = write_ring_dataset(data, num_images=9)
    test_image = data / "images" / written["names"][0]  # index 0: a test view (--test-every 8)
    test_image.write_bytes(test_image.read_bytes()[:-200])
    out = work / "r_trunc"
    shutil.rmtree(out, ignore_errors=True)
    result = run([BIN / "hico-train", "hico-gs-lite", "--data", str(data), "--max-steps", "4", "--vis", "none",
                  "--progress", "none", "--output-dir", str(out)])
    kept = sorted(p.name for p in (out / "checkpoints").iterdir()) if (out / "checkpoints").is_dir() else []
    row("truncated test image, hico-train", result, f"; checkpoints kept: {kept}")
    row("truncated image, hico-inspect", run([BIN / "hico-inspect", str(data)]))
    data2 = work / "size_mismatch"
    shutil.rmtree(data2, ignore_errors=True)
    names = write_ring_dataset(data2)["names"]
    import cv2
    import numpy as np
    cv2.imwrite(str(data2 / "images" / names[2]), np.zeros((30, 43, 3), np.uint8))
    row("image size disagrees with camera, hico-inspect", run([BIN / "hico-inspect", str(data2)]))


def disk_full_rows(work: Path, run_dir: Path) -> None:
    """Training into a tmpfs with room for the first checkpoint but not the second (disk full), and
    into a read-only mount. Mounting needs root, and root ignores a chmod 555 directory, so a
    non-root user gets the read-only case as a chmod 555 directory and no disk-full row."""
    files = [f for f in run_dir.rglob("*") if f.is_file()]
    checkpoint = max(f.stat().st_size for f in files if f.suffix == ".ckpt")
    others = sum(f.stat().st_size for f in files if f.suffix != ".ckpt")
    train = [BIN / "hico-train", "hico-gs-lite", "--scene", "tiny", "--max-steps", "4", "--save-every", "2",
             "--vis", "none", "--progress", "none", "--output-dir"]
    for label, options in ((f"output disk full while saving (tmpfs of {(others + 1.5 * checkpoint) / 1024:.0f} kB)",
                            f"size={int(others + 1.5 * checkpoint) // 1024 + 1}k"), ("read-only output (ro mount)", "ro")):
        mount = work / f"mnt_{options[:4]}"
        mount.mkdir(exist_ok=True)
        if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mount)], check=False).returncode:
            if "ro" != options:
                continue
            mount.chmod(0o555)
            label = "read-only output (chmod 555 directory)"
        try:
            result = run(train + [str(mount / "run")])
            ckpts = sorted(p.name for p in (mount / "run" / "checkpoints").iterdir()) if (mount / "run" / "checkpoints").is_dir() else []
            row(f"{label}, hico-train", result, f"; checkpoints kept: {ckpts}")
        finally:
            subprocess.run(["umount", str(mount)], capture_output=True, check=False)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="hico_table_")))
