"""What `vmocap bench faults` builds its faults from: real MCAP bags (synthetic subject, benchmark
rig), altered copies of them, graph configs, the launcher and players as processes, and the
graph's own recording (outputs and /diagnostics) read back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
MOTION = REPO / "vmocap_core" / "data" / "motions" / "walk.npz"
FPS = 30.0
T0 = 1_000_000_000_000  # the synthetic bags' first stamp (ns)
# the harness's bags, configs and recordings live in its own work folder: a --workdir used
# again replaces them (BagWriter's and the recorder's `overwrite`)
SCRATCH = True


def stamp_of(k: int) -> int:
    return T0 + int(round(k * 1e9 / FPS))


def synthetic_bag(path: Path, frames: int, images: bool, size: tuple[int, int] = (320, 240)):
    """A bag of `frames` frame sets (4 cameras, PCM topics, images optional) and its rig."""
    from vmocap_core.bag.synth import write_synthetic_bag
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.keypoints import KEYPOINTS
    from vmocap_core.motion import load_motion, resample
    from vmocap_core.pcm.synthetic import benchmark_rig

    rig = benchmark_rig(width=size[0], height=size[1])
    m = resample(load_motion(MOTION), FPS)
    if not path.exists():
        write_synthetic_bag(path, rig, m.positions, m.present, frames, fps=FPS, images=images)
    rig_path = path.with_suffix(".rig.yaml")
    save_rig(rig, rig_path)
    return rig, rig_path, [KEYPOINTS[i] for i in np.flatnonzero(m.present)]


def alter_heatmaps(src: Path, dst: Path, frames: range, views: list[str], how: str, keypoints: int) -> Path:
    """A copy of `src` whose heatmaps of `views` in `frames` are NaN, +Inf, negative, or say
    "nobody here" (`absent`: every keypoint channel NaN, presence 0). The maps hold `keypoints`
    channels, then presence, then (BlazePose) the visibility plane (bag/messages.py)."""
    from vmocap_core.bag import BagReader, BagWriter, cdr

    J = keypoints

    lo, hi = stamp_of(frames.start), stamp_of(frames.stop)
    with BagReader(src) as r, BagWriter(dst, overwrite=SCRATCH) as w:
        for m in r.messages():
            data: bytes | dict = bytes(m.data)
            view = m.topic.split("/")[-2] if "/pcm/" in m.topic else ""
            if m.topic.endswith("/heatmaps") and view in views and lo <= m.log_time_ns < hi:
                msg = cdr.decode(m.type, data)
                ch = int(msg["encoding"][4:])
                if ch not in (J + 1, J + 2):
                    raise ValueError(f"{m.topic}: {msg['encoding']}, not {J} keypoints + presence (+ visibility)")
                a = np.frombuffer(bytes(msg["data"]), np.float32).reshape(msg["height"], msg["width"], ch).copy()
                if how == "absent":
                    a[..., :J], a[..., J] = np.nan, 0.0
                else:
                    a[..., :J] = {"nan": np.nan, "inf": np.inf, "negative": -1.0}[how]
                msg["data"] = a.tobytes()
                data = cdr.encode(m.type, msg)
            w.write(m.topic, m.type, data, m.log_time_ns)
    return dst


def delay_view(src: Path, dst: Path, view: str, frames: int) -> Path:
    """A copy of `src` in which `view`'s heatmaps and their camera_info are those of `frames`
    frame sets earlier under the later stamps (a camera whose images lag the others); its
    first `frames` frame sets are left out."""
    from collections import deque

    from vmocap_core.bag import BagReader, BagWriter, cdr

    held: dict[str, deque] = {}
    with BagReader(src) as r, BagWriter(dst, overwrite=SCRATCH) as w:
        for m in r.messages():
            data: bytes = bytes(m.data)
            if f"/pcm/{view}/" in m.topic:
                queue = held.setdefault(m.topic, deque())
                now = cdr.decode(m.type, data)
                queue.append(now)
                if len(queue) <= frames:
                    continue
                msg = dict(queue.popleft(), header=now["header"])  # the stamp of the frame set it goes out with
                data = cdr.encode(m.type, msg)
            w.write(m.topic, m.type, data, m.log_time_ns)
    return dst


def miscalibrated(rig_path: Path, out: Path, camera: str, how: str) -> Path:
    """The rig with one camera turned by 5 degrees about its vertical axis (`rotated`) or its
    centre moved by 10 cm along world x (`moved`), the others as they were."""
    import dataclasses

    from vmocap_core.cameras.rig_file import load_rig, save_rig

    rig = load_rig(rig_path)
    cams = []
    for cam in rig:
        if cam.name == camera:
            if how == "rotated":
                a = np.deg2rad(5.0)
                turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
                cam = dataclasses.replace(cam, R=turn @ cam.R, t=turn @ cam.t)
            else:  # centre C = -R^T t moved by d: t' = t - R d
                cam = dataclasses.replace(cam, t=cam.t - cam.R @ np.array([0.1, 0.0, 0.0]))
        cams.append(cam)
    save_rig(type(rig)(cams), out)
    return out


def damage(src: Path, dst: Path, how: str, at: float = 0.6, seed: int = 0) -> Path:
    """A truncated copy (the first `at` of the bytes) or a corrupted one (64 KiB of random bytes
    written at `at` of the file; footer and summary intact)."""
    raw = bytearray(src.read_bytes())
    cut = int(len(raw) * at)
    if how == "truncated":
        raw = raw[:cut]
    else:
        raw[cut:cut + 65536] = np.random.default_rng(seed).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    dst.write_bytes(bytes(raw))
    return dst


def damage_chunk(src: Path, dst: Path) -> tuple[int, int, int]:
    """A copy of `src` with 8 bytes inverted inside the records of its middle chunk (summary and
    the other chunks intact); returns that chunk's index and its first and last message time."""
    from vmocap_core.bag import BagReader

    with BagReader(src) as r:
        chunks = r._summary.chunk_indexes
        k = len(chunks) // 2
        ci = chunks[k]
    raw = bytearray(src.read_bytes())
    pos = ci.chunk_start_offset + ci.chunk_length - 64  # inside the chunk's records
    raw[pos:pos + 8] = bytes(b ^ 0xFF for b in raw[pos:pos + 8])
    dst.write_bytes(bytes(raw))
    return k, ci.message_start_time, ci.message_end_time


