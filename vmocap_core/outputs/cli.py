"""`vmocap urdf -o SUBJECT.urdf`: the tracked subject's URDF, from the robot_description a run
recorded (`--bag OUT.mcap`: the last one, or the one in force at `--at` seconds), or from the
skeleton identified on a processed bag's keypoints (`--keypoints OUT.mcap`), or the default
body (no input: BodyDimensions' adult of 1.75 m)."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..errors import BagError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--bag", help="MCAP with NS/robot_description (`vmocap process`, `vmocap record`)")
    src.add_argument("--keypoints", help="MCAP with NS/keypoints: identify the skeleton on them (as the tracker does)")
    parser.add_argument("--at", type=float, default=None, help="with --bag: the description in force at this bag time (s from its start)")
    parser.add_argument("--namespace", default="/vmocap")
    parser.add_argument("--name", default="vmocap_subject", help="robot name in the URDF")
    parser.add_argument("-o", "--output", required=True, help="URDF file to write ('-': standard output)")
    parser.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    parser.add_argument("--json", action="store_true", help="print the link lengths as JSON")


def _from_bag(path: str, topic: str, at: float | None) -> str:
    from ..bag import BagReader

    found = None
    with BagReader(path) as r:
        if topic not in r.topics:
            raise BagError(f"{path}: no {topic} (recorded by `vmocap process` and `vmocap record` since the URDF outputs)")
        limit = None if at is None else r.start_ns + int(at * 1e9)
        for m in r.messages([topic]):
            if limit is not None and m.log_time_ns > limit and found is not None:
                break
            found = m.decode()["data"]
    if not found:
        raise BagError(f"{path}: {topic} is empty")
    return found


def _identified(path: str, topic: str):
    from ..bag import BagReader
    from ..bag import messages as M
    from ..method.init import fit_skeleton
    frames = []
    with BagReader(path) as r:
        if topic not in r.topics:
            raise BagError(f"{path}: no {topic}")
        for m in r.messages([topic]):
            P, _, _ = M.cloud_keypoints(m.decode())
            if P is not None:
                frames.append(P)
    if len(frames) < 2:
        raise BagError(f"{path}: {len(frames)} frames with keypoints on {topic}; at least 2 are needed")
    fitted = fit_skeleton(np.array(frames[-60:]), 0.05)
    if fitted is None:
        raise BagError(f"{path}: the keypoints of {topic} do not fit one body (RMS above 5 cm)")
    return fitted[0].dims


def run(args: argparse.Namespace) -> int:
    from ..files import check_output, write_text
    from ..graph_config import Topics
    from ..method.skeleton import BodyDimensions
    from .tf import UrdfKinematics
    from .urdf import SubjectModel

    topics = Topics(args.namespace)
    inputs = [p for p in (args.bag, args.keypoints) if p]
    if args.output != "-":
        check_output(args.output, inputs, args.overwrite)  # before reading: a refusal costs nothing
    dims = None
    if args.bag:
        xml = _from_bag(args.bag, topics.robot_description, args.at)
    else:
        dims = _identified(args.keypoints, topics.keypoints) if args.keypoints else BodyDimensions()
        xml = SubjectModel(dims).to_xml(args.name)
    kin = UrdfKinematics(xml)  # a description we cannot read back is not written
    if args.output == "-":
        sys.stdout.write(xml)
    else:
        write_text(args.output, xml, inputs, args.overwrite)
    info = {"output": args.output, "joints": len(kin.joint_names), "fixed_frames": len(kin.static_transforms())}
    if dims is not None:
        info["link_lengths"] = {k: round(v, 4) for k, v in dims.bone_lengths().items()}
    if args.json:
        print(json.dumps(info))
    elif args.output != "-":
        print(f"{info['joints']} joints, {info['fixed_frames']} keypoint frames -> {args.output}")
    return 0
