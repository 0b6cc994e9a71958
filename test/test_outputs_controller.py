"""The controller example (examples/wrist_velocity.py) as a separate process on the node
graph fed from a bag: its wrist velocities equal the difference quotients of the offline
run's keypoints; its lost-subject detection on stale stamps."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from graph_helpers import REPO, domain_env, stop, synthetic_bag, vmocap, wait_for, wait_ready, write_config

sys.path.insert(0, str(REPO / "examples"))
from wrist_velocity import WristVelocity  # noqa: E402

N = 30


def _offline_velocities(path: Path, stale_ns: int) -> dict[int, np.ndarray]:
    from vmocap_core.bag import BagReader
    from vmocap_core.bag.messages import cloud_keypoints, stamp_ns
    from vmocap_core.keypoints import INDEX
    from vmocap_core.method.skeleton import BONES

    bones = np.array([(INDEX[a], INDEX[b]) for a, b in BONES.values()])
    frames = []
    with BagReader(path) as r:
        for m in r.messages(["/vmocap/keypoints"]):
            d = m.decode()
            P = cloud_keypoints(d)[0]
            if P is not None:
                lengths = np.linalg.norm(P[bones[:, 0]] - P[bones[:, 1]], axis=-1)
                frames.append((stamp_ns(d), P[[INDEX["left_wrist"], INDEX["right_wrist"]]], lengths))
    frames.sort(key=lambda f: f[0])
    # not across a change of link lengths (the identified skeleton replacing the provisional
    # one): the controller gets a new description there and starts over
    return {t1: (p1 - p0) / ((t1 - t0) * 1e-9) for (t0, p0, l0), (t1, p1, l1) in zip(frames, frames[1:])
            if t1 - t0 <= stale_ns and np.abs(l1 - l0).max() < 1e-6}


def test_lost_subject_from_stale_stamps() -> None:
    from vmocap_core.method.skeleton import BodyDimensions, Skeleton
    from vmocap_core.outputs.urdf import JOINT_NAMES, SubjectModel, base_pose, joint_positions

    sk = Skeleton(BodyDimensions())
    ctl = WristVelocity(stale_ns=100_000_000)
    ctl.on_description(SubjectModel(sk.dims).to_xml())
    q = sk.neutral()
    period = 33_333_333
    records = []
    for k, stamp in enumerate([0, 1, 2, 10, 11]):  # frames 3..9: keypoints only (lost)
        t = stamp * period
        q[0] = 0.5 * t * 1e-9  # walking along x at 0.5 m/s
        a = sk.to_angles(q)
        if k == 3:
            for s in range(3, 10):
                records += ctl.on_frame_clock(s * period)
        records += ctl.on_state(t, "joints", (JOINT_NAMES, joint_positions(a)))
        records += ctl.on_state(t, "pose", base_pose(a))
    events = [(r["event"], r["stamp_ns"] // period) for r in records]
    assert events == [("velocity", 1), ("velocity", 2), ("lost", 6), ("found", 10), ("velocity", 11)]
    v = np.array([r["left"] for r in records if r["event"] == "velocity"])
    np.testing.assert_allclose(v, [[0.5, 0, 0]] * 3, atol=1e-9)


def test_controller_example_on_the_graph_equals_offline(tmp_path: Path) -> None:
    from vmocap_core.apps.process import process_bag
    env = domain_env(7)
    bag = tmp_path / "in.mcap"
    rig, rig_path, kps = synthetic_bag(bag, N)
    offline = tmp_path / "offline.mcap"
    stats = process_bag(bag, offline, rig, config={"fps": 30.0}, keypoints=kps, progress=False)
    assert stats["tracking"] >= 10, stats
    expected = _offline_velocities(offline, 200_000_000)

    cfg = write_config(tmp_path / "graph.yaml", rig_path, kps, ["vmocap_markers", "vmocap_skeleton"], mode="single_process",
                       extra={"vmocap_markers": {"feedback_timeout_ms": 5000.0, "queue_depth": 100},
                              "vmocap_skeleton": {"queue_depth": 100}})
    out = tmp_path / "wrists.jsonl"
    ctl = subprocess.Popen([sys.executable, str(REPO / "examples" / "wrist_velocity.py"), "--output", str(out)], env=env,
                           cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    launch = vmocap(["launch", str(cfg)], env)
    try:
        assert wait_ready(launch, ["vmocap_markers", "vmocap_skeleton"], 90.0), stop(launch)
        assert wait_ready(ctl, ["wrist_velocity"], 60.0), stop(ctl)
        assert wait_for(lambda: "CONNECTED" in "".join(ctl._lines) or ctl.poll() is not None, 60.0), stop(ctl)
        time.sleep(1.0)  # DDS matching follows discovery
        play = subprocess.run(
            [sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--rate", "2", "--wait-subscribers", "60",
             "--expect", *[f"/vmocap/pcm/{c}/{k}" for c in rig.names for k in ("heatmaps", "camera_info")]],
            env=env, capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stdout + play.stderr

        def velocities() -> int:
            return sum('"velocity"' in line for line in out.read_text().splitlines()) if out.exists() else 0

        assert wait_for(lambda: velocities() >= len(expected), 30.0), (velocities(), len(expected))
    finally:
        log_ctl = stop(ctl)
        log = stop(launch)
    assert ctl.returncode == 0 and launch.returncode == 0, log_ctl + log
    records = [json.loads(line) for line in out.read_text().splitlines()]
    got = {r["stamp_ns"]: np.array([r["left"], r["right"]]) for r in records if r["event"] == "velocity"}
    assert sorted(got) == sorted(expected) and len(got) >= 8
    worst = max(float(np.abs(got[s] - expected[s]).max()) for s in expected)
    assert worst < 1e-4, worst  # m/s: positions agree to 1e-6 m over 33 ms frames
    assert not any(r["event"] == "lost" for r in records)  # the walker is tracked to the end
