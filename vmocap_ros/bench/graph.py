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
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .graph_setup import NODES, graph_config, graph_env, people_bag, pose2sim_bag, synthetic_bag
from .probe import Probe, callback_cpu, in_window, latency, missing_periods, node_age

STAGE_NODES = list(NODES)  # the nodes whose diagnostics are read
REPORT_WAIT_S = 10.0  # how long to wait for a camera node report around the window (they come once a second)


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
    parser.add_argument("--people", type=int, default=0, choices=(0, 1, 2, 3),
                        help="1-3: that many rendered people (benchmark rig, 1024x768; use --frames 240 or more: "
                             "the scene loops) through the graph with max_people at least 2; "
                             "needs --pcm model")
    parser.add_argument("--cache", default=None, help="--people: where rendered scenes are kept (default out/render_cache)")
    parser.add_argument("--feed", default="camera", choices=("camera", "player"),
                        help="camera: the graph's own vmocap_camera node plays the bag (looped, restamped: capture "
                             "stamp = the moment the frame set is due), in the graph's process in single_process mode; "
                             "player: a separate `vmocap play --restamp` process publishes the images over DDS")
    parser.add_argument("--modes", nargs="+", default=["default", "processes", "single_process"],
                        choices=("default", "processes", "single_process"))
    parser.add_argument("--scaling", action="store_true",
                        help="also the default mode on 1 and 2 cores (taskset) with 2, 4 and 6 cameras (--images pose2sim: "
                             "cameras beyond the 4 videos repeat them), to size a machine")
    parser.add_argument("--workdir", default=None, help="where the bag and configs go, kept (default: a temp dir, removed at the end)")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="a parameter of the benchmarked graph (e.g. vmocap_pcm.inference_thread=false)")


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
        if player is None:
            # the input rate is read from the camera node's once-a-second reports, from the last
            # one before the window: on a loaded core the first may come late
            probe.spin_until(lambda: bool(probe.diag.get("vmocap_camera")), REPORT_WAIT_S)
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
        diag = {n: in_window(list(v), t0, t1) for n, v in probe.diag.items()}
        status = {n: v[-1] for n, v in diag.items() if v}
        if player is None:
            # the input rate is read between two of the camera node's once-a-second reports; on a
            # loaded core a short window may hold one or none, so wait for the first one after it
            probe.spin_until(lambda: any(t > t1 for t, _ in probe.diag.get("vmocap_camera", [])), REPORT_WAIT_S)
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
        input_from = f"{len(sets_in)} frame sets at the probe"
        transport = latency(s["transport"])  # the player's camera_info at the probe
    else:
        # the camera node stamps frame set k at epoch + k periods: a gap in the output stamps is
        # a frame set that never came out
        missing = missing_periods(sorted(sets_out), 1e9 / args.fps)
        expected = len(sets_out) + missing
        # from the camera's last report before the window to its first after it
        reports = probe.diag.get("vmocap_camera", [])
        reports = ([r for r in reports if r[0] < t0][-1:] + [r for r in reports if t0 <= r[0] <= t1]
                   + [r for r in reports if r[0] > t1][:1])
        # frames the camera node read: those it sent per camera, and the frame sets its flow
        # control did not send while the CNN was busy (cameras/flow.py)
        cam = [(t, ast.literal_eval(v["published"]), ast.literal_eval(v.get("flow", "{}")).get("skipped", 0))
               for t, v in reports]
        input_rate = float("nan")
        input_from = f"{len(cam)} camera node reports around the window (2 needed)"
        if len(cam) >= 2:
            (ta, a, sa), (tb, b, sb) = cam[0], cam[-1]
            input_rate = (float(np.mean([b[c] - a[c] for c in a])) + sb - sa) / ((tb - ta) / 1e9)
        transport = node_age(status.get("vmocap_camera"))  # capture (due) stamp -> sent by the camera node
    dropped = 100.0 * missing / max(expected, 1)
    pcm_name = args.pcm if args.pcm != "model" else (args.model or "blazepose")
    return {
        "rate_hz": round(len(sets_out) / seconds, 2),
        "input_rate_hz": round(input_rate, 2),
        "input_rate_from": input_from,
        "dropped_pct": round(dropped, 2),
        # the longest a subscriber waits for the next frame set (capture stamps): a stall, not a rate
        "longest_gap_ms": round(float(np.diff(sorted(sets_out)).max(initial=0)) / 1e6, 1),
        "latency_ms": latency(s["joint_states"]),
        # age after each stage: the nodes' own figures; joint_states as a controller receives it
        "stages_ms": {"transport": transport, "pcm": node_age(status.get("vmocap_pcm")),
                      "markers": node_age(status.get("vmocap_markers")), "skeleton": node_age(status.get("vmocap_skeleton")),
                      "joint_states": latency(s["joint_states"])},
        "cpu_pct": {n: callback_cpu(probe.diag.get(n, []), t0, t1) for n in STAGE_NODES if n in diag},  # callbacks only
        "process_cpu_pct": process_cpu,  # whole processes (rclpy executor and DDS threads included)
        "proc_ms_p50": {n: float(status[n].get("proc_ms_p50", "nan")) for n in STAGE_NODES if n in status},
        "pcm": pcm_name,
        "feed": args.feed,
        "tracking_frames": int(len(s["joint_states"])),
        # share of the frame sets out (keypoints go out also while not tracking) with the person tracked
        "tracking_pct": round(100.0 * len({st for _, st in s["joint_states"]} & sets_out) / max(len(sets_out), 1), 1),
        "precision": status.get("vmocap_pcm", {}).get("precision", "n/a"),
        "node_status": {n: {k: v for k, v in status[n].items() if k in ("frames", "sync", "queue_dropped", "feedback_timeouts", "queued", "tracking",
                                                                       "flow", "published")}
                        for n in ["vmocap_camera", *STAGE_NODES] if n in status},
    }


