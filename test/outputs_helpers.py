"""Helpers of the output tests: a bag's /tf chain read back with rosbags (a third-party reader)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def rosbags_messages(path: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time, message decoded by rosbags with the Jazzy type store)]."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    return out


def stamp(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def cloud(msg) -> np.ndarray:
    """Keypoints (25, 3) of a PointCloud2 as rosbags decodes it (layout: bag/messages.py)."""
    from vmocap_core.bag.messages import CLOUD_DTYPE

    pts = np.frombuffer(bytes(msg.data), dtype=CLOUD_DTYPE)
    return np.stack([pts["x"], pts["y"], pts["z"]], axis=1)[np.argsort(pts["id"])]


def tf_keypoint_errors(msgs: dict, ns: str = "/vmocap") -> tuple[float, list[int], set[int]]:
    """Largest distance between the kp_* frames of the TF chain (/tf_static, then each /tf in
    order) and the NS/keypoints of the same stamp; the /tf stamps; the tracked stamps."""
    from vmocap_core.keypoints import KEYPOINTS
    from vmocap_core.outputs.tf import TfTree, Transforms

    def transforms(m) -> Transforms:
        ts = m.transforms
        return Transforms([x.header.frame_id for x in ts], [x.child_frame_id for x in ts],
                          np.array([[x.transform.translation.x, x.transform.translation.y, x.transform.translation.z] for x in ts]),
                          np.array([[x.transform.rotation.x, x.transform.rotation.y, x.transform.rotation.z, x.transform.rotation.w] for x in ts]))

    tree = TfTree()
    clouds = {stamp(m.header): m for _, m in msgs[f"{ns}/keypoints"]}
    tf_stamps, worst = [], 0.0
    # in the order written: a new skeleton's /tf_static (other link lengths) holds from its frame on
    for _, dynamic, m in sorted([(t, 0, m) for t, m in msgs["/tf_static"]] + [(t, 1, m) for t, m in msgs.get("/tf", [])],
                                key=lambda e: e[:2]):
        tree.add(transforms(m))
        if not dynamic:
            continue
        s = stamp(m.transforms[0].header)
        tf_stamps.append(s)
        worst = max(worst, float(np.abs(tree.positions([f"kp_{k}" for k in KEYPOINTS]) - cloud(clouds[s])).max()))
    return worst, tf_stamps, {s for s, c in clouds.items() if c.width > 0}
