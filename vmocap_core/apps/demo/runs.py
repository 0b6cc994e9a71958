"""The demo's two ways to run the method on its bag: in this process (Pipeline.step with the
real CNN) or as the ROS 2 node graph; both give the per-frame record the report reads."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...cameras.projection import Rig
from ...errors import VmocapError
from ...keypoints import KEYPOINTS
from ...paths import REPO
from .data import FPS, bag_frame_sets

# 60 fps: a Butterworth at 20 Hz, since 8 Hz lags ~3 px behind fast limbs (the speed-adaptive
# default: 12.17 vs 11.63 px). The clip lasts 1.7 s: output from the provisional fit instead of
# a 0.5 s identification phase (which left 67 of 100 frames tracked).
TRACKER_SETTINGS = {"fps": FPS, "filter_kind": "butterworth", "filter_cutoff_hz": 20.0, "identify_seconds": 0.0}


# ------------------------------------------------------------------------------ pipeline
def run_pipeline(bag: Path, rig: Rig, out_bag: Path, n_frames: int, threads: int = 2,
                 settings: dict[str, Any] | None = None, binning: int = 1, overwrite: bool = False) -> dict:
    """The pipeline on the bag's images with the real CNN; records everything the report needs.
    `settings`: the method's tunables (default TRACKER_SETTINGS); `binning`: images decoded
    reduced that many times (ModelPcmProvider's binning); an existing out_bag is replaced only
    with `overwrite`."""
    from tqdm import tqdm

    from ...bag import BagWriter
    from ...graph_config import Topics
    from ...method.config import PipelineConfig
    from ...method.pipeline import ImageSet, Pipeline
    from ...outputs.messages import CLOUD, markers_message, write_results
    from ...outputs.streams import SubjectOutputs
    from ...pcm.peaks import camera_keypoints
    from ...pcm.providers import ModelPcmProvider

    topics = Topics()
    pipe = Pipeline(rig, PipelineConfig.from_dict(TRACKER_SETTINGS if settings is None else settings),
                    ModelPcmProvider(rig, threads=threads, binning=binning))
    subject = SubjectOutputs(rig)
    rec: dict[str, list] = {k: [] for k in ("stamp", "status", "keypoints", "raw", "markers", "uv", "w", "score", "weights",
                                             "t_decode", "t_pcm", "t_markers", "t_skeleton", "n_views", "links")}
    cameras = np.arange(len(rig))
    it = bag_frame_sets(bag, rig, binning)
    with BagWriter(out_bag, compression="zstd", overwrite=overwrite, inputs=[bag]) as writer:
        bar = tqdm(total=n_frames, desc="pipeline", unit="frame", file=sys.stderr)
        while True:
            t0 = time.perf_counter()
            try:
                ns, images = next(it)
            except StopIteration:
                break
            t1 = time.perf_counter()
            res = pipe.step(ImageSet(ns, images, cameras))
            result, markers, pcm = res.skeleton, res.markers, res.pcm
            writer.write(topics.markers, CLOUD, markers_message(markers), ns)
            write_results(writer, topics, result, ns, subject)
            uv, w = camera_keypoints(pcm, len(rig))
            for k, v in (("stamp", ns), ("status", result.status), ("keypoints", result.keypoints),
                         ("raw", result.raw_keypoints), ("markers", markers.positions), ("uv", uv),
                         ("w", w), ("score", markers.score), ("weights", markers.weights), ("t_decode", t1 - t0),
                         ("t_pcm", pipe.timings["pcm"]), ("t_markers", pipe.timings["markers"]),
                         ("t_skeleton", pipe.timings["skeleton"]), ("n_views", pcm.n_views), ("links", result.link_lengths)):
                rec[k].append(v)
            bar.update(1)
        bar.close()
    out = {k: (np.array(v) if k not in ("status", "links") else v) for k, v in rec.items()}
    return out


# ------------------------------------------------------------------------------ node graph
# Share of the CPU the demo's graph may plan on; the rest goes to what the estimate leaves out
# (the detector while initializing, the decoder and the CNN slowing each other, the graph's own
# work). Measured on 2 Zen 5 cores (35 ms estimated per frame set): at 0.6x and 0.8x real time
# 96/100 tracked (2 runs each), at 0.9x 88-96, at 1x 89-95.
CPU_SHARE = 0.6
DECODE_SAMPLE = 5  # frame sets decoded to time the JPEG decoding
TRACKER_MS = 5.0  # markers, skeleton, transport and recorder per frame set (CPU ms; bench graph: ~3-5)
MIN_RATE = 0.01  # the slowest playback: 100 frame sets in under 3 minutes (a rate rounded to 0 would never end)


def live_rate(bag: Path, rig: Rig, views: int = 4, binning: int = 1) -> tuple[float, str]:
    """The demo's playback rate on this CPU: 1 (live speed) if the CPU time a frame set needs
    (decoding its JPEGs, timed here on the bag's first frame sets; the CNN on `views` crops, from
    the self-check; the tracker) fits in CPU_SHARE of the cores over a 60 Hz frame period, else
    slowed in proportion: a slow CPU reports accuracy, not dropped frame sets."""
    import os

    from ...pcm import selfcheck

    check = selfcheck.verdict("full")
    cnn = views * check.ms_per_crop[check.precision]
    t0, n = time.process_time(), 0
    for n, _ in enumerate(bag_frame_sets(bag, rig, binning), 1):
        if n == DECODE_SAMPLE:
            break
    decode = (time.process_time() - t0) * 1e3 / max(n, 1)
    need = decode + cnn + TRACKER_MS
    cores = len(os.sched_getaffinity(0))
    rate = max(MIN_RATE, round(min(1.0, CPU_SHARE * cores * 1e3 / FPS / need), 2))
    return rate, (f"{need:.0f} ms of CPU per frame set: JPEG decoding {decode:.0f}, CNN {cnn:.0f} "
                  f"({check.precision}), tracker ~{TRACKER_MS:.0f}; {cores} cores")


HOT_PATH = ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton"]  # one process, as config/graph.yaml


def run_graph(bag: Path, rig_yaml: Path, rig: Rig, out_dir: Path, n_frames: int, rate: float = 0.05,
              binning: int = 1, overwrite: bool = False) -> Path:
    """The ROS 2 node graph (camera from the bag: JPEG CompressedImage decoded in the camera
    node, or raw Image; CNN PCM node, markers, skeleton, recorder) as `vmocap launch` runs it
    by default: camera, CNN and tracker in one process (images never cross a process), the
    recorder apart; returns the recorded MCAP (outputs + each camera's 2D keypoints).

    The bag is played at `rate` x real time (1 = live speed, see live_rate); every node queues
    up to 50 frame sets, and what a node cannot take beyond that is dropped. The recorder
    replaces an earlier run's recording only with `overwrite`."""
    import os
    import signal
    import subprocess

    import yaml
    from tqdm import tqdm

    from ...graph_config import Topics, stage_sections

    if not rate > 0:
        raise VmocapError(f"playback rate {rate}: must be above 0 (1 = live speed)")

    topics = Topics()
    record = [topics.keypoints, topics.feedback, topics.joint_states, topics.root_pose, topics.robot_description,
              topics.markers, topics.skeleton, Topics.diagnostics]
    # the report needs each camera's 2D detections, not the heatmaps (1.7 MB a frame set at 60 Hz)
    record += [topics.pcm_keypoints(c.name) for c in rig]
    # /tf as well, so the recording is complete for `vmocap export` and RViz (the recorder derives
    # it where it does not travel over DDS; then nobody publishes it: the camera must not wait for it)
    tf = [Topics.tf, Topics.tf_static]
    output = out_dir / "graph_outputs.mcap"
    stages = stage_sections(TRACKER_SETTINGS)
    cfg = {
        "/**": {"ros__parameters": {"rig": str(rig_yaml), "cameras": [""], "namespace": topics.ns,
                                    "pcm_keypoints": [""], "use_sim_time": False, "binning": binning, **stages["/**"]}},
        "vmocap_camera": {"ros__parameters": {"source": "bag", "uri": str(bag), "rate": rate, "loop": False,
                                              "start_offset": 0.0, "wait_topics": record}},
        "vmocap_pcm": {"ros__parameters": {"source": "model", "model": "blazepose", "min_cameras": 2,
                                           "silent_after_ms": 5000.0, "use_feedback": True, "queue_depth": 50}},
        # a recording, not a live feed: every node queues frame sets (up to 50) rather than
        # keeping only the newest
        "vmocap_markers": {"ros__parameters": {"min_cameras": 2, "silent_after_ms": 5000.0,
                                               "feedback_timeout_ms": 2000.0, "views": [""], "queue_depth": 50,
                                               **stages["vmocap_markers"]}},
        "vmocap_skeleton": {"ros__parameters": {"queue_depth": 50, **stages["vmocap_skeleton"]}},
        "vmocap_recorder": {"ros__parameters": {"output": str(output), "topics": record + tf, "compression": "zstd",
                                                "overwrite": overwrite}},
        "vmocap_launch": {"mode": "processes", "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml"),
                          "nodes": [*HOT_PATH, "vmocap_recorder"], "groups": [HOT_PATH]},
    }
    earlier = _identity(output)  # an earlier run's recording, replaced only when this run's is complete
    cfg_path = out_dir / "graph.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    launch = [sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg_path), "--nodes"]
    back = ["vmocap_recorder"]
    procs: list[subprocess.Popen] = []

    def stop(proc: subprocess.Popen) -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # the launcher stops its nodes; the recorder flushes
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    log_rec, log_hot = out_dir / "graph_recorder.log", out_dir / "graph.log"
    with open(log_rec, "w") as lr, open(log_hot, "w") as lh:
        try:
            # The hot path starts once the recorder is up (else the first outputs would go
            # unrecorded); in its process the camera plays once the PCM node subscribes.
            procs.append(subprocess.Popen(launch + back, stdout=lr, stderr=subprocess.STDOUT, env=env, cwd=REPO))
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline and procs[0].poll() is None:
                if all(f"READY {n}" in log_rec.read_text() for n in back):
                    break
                time.sleep(0.5)
            else:
                raise VmocapError(f"the recorder did not start; see {log_rec}")
            procs.append(subprocess.Popen(launch + HOT_PATH, stdout=lh, stderr=subprocess.STDOUT, env=env, cwd=REPO))
            seconds = int(n_frames / FPS / rate + 15)  # playback + the last frames through the graph
            for _ in tqdm(range(seconds), desc="node graph", unit="s", file=sys.stderr):
                if any(p.poll() is not None for p in procs):
                    break
                time.sleep(1.0)
        finally:
            for proc in reversed(procs):
                stop(proc)
    if not output.exists() or _identity(output) == earlier:
        raise VmocapError(f"the node graph wrote no {output}; see {log_hot} and {log_rec}")
    return output


def _identity(path: Path) -> tuple[int, int] | None:
    """(inode, modification time) of a file, None when there is none."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns


def recording_from_graph(path: Path, rig: Rig, n_frames: int) -> dict:
    """The report's per-frame record from the graph's recorded topics (frame f = stamp f/60 s)."""
    from ...bag import BagReader
    from ...bag import messages as M
    from ...graph_config import Topics
    topics = Topics()
    stamps = np.array([int(round(f * 1e9 / FPS)) for f in range(n_frames)], dtype=np.int64)
    index = {int(s): f for f, s in enumerate(stamps)}
    J, C = len(KEYPOINTS), len(rig)
    nan3 = np.full((n_frames, J, 3), np.nan)
    rec: dict[str, Any] = {"stamp": stamps, "status": ["dropped"] * n_frames, "keypoints": nan3.copy(), "raw": nan3.copy(),
           "markers": nan3.copy(), "uv": np.full((n_frames, C, J, 2), np.nan), "w": np.zeros((n_frames, C, J)),
           "score": np.zeros(n_frames), "weights": np.zeros((n_frames, J)), "n_views": np.zeros(n_frames, int)}
    for k in ("t_decode", "t_pcm", "t_markers", "t_skeleton"):
        rec[k] = np.full(n_frames, np.nan)  # per-stage timing: `vmocap bench graph` measures the graph
    detections = {topics.pcm_keypoints(c.name): i for i, c in enumerate(rig)}
    node_timing: dict[str, dict[str, float]] = {}
    with BagReader(path) as reader:
        for m in reader.messages():
            msg = m.decode()
            if m.topic == Topics.diagnostics:
                for st in msg.get("status", []):  # the nodes' own processing time (last report wins)
                    kv = {e["key"]: e["value"] for e in st.get("values", [])}
                    if "proc_ms_p50" in kv:
                        node_timing[st["name"]] = {"mean_ms": float(kv.get("proc_ms_mean", "nan")),
                                                   "median_ms": float(kv["proc_ms_p50"]), "p95_ms": float(kv["proc_ms_p95"]),
                                                   "frames": float(kv.get("proc_ms_n", "nan"))}
                continue
            f = index.get(M.stamp_ns(msg)) if isinstance(msg, dict) and "header" in msg else None
            if f is None:
                continue
            if m.topic in detections:
                c = detections[m.topic]
                rec["uv"][f, c], rec["w"][f, c] = M.image_keypoints(msg)
                rec["n_views"][f] += 1
            elif m.topic == topics.keypoints:
                P, S, _ = M.cloud_keypoints(msg)
                rec["status"][f] = "tracking" if P is not None else "initializing"
                if P is not None:
                    rec["keypoints"][f] = P
            elif m.topic == topics.feedback:  # the first IK, at the CNN's landmarks
                P, _, _ = M.cloud_keypoints(msg)
                if P is not None:
                    rec["raw"][f] = P
            elif m.topic == topics.markers:
                P, S, _ = M.cloud_keypoints(msg)
                if P is not None:
                    rec["markers"][f] = P
                rec["weights"][f] = S
    rec["node_timing"] = node_timing
    seen = rec["n_views"] > 0
    rec["score"] = np.where(seen, rec["weights"].sum(axis=1) / np.maximum(rec["n_views"], 1) / J, 0.0)
    return rec