def frame_stamps(path: Path, recover: bool = False) -> set[int]:
    """The log times of the heatmaps in a bag: its frame sets."""
    from vmocap_core.bag import BagReader

    with BagReader(path, recover=recover) as r:
        return {m.log_time_ns for m in r.messages() if m.topic.endswith("/heatmaps")}


def launch_mode(mode: str) -> str:
    """The vmocap_launch mode of a benchmark mode ("default": the shipped process groups)."""
    return "processes" if mode == "default" else mode


def write_config(path: Path, rig_path: Path, kps: list[str], nodes: list[str], mode: str, output: Path,
                 groups: list[list[str]] | None = None, extra: dict | None = None, launch: dict | None = None) -> Path:
    cfg = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    cfg["/**"]["ros__parameters"].update(rig=str(rig_path), pcm_keypoints=kps)
    cfg["vmocap_pcm"]["ros__parameters"]["model"] = str(MOTION)
    cfg["vmocap_recorder"]["ros__parameters"].update(output=str(output), overwrite=SCRATCH)
    cfg["vmocap_launch"] = {"mode": mode, "nodes": nodes, "groups": groups or [],
                            "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml"), **(launch or {})}
    # the synthetic heatmaps' noise (6 px, false peaks, swaps) is harsher than the CNN's: a wider
    # skeleton-fit bound lets the subject initialize on these bags (as test/test_graph_hosts.py)
    cfg["vmocap_skeleton"]["ros__parameters"]["init_max_fit_error_m"] = 0.08
    for section, params in (extra or {}).items():
        cfg.setdefault(section, {"ros__parameters": {}})["ros__parameters"].update(params)
    path.write_text(yaml.safe_dump(cfg))
    return path


def vmocap_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "vmocap_core.cli", *args]