def run(args: argparse.Namespace) -> int:
    if args.workdir:
        work = Path(args.workdir)
        work.mkdir(parents=True, exist_ok=True)
        return _run(args, work)
    # a temp dir of our own goes when we are done: each run writes a ~180 MB bag there
    with tempfile.TemporaryDirectory(prefix="vmocap_bench_graph_") as tmp:
        return _run(args, Path(tmp))


def scene_restarts(scene_s: float, warmup_s: float, seconds: float) -> int:
    """How often a looped scene of scene_s seconds jumps back to its start within the measured
    window (warmup_s to warmup_s + seconds from the first frame set; the graph's start-up delays
    it a little)."""
    return math.floor((warmup_s + seconds) / scene_s) - math.floor(warmup_s / scene_s) if scene_s > 0 else 0


def _run(args: argparse.Namespace, work: Path) -> int:
    if not args.json:
        print(f"bench graph: preparing the bag in {work} ...", file=sys.stderr)
    if args.people:
        if args.pcm != "model":
            print("bench graph: --people needs --pcm model", file=sys.stderr)
            return 2
        rig, bag, rig_path, kps, motion = people_bag(work, args)
    elif args.images == "pose2sim":
        if args.pcm != "model":
            print("bench graph: --images pose2sim needs --pcm model", file=sys.stderr)
            return 2
        rig, bag, rig_path, kps, motion = pose2sim_bag(work, args)
    else:
        rig, bag, rig_path, kps, motion = synthetic_bag(work, args)
    env = graph_env()
    from ..common import init_rclpy

    rclpy = init_rclpy()
    probe = Probe(rclpy, rig.names, input_topic=args.feed == "player")
    results = {}
    try:
        for mode in args.modes:
            if not args.json:
                print(f"bench graph: {mode} ...", file=sys.stderr)
            results[mode] = run_mode(mode, graph_config(work, mode, rig_path, kps, args, bag, motion), bag, rig, args, probe, env)
        scaling = _scaling(work, args, probe, env) if args.scaling else None
    finally:
        probe.close()
        if rclpy.ok():
            rclpy.shutdown()
    # the same frames offline (no DDS): what the graph adds on top of the computation
    offline_ms = offline_steady = None
    if args.images == "synthetic" and not args.people:
        from vmocap_core.apps.bench.speed import time_pipeline
        from vmocap_core.apps.process import process_bag
        from vmocap_core.method.config import PipelineConfig
        from vmocap_core.pcm.assembly import channel_keypoints
        from vmocap_core.pcm.providers import BagPcmProvider
        off = process_bag(bag, work / "offline_out.mcap", rig, config={"fps": float(args.fps)}, keypoints=kps, progress=False,
                          overwrite=True)  # the benchmark's own scratch file (a --workdir used again)
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
    # --people: the looped scene jumps back at its end and everyone is found anew there: a
    # window that holds a jump measures those searches too, not the steady rate alone
    restarts = scene_restarts(args.frames / args.fps, args.warmup, args.seconds) if args.people else None
    out = {"modes": results, "scaling": scaling, "cpu": cpu_flags(), "people": args.people, "scene_restarts_in_window": restarts,
           "offline_ms_per_frame": offline_ms,
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
    if restarts:
        steady = math.ceil((args.warmup + args.seconds + 1.0) * args.fps / 60.0) * 60
        print(f"the {args.frames / args.fps:.1f} s scene jumps back {restarts}x in the measured window (everyone found anew "
              f"there); --frames {steady} or more measures the steady rate")
    for mode, r in results.items():
        st = r["stages_ms"]
        print(f"{mode:15s} rate {r['rate_hz']:6.2f} Hz (input {r['input_rate_hz']:.2f})  dropped {r['dropped_pct']:5.2f} %  "
              f"end-to-end p50 {r['latency_ms']['p50']:.1f} ms p95 {r['latency_ms']['p95']:.1f} ms  pcm: {r['pcm']}  feed: {r['feed']}"
              + (f"  graph adds {r['graph_overhead_ms_p50']:.1f} ms p50" if r["graph_overhead_ms_p50"] is not None else ""))
        if math.isnan(r["input_rate_hz"]):  # say why
            print(f"   input rate unknown: {r['input_rate_from']}")
        print(f"   tracking {r['tracking_pct']:.1f} % of the frame sets out; longest gap between two out "
              f"{r['longest_gap_ms']:.0f} ms; CNN precision: {r['precision']}")
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


def cpu_flags() -> str:
    """This machine's CPU as the benchmark reports name it."""
    from vmocap_core.pcm.selfcheck import cpu_info

    return cpu_info().describe()


def _scaling(work: Path, args: argparse.Namespace, probe: Probe, env: dict[str, str]) -> list[dict]:
    """The default mode pinned to 1 and 2 cores, with 2, 4 and 6 cameras."""
    rows = []
    for cameras in (2, 4, 6):
        a = argparse.Namespace(**{**vars(args), "cameras": cameras})
        rig, bag, rig_path, kps, motion = (pose2sim_bag if args.images == "pose2sim" else synthetic_bag)(work, a)
        cfg = graph_config(work, "default", rig_path, kps, a, bag, motion)
        for cores in ("0", "0,1"):
            r = run_mode("default", cfg, bag, rig, a, probe, env, cores)
            rows.append({"cores": cores.count(",") + 1, "cameras": cameras, "rate_hz": r["rate_hz"],
                         "dropped_pct": r["dropped_pct"], "p95_ms": r["latency_ms"]["p95"], "tracking_pct": r["tracking_pct"]})
    return rows
