"""Helpers of the graph tests: synthetic PCM bags, configs, processes on a private ROS domain."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
MOTION = REPO / "vmocap_core" / "data" / "motions" / "walk.npz"


def domain_env(offset: int = 0) -> dict[str, str]:
    """A ROS domain of this test process only (isolation from other test runs)."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(1 + (os.getpid() + offset) % 100)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def synthetic_bag(path: Path, frames: int = 30, fps: float = 30.0, images: bool = False, size=(1024, 768), noise=None):
    from vmocap_core.bag.synth import write_synthetic_bag
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.keypoints import KEYPOINTS
    from vmocap_core.motion import load_motion, resample
    from vmocap_core.pcm.synthetic import benchmark_rig

    rig = benchmark_rig(width=size[0], height=size[1])
    m = resample(load_motion(MOTION), fps)
    write_synthetic_bag(path, rig, m.positions, m.present, frames, fps=fps, images=images, noise=noise)
    rig_path = path.with_suffix(".rig.yaml")
    save_rig(rig, rig_path)
    return rig, rig_path, [KEYPOINTS[i] for i in np.flatnonzero(m.present)]


def write_config(path: Path, rig_path: Path, keypoints: list[str], nodes: list[str], mode: str = "processes",
                 output: Path | None = None, extra: dict | None = None) -> Path:
    cfg = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    cfg["/**"]["ros__parameters"]["rig"] = str(rig_path)
    cfg["/**"]["ros__parameters"]["pcm_keypoints"] = keypoints
    cfg["vmocap_pcm"]["ros__parameters"]["model"] = str(MOTION)
    if output is not None:
        cfg["vmocap_recorder"]["ros__parameters"]["output"] = str(output)
    cfg["vmocap_launch"] = {"mode": mode, "nodes": nodes, "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml")}
    for section, params in (extra or {}).items():
        cfg.setdefault(section, {"ros__parameters": {}})["ros__parameters"].update(params)
    path.write_text(yaml.safe_dump(cfg))
    return path


def vmocap(args: list[str], env: dict[str, str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vmocap_core.cli", *args], env=env, cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def wait_ready(proc: subprocess.Popen, nodes: list[str], timeout: float = 60.0) -> bool:
    """Read the launcher's output (in a thread, kept for `stop`) until every node printed READY."""
    import threading

    if not hasattr(proc, "_lines"):
        proc._lines = []  # type: ignore[attr-defined]

        def pump() -> None:
            for line in proc.stdout:  # type: ignore[union-attr]
                proc._lines.append(line)  # type: ignore[attr-defined]

        proc._reader = threading.Thread(target=pump, daemon=True)  # type: ignore[attr-defined]
        proc._reader.start()  # type: ignore[attr-defined]

    def ready() -> bool:
        text = "".join(proc._lines)  # type: ignore[attr-defined]
        return all(n in " ".join(l for l in text.splitlines() if l.startswith("READY")) for n in nodes)

    return wait_for(lambda: ready() or proc.poll() is not None, timeout) and ready()


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 20.0) -> str:
    if proc.poll() is None:
        proc.send_signal(sig)
    if hasattr(proc, "_reader"):
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError(f"process did not stop on signal {sig}:\n{''.join(proc._lines)}") from None
        proc._reader.join(timeout=5)
        return "".join(proc._lines)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"process did not stop on signal {sig}:\n{out}") from None
    return out


def wait_for(predicate, timeout: float, step: float = 0.1) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def without_frames(src: Path, dst: Path, frames, fps: float, t0: int = 1_000_000_000_000) -> Path:
    """A copy of the bag `src` without the frame sets numbered `frames` (frame k at t0 + k / fps):
    a recording with a gap."""
    from vmocap_core.bag import BagReader, BagWriter

    with BagReader(src) as r, BagWriter(dst) as w:
        for m in r.messages():
            if round((m.log_time_ns - t0) * fps / 1e9) not in frames:
                w.write(m.topic, m.type, m.data, m.log_time_ns)
    return dst
