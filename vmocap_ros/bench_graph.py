"""`vmocap bench graph [--json]`: rate, drops and latency of the node graph.

A synthetic bag (4 cameras, 1024x768 bgr8, 30 Hz; benchmark rig, walk clip) is played in a
loop, by the graph's own vmocap_camera node (`--feed camera`, default: capture stamp = the
moment the frame set is due) or by `vmocap play --restamp` in its own process (`--feed
player`), through vmocap_pcm -> vmocap_markers -> vmocap_skeleton, in each launch mode: `default`
(the shipped config's process groups: camera, CNN and tracker share a process, images never
cross a process boundary), `processes` (each node its own process) and `single_process`.
A probe node in this process receives joint_states (end-to-end latency, as a controller sees
it) and keypoints (frame sets out, also while not tracking); the age after each stage comes
from the nodes' own /diagnostics (capture stamp -> end of the node's processing, last 300
frame sets): the camera node (or, with the player, cam0/camera_info at the probe:
"transport"), vmocap_pcm, vmocap_markers, vmocap_skeleton. The probe subscribes to nothing
else, because our nodes encode and send a topic over DDS only when a DDS reader matched: a
probe on the heatmaps would add their encoding to what it measures.
Reported: the output rate, the frame sets that never came out (dropped %: gaps in the
evenly spaced output stamps with the camera feed, player frame sets missing at the output
with the player), and the CPU per node (callback CPU time from the nodes' diagnostics, % of
one core) and per process.
PCM: `--pcm bag` (default) hands out heatmaps recorded in the bag (no CNN cost), `synthetic`
renders them per frame set, `model` runs the CNN (vmocap_core.pcm) when it is available.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parent.parent
NODES = ["vmocap_pcm", "vmocap_markers", "vmocap_skeleton"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--seconds", type=float, default=8.0, help="measured seconds per mode")
    parser.add_argument("--warmup", type=float, default=2.0, help="seconds ignored at the start of each mode")
    parser.add_argument("--frames", type=int, default=15, help="frame sets in the looped bag")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--size", default="1024x768", help="image size WxH")
    parser.add_argument("--pcm", default="bag", choices=("bag", "synthetic", "model"))
    parser.add_argument("--images", default="synthetic", choices=("synthetic", "pose2sim"),
                        help="synthetic: random texture (no person; use with --pcm bag/synthetic); pose2sim: the "
                             "Pose2Sim demo videos (a real person, 4 calibrated cameras) resized to --size (with --pcm model)")
    parser.add_argument("--model", default="", help="PCM model for --pcm model")
    parser.add_argument("--feed", default="camera", choices=("camera", "player"),
                        help="camera: the graph's own vmocap_camera node plays the bag (looped, restamped: capture "
                             "stamp = the moment the frame set is due), in the graph's process in single_process mode; "
                             "player: a separate `vmocap play --restamp` process publishes the images over DDS")
    parser.add_argument("--modes", nargs="+", default=["default", "processes", "single_process"],
                        choices=("default", "processes", "single_process"))
    parser.add_argument("--scaling", action="store_true",
                        help="also the default mode on 1 and 2 cores (taskset) with 2, 4 and 6 cameras (--images pose2sim: "
                             "cameras beyond the 4 videos repeat them), to size a machine")
    parser.add_argument("--workdir", default=None, help="where the bag and configs go (default: a temp dir)")


def _bag(work: Path, args: argparse.Namespace):
    from vmocap_core.bag.synth import write_synthetic_bag
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.keypoints import KEYPOINTS
    from vmocap_core.motion import load_motion, resample
    from vmocap_core.pcm.synthetic import benchmark_rig

    w, h = (int(x) for x in args.size.split("x"))
    rig = benchmark_rig(width=w, height=h)
    rig = rig.subset(rig.names[: args.cameras]) if args.cameras < len(rig) else rig
    motion_path = REPO / "vmocap_core" / "data" / "motions" / "walk.npz"
    m = resample(load_motion(motion_path), args.fps)
    bag = work / f"bench_{args.cameras}x{w}x{h}_{args.frames}.mcap"
    if not bag.exists():
        write_synthetic_bag(bag, rig, m.positions, m.present, args.frames, fps=args.fps, images=True, pcm=True)
    rig_path = work / "rig.yaml"
    save_rig(rig, rig_path)
    return rig, bag, rig_path, [KEYPOINTS[i] for i in np.flatnonzero(m.present)], motion_path


def _pose2sim_bag(work: Path, args: argparse.Namespace):
    """The first --frames frame sets of the Pose2Sim demo (real person), resized to --size
    (intrinsics scaled to match), stamps at --fps."""
    import cv2

    from vmocap_core.apps.demo.data import load_qualisys_rig, video_paths, video_sizes
    from vmocap_core.bag import BagWriter
    from vmocap_core.bag import messages as M
    from vmocap_core.calibration.datasets import pose2sim_demo
    from vmocap_core.cameras.projection import Camera, Rig
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.graph_config import Topics

    demo = pose2sim_demo(fetch=True)
    videos = video_paths(demo)
    full = load_qualisys_rig(demo / "calibration" / "Calib.qca.txt", video_sizes(videos))
    w, h = (int(x) for x in args.size.split("x"))
    cams = []
    for c in full:
        # keep the aspect: fit into w x h (portrait videos give a portrait image)
        s = min(w, h) / min(c.width, c.height)
        W, H = int(round(c.width * s)), int(round(c.height * s))
        sx, sy = W / c.width, H / c.height
        S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])  # pixel centres at integers
        cams.append(Camera(c.name, S @ c.K, c.dist, c.R, c.t, W, H))
    # more cameras than videos: the videos again under new names (the same views: the cost of
    # more cameras, not their geometry)
    extra = [dataclasses.replace(cams[k % len(cams)], name=f"cam{k + 1:02d}") for k in range(len(cams), args.cameras)]
    rig = Rig((cams + extra)[: args.cameras])
    source = {c.name: (cams + extra)[k % len(cams)].name for k, c in enumerate(rig)}
    bag = work / f"pose2sim_{args.cameras}x{args.size}_{args.frames}.mcap"
    if not bag.exists():
        topics = Topics()
        caps = {c.name: cv2.VideoCapture(str(videos[source[c.name]])) for c in rig}
        with BagWriter(bag) as wr:
            for k in range(args.frames):
                t = 1_000_000_000_000 + int(round(k * 1e9 / args.fps))
                for c in rig:
                    ok, img = caps[c.name].read()
                    if not ok:
                        raise RuntimeError(f"{videos[source[c.name]]}: fewer than {args.frames} frames")
                    img = cv2.resize(img, (c.width, c.height), interpolation=cv2.INTER_AREA)
                    wr.write(topics.image(c.name), "sensor_msgs/msg/Image", M.image_msg(img, t, c.name), t)
                    wr.write(topics.camera_info(c.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(c, t), t)
        for cap in caps.values():
            cap.release()
    rig_path = work / "rig_pose2sim.yaml"
    save_rig(rig, rig_path)
    return rig, bag, rig_path, [], None


def _config(work: Path, mode: str, rig_path: Path, kps: list[str], args: argparse.Namespace, bag: Path, motion: Path) -> Path:
    cfg = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    common = cfg["/**"]["ros__parameters"]
    common.update(rig=str(rig_path), pcm_keypoints=kps)
    pcm = cfg["vmocap_pcm"]["ros__parameters"]
    if args.pcm == "bag":
        pcm.update(source="model", model=str(bag))
    elif args.pcm == "synthetic":
        pcm.update(source="synthetic", model=str(motion))
    else:
        pcm.update(source="model", model=args.model or "blazepose")
        common["pcm_keypoints"] = [""]  # the CNN's channels are all 25 KEYPOINTS
    common["fps"] = float(args.fps)
    nodes = list(NODES)
    if args.feed == "camera":
        nodes.insert(0, "vmocap_camera")
        cfg["vmocap_camera"]["ros__parameters"].update(source="bag", uri=str(bag), rate=1.0, loop=True, restamp=True)
    shipped = cfg.get("vmocap_launch") or {}
    cfg["vmocap_launch"] = {"mode": "processes" if mode == "default" else mode, "nodes": nodes,
                            "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml")}
    if mode == "default":
        cfg["vmocap_launch"]["groups"] = shipped.get("groups") or []
    path = work / f"graph_{mode}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


class Probe:
    """Records (receive wall time, capture stamp) of the graph's outputs and the nodes'
    /diagnostics. A measurement must not change what it measures: a node encodes and sends a
    topic over DDS only when a DDS reader matched, so the probe subscribes to the small
    outputs a controller takes (joint_states, keypoints) and, with the player feed, to the
    player's camera_info (the player pays for that); per-stage ages come from the nodes' own
    diagnostics (each node's `age`: capture stamp -> end of its processing)."""

    def __init__(self, rclpy, cameras: list[str], input_topic: bool) -> None:
        from vmocap_core.bag import cdr

        from .common import Topics, msg_class, qos

        self.rclpy = rclpy
        self.node = rclpy.create_node("vmocap_bench_probe")
        t = Topics("/vmocap")
        self.samples: dict[str, list[tuple[int, int]]] = {k: [] for k in ("transport", "joint_states", "keypoints")}
        self.diag: dict[str, list[tuple[int, dict[str, str]]]] = {}  # node -> (monotonic ns, values)
        self.recording = False
        self.min_stamp = 0  # ignore outputs of frames captured before the current mode started

        def stamp_of(data: bytes) -> int:
            import struct

            sec, nsec = struct.unpack_from("<iI", data, 4)
            return sec * 1_000_000_000 + nsec

        def sub(kind: str, ty: str, topic: str, latched: bool = False) -> None:
            def cb(data: bytes) -> None:
                if self.recording:
                    st = stamp_of(data)
                    if st >= self.min_stamp:
                        self.samples[kind].append((time.time_ns(), st))

            self.node.create_subscription(msg_class(ty), topic, cb, qos(50, latched=latched), raw=True)

        if input_topic:
            sub("transport", "sensor_msgs/msg/CameraInfo", t.camera_info(cameras[0]))
        sub("joint_states", "sensor_msgs/msg/JointState", t.joint_states)
        sub("keypoints", "sensor_msgs/msg/PointCloud2", t.keypoints)

        def on_diag(data: bytes) -> None:
            d = cdr.decode("diagnostic_msgs/msg/DiagnosticArray", data)
            for s in d["status"]:
                vals = {v["key"]: v["value"] for v in s["values"]}
                if "cpu_s" in vals:
                    self.diag.setdefault(s["name"], []).append((time.monotonic_ns(), vals))

        self.node.create_subscription(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", on_diag, qos(50), raw=True)
        from .run_node import make_executor

        self.executor = make_executor()  # the probe shares the CPU with the graph: keep it cheap
        self.executor.add_node(self.node)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)

    def clear(self, all_: bool = False) -> None:
        for v in self.samples.values():
            v.clear()
        if all_:
            self.diag.clear()

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown()
        self.node.destroy_node()


def _lat(samples: list[tuple[int, int]]) -> dict[str, float]:
    if not samples:
        return {"p50": float("nan"), "p95": float("nan"), "n": 0}
    a = np.array([(r - s) / 1e6 for r, s in samples])
    return {"p50": round(float(np.percentile(a, 50)), 2), "p95": round(float(np.percentile(a, 95)), 2), "n": int(a.size)}


def _in_window(diag: list[tuple[int, dict[str, str]]], t0: int, t1: int) -> list[dict[str, str]]:
    return [v for t, v in diag if t0 <= t <= t1]


def _cpu(diag: list[tuple[int, dict[str, str]]], t0: int, t1: int) -> float:
    pts = [(t, float(v["cpu_s"])) for t, v in diag if t0 <= t <= t1]
    if len(pts) < 2:
        return float("nan")
    (ta, ca), (tb, cb) = pts[0], pts[-1]
    return round(100.0 * (cb - ca) / ((tb - ta) / 1e9), 1)


def _node_age(vals: dict[str, str] | None) -> dict[str, float]:
    """A node's own latency figure (capture stamp -> end of its processing, over its last
    300 frame sets) from its diagnostics."""
    if not vals or "age_ms_p50" not in vals:
        return {"p50": float("nan"), "p95": float("nan"), "n": 0}
    return {"p50": round(float(vals["age_ms_p50"]), 2), "p95": round(float(vals["age_ms_p95"]), 2), "n": int(vals["age_ms_n"])}


def _missing_periods(stamps: list[int], period_ns: float) -> int:
    """Frame sets missing between the first and the last of evenly spaced stamps (the camera
    node stamps the frame set due at epoch + k periods)."""
    s = np.unique(np.asarray(stamps, dtype=np.int64))
    if s.size < 2:
        return 0
    return int(np.maximum(np.rint(np.diff(s) / period_ns) - 1, 0).sum())


def _proc_cpu_s(pid: int) -> float:
    """utime + stime of a process (seconds), 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def run_mode(mode: str, cfg: Path, bag: Path, rig, args: argparse.Namespace, probe: Probe, env: dict[str, str],
             cores: str | None = None) -> dict:
    pin = ["taskset", "-c", cores] if cores else []  # the children inherit the affinity
    launch = subprocess.Popen([*pin, sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # process ids: the launcher prints its children first (processes mode); single process: itself
    pids = {"launcher (all nodes)" if mode == "single_process" else "launcher": launch.pid}
    if mode != "single_process":
        line = launch.stdout.readline()
        for item in line.rsplit(": ", 1)[-1].split(","):
            name, _, pid = item.strip().rstrip("]").partition("[")
            if pid.isdigit():
                pids[name] = int(pid)
    topics = [t for c in rig.names for t in (f"/vmocap/{c}/image_raw", f"/vmocap/{c}/camera_info")]
    if args.feed == "player":
        player = subprocess.Popen(
            [sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--loop", "--restamp", "--no-clock", "--quiet",
             "--wait-subscribers", "60", "--expect", *[f"/vmocap/{c}/image_raw" for c in rig.names], "--topics", *topics],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    else:  # the graph's camera node plays the bag
        player = None
    try:
        # wait for the graph's first output, then warm up, then measure
        probe.clear(all_=True)
        probe.min_stamp = time.time_ns()
        probe.recording = True
        deadline = time.monotonic() + 90
        while not (probe.samples["keypoints"] and (probe.samples["transport"] or player is None)) and time.monotonic() < deadline:
            probe.spin_for(0.2)
            if launch.poll() is not None or (player is not None and player.poll() is not None):
                raise RuntimeError("graph or player exited early:\n" + (launch.communicate()[0] if launch.poll() is not None else player.communicate()[0]))
        probe.spin_for(args.warmup)
        probe.clear()
        t0 = time.monotonic_ns()
        cpu0 = {n: _proc_cpu_s(p) for n, p in pids.items()}
        if args.feed == "player":
            cpu0["player"] = _proc_cpu_s(player.pid)
        probe.spin_for(args.seconds)
        t1 = time.monotonic_ns()
        cpu1 = {n: _proc_cpu_s(p) for n, p in pids.items()}
        if args.feed == "player":
            cpu1["player"] = _proc_cpu_s(player.pid)
        process_cpu = {n: round(100.0 * (cpu1[n] - cpu0[n]) / ((t1 - t0) / 1e9), 1) for n in cpu0}
        probe.recording = False
        s = {k: list(v) for k, v in probe.samples.items()}
        diag = {n: _in_window(list(v), t0, t1) for n, v in probe.diag.items()}
        status = {n: v[-1] for n, v in diag.items() if v}
    finally:
        procs = [p for p in (player, launch) if p is not None]
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.communicate()
    seconds = (t1 - t0) / 1e9
    sets_out = {st for _, st in s["keypoints"]}
    if player is not None:
        # frame sets the player published in the window (camera_info of cam0, as delivered) vs out
        sets_in = {st for _, st in s["transport"]}
        # a frame set published near the end may still be in flight: count only those well before
        horizon = max((st for st in sets_in), default=0) - int(0.3e9)
        considered = {st for st in sets_in if st <= horizon}
        missing, expected = len(considered - sets_out), len(considered)
        input_rate = len(sets_in) / seconds
        transport = _lat(s["transport"])  # the player's camera_info at the probe
    else:
        # the camera node stamps frame set k at epoch + k periods: a gap in the output stamps is
        # a frame set that never came out
        missing = _missing_periods(sorted(sets_out), 1e9 / args.fps)
        expected = len(sets_out) + missing
        cam = [(t, ast.literal_eval(v["published"])) for t, v in probe.diag.get("vmocap_camera", []) if t0 <= t <= t1]
        input_rate = float("nan")
        if len(cam) >= 2:  # frames the camera node sent per camera and second
            (ta, a), (tb, b) = cam[0], cam[-1]
            input_rate = float(np.mean([b[c] - a[c] for c in a])) / ((tb - ta) / 1e9)
        transport = _node_age(status.get("vmocap_camera"))  # capture (due) stamp -> sent by the camera node
    dropped = 100.0 * missing / max(expected, 1)
    pcm_name = args.pcm if args.pcm != "model" else (args.model or "blazepose")
    return {
        "rate_hz": round(len(sets_out) / seconds, 2),
        "input_rate_hz": round(input_rate, 2),
        "dropped_pct": round(dropped, 2),
        "latency_ms": _lat(s["joint_states"]),
        # age after each stage: the nodes' own figures; joint_states as a controller receives it
        "stages_ms": {"transport": transport, "pcm": _node_age(status.get("vmocap_pcm")),
                      "markers": _node_age(status.get("vmocap_markers")), "skeleton": _node_age(status.get("vmocap_skeleton")),
                      "joint_states": _lat(s["joint_states"])},
        "cpu_pct": {n: _cpu(probe.diag.get(n, []), t0, t1) for n in NODES if n in diag},  # callbacks only
        "process_cpu_pct": process_cpu,  # whole processes (rclpy executor and DDS threads included)
        "proc_ms_p50": {n: float(status[n].get("proc_ms_p50", "nan")) for n in NODES if n in status},
        "pcm": pcm_name,
        "feed": args.feed,
        "tracking_frames": int(len(s["joint_states"])),
        # share of the frame sets out (keypoints go out also while not tracking) with the person tracked
        "tracking_pct": round(100.0 * len({st for _, st in s["joint_states"]} & sets_out) / max(len(sets_out), 1), 1),
        "precision": status.get("vmocap_pcm", {}).get("precision", "n/a"),
        "node_status": {n: {k: v for k, v in status[n].items() if k in ("frames", "sync", "queue_dropped", "feedback_timeouts", "queued", "tracking")}
                        for n in NODES if n in status},
    }


def run(args: argparse.Namespace) -> int:

    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="vmocap_bench_graph_"))
    work.mkdir(parents=True, exist_ok=True)
    if not args.json:
        print(f"bench graph: preparing the bag in {work} ...", file=sys.stderr)
    if args.images == "pose2sim":
        if args.pcm != "model":
            print("bench graph: --images pose2sim needs --pcm model", file=sys.stderr)
            return 2
        rig, bag, rig_path, kps, motion = _pose2sim_bag(work, args)
    else:
        rig, bag, rig_path, kps, motion = _bag(work, args)
    env = graph_env()
    from .common import init_rclpy

    rclpy = init_rclpy()
    probe = Probe(rclpy, rig.names, input_topic=args.feed == "player")
    results = {}
    try:
        for mode in args.modes:
            if not args.json:
                print(f"bench graph: {mode} ...", file=sys.stderr)
            results[mode] = run_mode(mode, _config(work, mode, rig_path, kps, args, bag, motion), bag, rig, args, probe, env)
        scaling = _scaling(work, args, probe, env) if args.scaling else None
    finally:
        probe.close()
        if rclpy.ok():
            rclpy.shutdown()
    # the same frames offline (no DDS): what the graph adds on top of the computation
    offline_ms = offline_steady = None
    if args.images == "synthetic":
        from vmocap_core.apps.bench.speed import time_pipeline
        from vmocap_core.apps.process import process_bag
        from vmocap_core.method.config import PipelineConfig
        from vmocap_core.pcm.assembly import channel_keypoints
        from vmocap_core.pcm.providers import BagPcmProvider
        off = process_bag(bag, work / "offline_out.mcap", rig, config={"fps": float(args.fps)}, keypoints=kps, progress=False)
        offline_ms = round(off["ms_per_frame"], 2)
        # steady state, as the graph sees it: the bag's frame sets looped for as many frame sets
        # as one measured window holds (the mean above is over the bag once, initialization included)
        frames = BagPcmProvider(bag, rig, channel_keypoints(kps)).frames
        steady = time_pipeline(frames, rig, PipelineConfig.of(fps=float(args.fps)), int(args.fps * (args.seconds + args.warmup)),
                               int(1e9 / args.fps))
        offline_steady = {k: round(v, 2) for k, v in steady.items()}
    for r in results.values():
        r["graph_overhead_ms_p50"] = (round(r["latency_ms"]["p50"] - offline_steady["p50"], 2)
                                      if offline_ms is not None and args.pcm != "model" else None)
    out = {"modes": results, "scaling": scaling, "cpu": _cpu_flags(), "offline_ms_per_frame": offline_ms,
           "offline_ms_steady": offline_steady if offline_ms is not None else None, "cameras": len(rig), "size": args.size, "fps": args.fps, "seconds": args.seconds,
           "shm_profile": env.get("FASTRTPS_DEFAULT_PROFILES_FILE", "")}
    if args.json:
        print(json.dumps(out))
        return 0
    if offline_ms is not None:
        print(f"offline pipeline (vmocap process, same PCM frames): {offline_ms:.2f} ms per frame set over the bag once "
              f"(initialization included); looped as in the graph: p50 {offline_steady['p50']:.2f} ms, "
              f"p95 {offline_steady['p95']:.2f} ms, mean {offline_steady['mean']:.2f} ms")
    print(f"CPU: {out['cpu']}")
    for mode, r in results.items():
        st = r["stages_ms"]
        print(f"{mode:15s} rate {r['rate_hz']:6.2f} Hz (input {r['input_rate_hz']:.2f})  dropped {r['dropped_pct']:5.2f} %  "
              f"end-to-end p50 {r['latency_ms']['p50']:.1f} ms p95 {r['latency_ms']['p95']:.1f} ms  pcm: {r['pcm']}  feed: {r['feed']}"
              + (f"  graph adds {r['graph_overhead_ms_p50']:.1f} ms p50" if r["graph_overhead_ms_p50"] is not None else ""))
        print(f"   tracking {r['tracking_pct']:.1f} % of the frame sets out; CNN precision: {r['precision']}")
        print("   age after stage (p50/p95 ms): " + ", ".join(f"{k} {v['p50']}/{v['p95']}" for k, v in st.items()))
        print("   process CPU % of one core: " + ", ".join(f"{k} {v}" for k, v in r["process_cpu_pct"].items()))
        print("   callback CPU % of one core: " + ", ".join(f"{k} {v}" for k, v in r["cpu_pct"].items())
              + "   proc ms p50: " + ", ".join(f"{k} {v}" for k, v in r["proc_ms_p50"].items()))
    if scaling:
        print("scaling (default mode): cores cameras -> rate Hz, dropped %, end-to-end p95 ms, tracking %")
        for row in scaling:
            print(f"   {row['cores']} core(s) {row['cameras']} cameras: {row['rate_hz']:.2f} Hz, {row['dropped_pct']:.2f} %, "
                  f"{row['p95_ms']:.1f} ms, {row['tracking_pct']:.1f} %")
    return 0


def graph_env() -> dict[str, str]:
    """The environment of the graph a benchmark starts (localhost discovery, a domain of its own),
    also applied to this process, whose probe node joins that graph."""
    from .common import prepare_env

    env = dict(os.environ)
    prepare_env(env)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env["PYTHONUNBUFFERED"] = "1"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION")})
    if "FASTRTPS_DEFAULT_PROFILES_FILE" in env:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTRTPS_DEFAULT_PROFILES_FILE"]
    return env


def _cpu_flags() -> str:
    from vmocap_core.pcm.selfcheck import cpu_info

    return cpu_info().describe()


def _scaling(work: Path, args: argparse.Namespace, probe: Probe, env: dict[str, str]) -> list[dict]:
    """The default mode pinned to 1 and 2 cores, with 2, 4 and 6 cameras."""
    rows = []
    for cameras in (2, 4, 6):
        a = argparse.Namespace(**{**vars(args), "cameras": cameras})
        rig, bag, rig_path, kps, motion = (_pose2sim_bag if args.images == "pose2sim" else _bag)(work, a)
        cfg = _config(work, "default", rig_path, kps, a, bag, motion)
        for cores in ("0", "0,1"):
            r = run_mode("default", cfg, bag, rig, a, probe, env, cores)
            rows.append({"cores": cores.count(",") + 1, "cameras": cameras, "rate_hz": r["rate_hz"],
                         "dropped_pct": r["dropped_pct"], "p95_ms": r["latency_ms"]["p95"], "tracking_pct": r["tracking_pct"]})
    return rows
