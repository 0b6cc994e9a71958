"""The image benchmark's recordings through the ROS 2 node graph (`vmocap bench images --graph`).

The graph's own vmocap_camera node plays the rendered MCAP (original stamps) in lockstep: each
frame set once the previous one's feedback came back, so every frame set is processed whatever
this CPU's speed (`rate` > 0 plays at that fraction of real time instead, as a live camera
would feed it, dropping what the CNN cannot keep up with), vmocap_pcm runs the CNN (rotation and
precision as asked), vmocap_markers and vmocap_skeleton track; all nodes in one process
(`vmocap launch`, single_process). A subscriber here collects /vmocap/keypoints by capture
stamp until the recording's last frame set came out (or the graph fell silent).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from vmocap_core.errors import VmocapError
from vmocap_core.keypoints import KEYPOINTS

REPO = Path(__file__).resolve().parents[2]
NODES = ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton"]


def graph_config(work: Path, rec: Path, rig_path: Path, rotation: str, tracker: dict, rate: float,
                 crop_prediction: str = "rigid", max_people: int = 1) -> Path:
    """tracker: flat tracker settings (PipelineConfig keys, `fps` among them) for the nodes;
    rate <= 0: lockstep; max_people > 1: everyone in view (the nodes' several-people kinds)."""
    from vmocap_core.graph_config import stage_sections

    cfg = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    cfg["/**"]["ros__parameters"].update(rig=str(rig_path), pcm_keypoints=[""])  # the CNN's 25 channels
    cfg["vmocap_camera"]["ros__parameters"].update(source="bag", uri=str(rec), rate=max(float(rate), 0.0), loop=False,
                                                    restamp=False, wait_subscribers=120.0,
                                                    wait_topics=["/vmocap/keypoints"])  # this probe: the first outputs are volatile
    cfg["/**"]["ros__parameters"]["lockstep"] = rate <= 0
    cfg["vmocap_pcm"]["ros__parameters"].update(source="model", model="blazepose", rotation=rotation,
                                                 crop_prediction=crop_prediction)
    for section, values in stage_sections(tracker).items():
        cfg.setdefault(section, {}).setdefault("ros__parameters", {}).update(values)
    cfg["/**"]["ros__parameters"]["max_people"] = int(max_people)
    cfg["vmocap_launch"] = {"mode": "single_process", "nodes": NODES,
                            "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml")}
    path = work / f"graph_{rec.stem}_{rotation}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def run_graph(rec: Path, rig_path: Path, stamps: np.ndarray, rotation: str, precision: str, tracker: dict,
              rate: float, work: Path, silent_s: float = 30.0, crop_prediction: str = "rigid",
              max_people: int = 1) -> tuple[np.ndarray, dict]:
    """Estimates (T, 25, 3) at `stamps` (NaN where none came out) and counts; tracker: flat
    tracker settings (PipelineConfig keys, `fps` among them). max_people > 1: the counts hold
    `bodies`, each REP-155 body's keypoints (T, 25, 3) by id, taken as a ROS4HRI listener
    does (a body's topic opened when its id first appears in /humans/bodies/tracked; its first
    frame sets may pass before the subscription matched)."""
    from vmocap_core.bag import cdr
    from vmocap_core.bag import messages as M
    from vmocap_core.outputs.messages import DIAG, DIAGNOSTICS_PERIOD_S

    from ..common import msg_class, prepare_env, qos, stop_graph
    from ..run_node import probe_node

    cfg = graph_config(work, rec, rig_path, rotation, tracker, rate, crop_prediction, max_people)
    fps = float(tracker["fps"])
    env = dict(os.environ)
    prepare_env(env)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env["VMOCAP_PCM_PRECISION"] = precision  # read by the CNN in vmocap_pcm
    env["PYTHONUNBUFFERED"] = "1"
    got: dict[int, np.ndarray] = {}
    last_rx = [0.0]

    def on_cloud(store: dict[int, np.ndarray]):
        """Keypoint clouds into `store` by capture stamp (NaN: the frame set came out without a body)."""
        def take(data: bytes) -> None:
            d = cdr.decode("sensor_msgs/msg/PointCloud2", data)
            P, _, _ = M.cloud_keypoints(d)
            store[M.stamp_ns(d)] = P if P is not None else np.full((len(KEYPOINTS), 3), np.nan)
            last_rx[0] = time.monotonic()
        return take

    others: list[tuple[bool, int]] = []  # per vmocap_pcm /diagnostics report: tracking yet, others in view

    warnings: dict[str, None] = {}  # "node: message" of every WARN/ERROR report, in order, once each

    def on_diagnostics(data: bytes) -> None:
        for st in cdr.decode(DIAG, data)["status"]:
            level = st["level"] if isinstance(st["level"], int) else int.from_bytes(st["level"], "little")
            if level >= 1:
                warnings.setdefault(f"{st['name']}: {st['message']}")
            if st["name"].startswith("vmocap_pcm"):
                v = {kv["key"]: kv["value"] for kv in st["values"]}.get("others_in_view", "0")
                others.append((bool(got), int(v) if v.isdigit() else 0))

    bodies: dict[str, dict[int, np.ndarray]] = {}

    last = int(stamps[-1])
    # lockstep goes at the graph's pace, which only the silence check bounds
    expected_s = len(stamps) / fps / rate if rate > 0 else len(stamps) * 1.0
    with probe_node("vmocap_bench_images_probe", env) as (node, ex), open(work / f"{cfg.stem}.log", "w") as log:
        node.create_subscription(msg_class("sensor_msgs/msg/PointCloud2"), "/vmocap/keypoints", on_cloud(got), qos(200), raw=True)
        node.create_subscription(msg_class(DIAG), "/diagnostics", on_diagnostics, qos(50), raw=True)
        if max_people > 1:
            from vmocap_core.outputs.hri import IDS_LIST, TRACKED
            from vmocap_core.outputs.people import keypoints_topic

            def on_tracked(data: bytes) -> None:
                for i in cdr.decode(IDS_LIST, data)["ids"]:
                    if i not in bodies:
                        bodies[i] = {}
                        node.create_subscription(msg_class("sensor_msgs/msg/PointCloud2"), keypoints_topic("/vmocap", i),
                                                 on_cloud(bodies[i]), qos(200), raw=True)

            node.create_subscription(msg_class(IDS_LIST), TRACKED, on_tracked, qos(50), raw=True)
        launch = subprocess.Popen([sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg)], env=env,
                                  stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180.0 + 3.0 * expected_s
        try:
            while time.monotonic() < deadline and last not in got:
                ex.spin_once(timeout_sec=0.1)
                if launch.poll() is not None:
                    raise VmocapError(f"the node graph exited early (log: {log.name})")
                if got and time.monotonic() - last_rx[0] > silent_s:
                    break  # the graph fell silent: the tail of the recording was dropped
            # one more diagnostics period (the nodes report at 1 Hz): a WARN raised in the last
            # frame sets reaches the bench too, not only when the graph happened to report after it
            drain = time.monotonic() + DIAGNOSTICS_PERIOD_S + 0.3
            while time.monotonic() < drain and launch.poll() is None:
                ex.spin_once(timeout_sec=0.1)
        finally:
            stop_graph(launch)
    if not got:
        raise VmocapError(f"no keypoints came out of the node graph (log: {log.name})")
    row = {int(s): i for i, s in enumerate(stamps)}
    est = np.full((len(stamps), len(KEYPOINTS), 3), np.nan)
    for s, P in got.items():
        if s in row:
            est[row[s]] = P
    counts: dict = {"frame_sets_out": len(got), "frame_sets_in": len(stamps), "rate": rate, "others_in_view_max": max((n for _, n in others), default=0)}
    said = [n > 0 for out, n in others if out]  # once keypoints came out: did a report say someone else is there
    counts["others_in_view_pct"] = 100.0 * float(np.mean(said)) if said else None
    counts["warnings"] = list(warnings)
    if max_people > 1:
        counts["bodies"] = {}
        for i, store in bodies.items():
            b = np.full((len(stamps), len(KEYPOINTS), 3), np.nan)
            for s, P in store.items():
                if s in row:
                    b[row[s]] = P
            counts["bodies"][i] = b
    return est, counts