@dataclass
class Proc:
    """A child process whose output is collected by a thread (no pipe can fill up)."""

    popen: subprocess.Popen
    lines: list[str] = field(default_factory=list)

    @classmethod
    def start(cls, cmd: list[str], env: dict[str, str]) -> "Proc":
        p = cls(subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        threading.Thread(target=lambda: p.lines.extend(p.popen.stdout), daemon=True).start()  # type: ignore[arg-type]
        return p

    @property
    def text(self) -> str:
        return "".join(self.lines)

    def pids(self) -> dict[str, int]:
        """The launcher's children (processes mode): `vmocap launch: N processes: a+b[pid], ...`."""
        out: dict[str, int] = {}
        for line in self.lines:
            if line.startswith("vmocap launch:") and "processes:" in line:
                items = line.rsplit("processes: ", 1)[1].split(", ")
                out = {i.split("[")[0]: int(i.split("[")[1].rstrip("]\n")) for i in items}
            elif line.startswith("vmocap launch:") and "; restarted as " in line:  # restart policy
                item = line.split("; restarted as ", 1)[1].split(" ", 1)[0]
                out[item.split("[")[0]] = int(item.split("[")[1].rstrip("]"))
        return out

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait()
            raise RuntimeError(f"{self.popen.args[3:5]} did not stop on signal {sig}:\n{self.text[-2000:]}") from None


def wait_for(pred, timeout: float, step: float = 0.1) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


def wait_ready(launch: Proc, nodes: list[str], timeout: float = 90.0) -> None:
    def ready() -> bool:
        text = " ".join(line for line in launch.lines if line.startswith("READY"))
        return all(n in text for n in nodes)

    if not wait_for(lambda: ready() or launch.popen.poll() is not None, timeout) or not ready():
        raise RuntimeError(f"the graph did not start:\n{launch.text[-3000:]}")


@dataclass
class Outputs:
    """The graph's recording read back: joint_states (receive time, stamp) and per node the
    diagnostics (receive time, level, message, values)."""

    joint_states: list[tuple[int, int]]
    diag: dict[str, list[tuple[int, int, str, dict[str, str]]]]
    closed: bool  # footer written: the bag opens without recovery

    @classmethod
    def read(cls, path: Path, recover: bool = False) -> "Outputs":
        from vmocap_core.bag import BagReader
        from vmocap_core.bag import messages as M
        from vmocap_core.errors import VmocapError

        if path.stat().st_size < 8:  # killed before anything reached the disk
            return cls([], {}, False)
        closed = True
        try:
            BagReader(path).open().close()
        except VmocapError:
            closed = False
        js, diag = [], {}
        with BagReader(path, recover=recover or not closed) as r:
            for m in r.messages():
                if m.topic.endswith("/joint_states"):
                    js.append((m.log_time_ns, M.stamp_ns(m.decode())))
                elif m.topic == "/diagnostics":
                    for s in m.decode()["status"]:
                        lvl = s["level"][0] if isinstance(s["level"], (bytes, bytearray)) else int(s["level"])
                        diag.setdefault(s["name"], []).append(
                            (m.log_time_ns, lvl, s["message"], {v["key"]: v["value"] for v in s["values"]}))
        return cls(js, diag, closed)

    def warned(self, node: str, text: str = "") -> bool:
        return any(lvl >= 1 and text in msg for _, lvl, msg, _ in self.diag.get(node, []))


def env_for(domain: int) -> dict[str, str]:
    from ..common import prepare_env

    env = dict(os.environ)
    prepare_env(env)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    return env


# ------------------------------------------------------------------ camera images (the CNN path)
DEMO_FPS = 60.0  # the Pose2Sim demo's videos; frame f has stamp f / 60 s


def demo_bag(path: Path, frames: int):
    """The first `frames` frame sets of the Pose2Sim demo's 4 videos (a real person, 1080x1920
    portrait, JPEG CompressedImage as `vmocap demo` writes them) and its rig; None when the
    pose2sim wheel is not cached (models/pose2sim or ~/.cache/vmocap/pose2sim: `make demo`)."""
    from vmocap_core.apps.demo.data import video_paths, video_sizes, videos_to_bag
    from vmocap_core.calibration.datasets import pose2sim_demo
    from vmocap_core.calibration.reference import load_qualisys
    from vmocap_core.cameras.rig_file import save_rig

    demo = pose2sim_demo(fetch=False)
    if demo is None:
        return None
    videos = video_paths(demo)
    rig = load_qualisys(demo / "calibration" / "Calib.qca.txt", video_sizes(videos))
    rig_path = path.with_suffix(".rig.yaml")
    save_rig(rig, rig_path)
    if not path.exists():
        videos_to_bag(videos, rig, path, frames, overwrite=SCRATCH)  # a .partial a killed run left
    return rig, rig_path


def alter_images(src: Path, dst: Path, camera: str, frames: range, how: str) -> Path:
    """A copy of `src` whose JPEG images of `camera` in `frames` are all black, all white, or
    the same picture at half the width and height (`half`: a camera delivering another size
    than the rig was calibrated at)."""
    import cv2

    from vmocap_core.bag import BagReader, BagWriter, cdr

    with BagReader(src) as r, BagWriter(dst, overwrite=SCRATCH) as w:
        for m in r.messages():
            data: bytes = bytes(m.data)
            k = round(m.log_time_ns * DEMO_FPS / 1e9)
            if m.topic.endswith("/compressed") and m.topic.split("/")[-3] == camera and k in frames:
                msg = cdr.decode(m.type, data)
                img = cv2.imdecode(np.frombuffer(bytes(msg["data"]), np.uint8), cv2.IMREAD_COLOR)
                if how == "half":
                    img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
                else:
                    img = np.full_like(img, {"black": 0, "white": 255}[how])
                msg["data"] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
                data = cdr.encode(m.type, msg)
            w.write(m.topic, m.type, data, m.log_time_ns)
    return dst


# ------------------------------------------------------------------ an Aravis camera unplugged
def aravis_camera_run(config: Path, camera: str, after_s: float, away_s: float, total_s: float) -> dict:
    """vmocap_camera (the real node, in this process) on Aravis' in-process Fake cameras (the
    only interface enabled: no GigE/USB3 discovery); after `after_s` one camera is unplugged
    (Aravis' 'control-lost' signal, and the Fake interface disabled so that reopening fails
    as for an absent device) for `away_s`, then plugged in again (interface enabled). A probe
    node here receives every camera_info (one per frame) and /diagnostics over DDS. (A stream
    that stops while connected cannot be made so: the Fake camera ignores AcquisitionStop.)"""
    from vmocap_core import graph_config
    from vmocap_core.cameras import aravis as arv
    from vmocap_core.outputs.messages import DIAG, INFO

    from ..common import Topics, init_rclpy, msg_class, qos
    from ..nodes.camera import CameraNode

    Ar = arv.setup_interfaces(("Fake",))  # before any device list update; open() keeps this setting
    rclpy = init_rclpy()
    node = CameraNode(graph_config.load(config))
    probe = rclpy.create_node("vmocap_fault_probe")
    frames: list[tuple[int, str, int]] = []  # (receive ns, camera, stamp ns)
    diags: list[tuple[int, int, str, dict[str, str]]] = []
    for name in node.rig.names:
        probe.create_subscription(msg_class(INFO), Topics(node.p["namespace"]).camera_info(name),
                                  lambda m, n=name: frames.append((time.time_ns(), n, m.header.stamp.sec * 10**9
                                                                   + m.header.stamp.nanosec)), qos(100))

    def on_diag(m) -> None:
        for s in m.status:
            if s.name == "vmocap_camera":
                lvl = s.level[0] if isinstance(s.level, (bytes, bytearray)) else int(s.level)
                diags.append((time.time_ns(), lvl, s.message, {v.key: v.value for v in s.values}))

    probe.create_subscription(msg_class(DIAG), "/diagnostics", on_diag, qos(50))
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(probe)
    sources = {src.name: src for _, src in node._threads}
    t0 = time.monotonic()
    marks: dict[str, int] = {}
    try:
        while time.monotonic() - t0 < total_s:
            ex.spin_once(timeout_sec=0.05)
            now = time.monotonic() - t0
            if "unplug" not in marks and now >= after_s:
                Ar.disable_interface("Fake")
                sources[camera]._cam.get_device().emit("control-lost")  # what Aravis signals when a camera drops
                marks["unplug"] = time.time_ns()
            if "plug" not in marks and now >= after_s + away_s:
                Ar.enable_interface("Fake")
                marks["plug"] = time.time_ns()
    finally:
        node.close()
        ex.shutdown()
        probe.destroy_node()
        node.destroy_node()
        rclpy.shutdown()
    return {"frames": frames, "diags": diags, "marks": marks, "cameras": list(sources)}


def main(argv: list[str] | None = None) -> int:
    """`python -m vmocap_ros.bench.fault_harness aravis CONFIG CAMERA AFTER AWAY TOTAL`: the run above,
    its record as JSON on stdout (one line)."""
    import json

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 6 or args[0] != "aravis":
        print(main.__doc__, file=sys.stderr)
        return 2
    out = aravis_camera_run(Path(args[1]), args[2], float(args[3]), float(args[4]), float(args[5]))
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
