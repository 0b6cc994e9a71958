"""`vmocap bench soak --minutes M [--json]`: the node graph at 30 Hz for M minutes on a looped
bag (the graph's camera node plays a synthetic images+PCM bag, restamped; PCM from the bag, as
`vmocap bench graph`), measured per window (default one minute): output rate, frame sets
dropped (gaps in the evenly spaced output stamps), end-to-end latency p95 (capture stamp ->
joint_states at a probe), and the RSS of every process of the graph. A benchmark, not a test."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, required=True, help="how long the graph runs (after a 5 s warm-up)")
    parser.add_argument("--window", type=float, default=60.0, help="seconds per reported window")
    parser.add_argument("--mode", default="processes", choices=("default", "processes", "single_process"),
                        help="processes (default here): one process per node, so RSS is per node")
    parser.add_argument("--size", default="1024x768", help="image size WxH")
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--workdir", default=None, help="where the bag and config go (default: a temp dir)")


def rss_mib(pid: int) -> float:
    """Resident set size of a process and its threads (MiB); NaN when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return float("nan")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..common import init_rclpy, stop_graph
    from .graph import cpu_flags
    from .graph_setup import graph_config, graph_env, synthetic_bag
    from .probe import Probe, latency, missing_periods

    if args.minutes <= 0:
        print("bench soak: --minutes must be > 0", file=sys.stderr)
        return 2
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="vmocap_soak_"))
    work.mkdir(parents=True, exist_ok=True)
    # bench graph's bag and config: 15 looped frame sets, PCM from the bag, the camera node feeding
    g = argparse.Namespace(size=args.size, cameras=args.cameras, frames=15, fps=30.0, pcm="bag", model="", feed="camera")
    rig, bag, rig_path, kps, motion = synthetic_bag(work, g)
    cfg = graph_config(work, args.mode, rig_path, kps, g, bag, motion)
    c = yaml.safe_load(cfg.read_text())  # the recorder too: a long run's memory includes its bag
    c["vmocap_launch"]["nodes"].append("vmocap_recorder")
    # its own recording in its work folder: a --workdir used again replaces it
    c["vmocap_recorder"]["ros__parameters"].update(output=str(work / "soak_out.mcap"), overwrite=True)
    cfg.write_text(yaml.safe_dump(c))
    env = graph_env()
    rclpy = init_rclpy()
    probe = Probe(rclpy, rig.names, input_topic=False)
    launch = subprocess.Popen([sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    pids = {"graph (one process)": launch.pid}
    if args.mode != "single_process":
        line = launch.stdout.readline()
        pids = {i.split("[")[0]: int(i.split("[")[1].rstrip("]\n")) for i in line.rsplit("processes: ", 1)[1].split(", ")}
    windows: list[dict] = []
    try:
        probe.min_stamp, probe.recording = time.time_ns(), True
        deadline = time.monotonic() + 120
        while not probe.samples["keypoints"]:
            probe.spin_for(0.2)
            if launch.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the graph gave no output:\n" + (launch.communicate()[0] if launch.poll() is not None else ""))
        probe.spin_for(5.0)  # warm-up
        rss0 = {n: rss_mib(p) for n, p in pids.items()}
        n_win = max(1, int(round(args.minutes * 60.0 / args.window)))
        for _ in tqdm(range(n_win), desc="soak windows", disable=args.json, file=sys.stderr):
            probe.clear()
            t0 = time.monotonic()
            probe.spin_for(args.window)
            secs = time.monotonic() - t0
            out = sorted({st for _, st in probe.samples["keypoints"]})
            missing = missing_periods(out, 1e9 / g.fps)
            lat = latency(probe.samples["joint_states"])
            windows.append({"rate_hz": round(len(out) / secs, 2), "dropped": missing,
                            "dropped_pct": round(100.0 * missing / max(len(out) + missing, 1), 2),
                            "latency_p95_ms": lat["p95"], "latency_p50_ms": lat["p50"],
                            "rss_mib": {n: rss_mib(p) for n, p in pids.items()}})
            if launch.poll() is not None:
                raise RuntimeError(f"the graph exited during the soak with {launch.returncode}")
    finally:
        probe.close()
        if rclpy.ok():
            rclpy.shutdown()
        stop_graph(launch)
    rss1 = windows[-1]["rss_mib"]
    # growth after the first window (the target's "after the first minute")
    base = windows[0]["rss_mib"]
    growth = {n: round(100.0 * (rss1[n] - base[n]) / base[n], 2) for n in base}
    trend = {k: _slope([w[k] for w in windows]) for k in ("dropped", "latency_p95_ms", "rate_hz")}
    res = {"mode": args.mode, "minutes": args.minutes, "window_s": args.window, "cameras": len(rig), "size": args.size,
           "rss_start_mib": rss0, "rss_end_mib": rss1, "rss_growth_after_first_window_pct": growth,
           "trend_per_window": trend, "windows": windows, "cpu": cpu_flags(), "load": os.getloadavg()}
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"soak {args.minutes} min, mode {args.mode}, {len(rig)} cameras {args.size}; CPU: {res['cpu']}; load {res['load']}")
    for k, w in enumerate(windows):
        print(f"  window {k + 1}: {w['rate_hz']:.2f} Hz, dropped {w['dropped']} ({w['dropped_pct']} %), "
              f"latency p95 {w['latency_p95_ms']} ms, RSS MiB " + ", ".join(f"{n} {v}" for n, v in w["rss_mib"].items()))
    print("  RSS start -> end MiB: " + ", ".join(f"{n} {rss0[n]} -> {rss1[n]}" for n in rss0))
    print(f"  RSS growth after the first window %: {growth}; trend per window (least squares): {trend}")
    return 0


def _slope(values: list[float]) -> float:
    y = np.asarray(values, dtype=float)
    if y.size < 2 or not np.isfinite(y).all():
        return float("nan")
    return round(float(np.polyfit(np.arange(y.size), y, 1)[0]), 3)
