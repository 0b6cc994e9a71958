"""What a node-graph benchmark runs (graph.py, soak.py): the looped bag, the graph
config per launch mode, and the environment the graph and the probe share.

- `synthetic_bag`: benchmark rig, walk clip, random-texture images and the heatmaps recorded in
  the bag (`--pcm bag`); `pose2sim_bag`: the Pose2Sim demo videos (a real person), resized;
  `people_bag`: several rendered people (`--people`, max_people >= 2);
- `graph_config`: the shipped config/graph.yaml for one launch mode, PCM source and feed;
- `graph_env`: localhost discovery and a DDS domain of the benchmark's own.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
NODES = ["vmocap_pcm", "vmocap_markers", "vmocap_skeleton"]


def synthetic_bag(work: Path, args: argparse.Namespace):
    """--frames frame sets of the walk clip seen by the benchmark rig's first --cameras cameras at
    --size: random-texture images and the heatmaps, in a bag under `work` (kept between runs).
    Returns (rig, bag, rig file, the heatmaps' keypoints, motion file)."""
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


def pose2sim_bag(work: Path, args: argparse.Namespace):
    """The first --frames frame sets of the Pose2Sim demo (real person), resized to --size
    (intrinsics scaled to match), stamps at --fps."""
    import cv2

    from vmocap_core.apps.demo.data import video_paths, video_sizes
    from vmocap_core.bag import BagWriter
    from vmocap_core.bag import messages as M
    from vmocap_core.calibration.datasets import pose2sim_demo
    from vmocap_core.calibration.reference import load_qualisys
    from vmocap_core.cameras.projection import Camera, Rig
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.graph_config import Topics

    demo = pose2sim_demo(fetch=True)
    videos = video_paths(demo)
    full = load_qualisys(demo / "calibration" / "Calib.qca.txt", video_sizes(videos))
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
        with BagWriter(bag, overwrite=True) as wr:  # its own scratch bag: a .partial a killed run left is replaced
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


def people_bag(work: Path, args: argparse.Namespace):
    """--people people rendered with exact bodies (bench images --people's scene: the walk
    clip, the others crossing and standing beside it) in the benchmark rig's first --cameras
    cameras at 1024x768, --frames frame sets re-stamped at --fps (the looped scene jumps back
    at its end: people may be found anew there)."""
    from vmocap_core.apps.bench import people as scene
    from vmocap_core.apps.bench.images import DEFAULT_CACHE
    from vmocap_core.apps.render.group import GroupSpec, Walker, render_group
    from vmocap_core.apps.render.recording import ClipSpec
    from vmocap_core.bag import BagReader, BagWriter
    from vmocap_core.cameras.rig_file import load_rig, save_rig
    from vmocap_core.graph_config import Topics

    full = load_rig(REPO / "config" / "benchmark_rig.yaml")
    rig = full.subset(full.names[: args.cameras]) if args.cameras < len(full) else full
    clips = scene.person_clips(None, args.people)
    seconds = args.frames / 60.0  # rendered at 60 Hz, whatever --fps plays it at
    subject = ClipSpec(clips[0], args.frames, 60.0, 0)
    walkers = tuple(Walker(ClipSpec(c, args.frames, 60.0, 0, variant=k), path, scene.SIZES[k])
                    for k, (c, path) in enumerate(zip(clips[1:], scene.walker_paths(args.people, seconds)), start=1))
    rec = render_group(GroupSpec(subject, walkers), full, Path(args.cache or DEFAULT_CACHE), progress=not args.json)
    bag = work / f"people{args.people}_{len(rig)}cams_{args.frames}_{args.fps:g}.mcap"
    if not bag.exists():
        topics = Topics()
        wanted = [t for c in rig.names for t in (topics.image(c), topics.camera_info(c))]
        with BagReader(rec) as r, BagWriter(bag, overwrite=True) as wr:  # its own scratch bag
            first = None
            for m in r.messages(wanted):
                first = m.log_time_ns if first is None else first
                k = round((m.log_time_ns - first) * 60.0 / 1e9)  # the frame set's index at 60 Hz
                t = 1_000_000_000_000 + int(round(k * 1e9 / args.fps))
                msg = m.decode()
                msg["header"]["stamp"] = {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}
                wr.write(m.topic, m.type, msg, t)
    rig_path = work / f"rig_people{len(rig)}.yaml"
    save_rig(rig, rig_path)
    return rig, bag, rig_path, [], None


def graph_config(work: Path, mode: str, rig_path: Path, kps: list[str], args: argparse.Namespace, bag: Path, motion: Path) -> Path:
    """config/graph.yaml for launch `mode` (`default`: the shipped process groups), the PCM source
    (--pcm) and the feed (--feed), written to work/graph_<mode>.yaml."""
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
    people = getattr(args, "people", 0)
    if people:  # everyone in view: the nodes' several-people kinds
        common["max_people"] = max(people, 2)
    if args.feed == "camera":
        nodes.insert(0, "vmocap_camera")
        cfg["vmocap_camera"]["ros__parameters"].update(source="bag", uri=str(bag), rate=1.0, loop=True, restamp=True)
    shipped = cfg.get("vmocap_launch") or {}
    cfg["vmocap_launch"] = {"mode": "processes" if mode == "default" else mode, "nodes": nodes,
                            "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml")}
    if mode == "default":
        cfg["vmocap_launch"]["groups"] = shipped.get("groups") or []
    from ..run_node import parse_sets

    for node, params in parse_sets(getattr(args, "set", None) or []).items():  # --set NODE.PARAM=VALUE
        cfg.setdefault(node, {"ros__parameters": {}})["ros__parameters"].update(params)
    path = work / f"graph_{mode}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def graph_env() -> dict[str, str]:
    """The environment of the graph a benchmark starts (localhost discovery, a domain of its own),
    also applied to this process, whose probe node joins that graph."""
    from ..common import prepare_env

    env = dict(os.environ)
    prepare_env(env)
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env["PYTHONUNBUFFERED"] = "1"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION")})
    if "FASTRTPS_DEFAULT_PROFILES_FILE" in env:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTRTPS_DEFAULT_PROFILES_FILE"]
    return env
