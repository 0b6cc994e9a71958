"""Per-camera PCM workers on one "host", the tracker on another: two network namespaces joined by
a veth pair (10.213.0.1 and .2, nothing else reachable), DDS over UDP between them.

Host A runs the camera node with the PCM workers of cam0-cam2 in one process (images stay in it)
and cam3's worker as a process of its own; host B runs markers, skeleton and recorder. Killing
cam3's worker leaves the tracker going on three views with cam3 reported silent; started again,
its views are used again."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import REPO, domain_env, stop, synthetic_bag, wait_ready, write_config

from vmocap_core.bag import BagReader

SUBNET = "10.213.0"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def hosts():
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    a, b = f"vmocapA{os.getpid()}", f"vmocapB{os.getpid()}"
    try:
        _ip("netns", "add", a)
        _ip("netns", "add", b)
    except subprocess.CalledProcessError as exc:
        pytest.skip(f"cannot create network namespaces here: {exc.stderr.decode().strip()}")
    try:
        va, vb = f"va{os.getpid() % 100000}", f"vb{os.getpid() % 100000}"
        _ip("link", "add", va, "type", "veth", "peer", "name", vb)
        _ip("link", "set", va, "netns", a)
        _ip("link", "set", vb, "netns", b)
        for ns, dev, host in ((a, va, 1), (b, vb, 2)):
            _ip("-n", ns, "addr", "add", f"{SUBNET}.{host}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up", "multicast", "on")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", dev)
        yield a, b
    finally:
        subprocess.run(["ip", "netns", "del", a], capture_output=True)
        subprocess.run(["ip", "netns", "del", b], capture_output=True)


def _launch(ns: str, cfg: Path, nodes: list[str], env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg),
                             "--nodes", *nodes], env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


# a subscriber on the tracker's host that says when the first joint_states arrived
_WATCH = """
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState
rclpy.init()
node = rclpy.create_node("hosts_test_watch")
got = []
node.create_subscription(JointState, "/vmocap/joint_states", got.append, qos_profile_sensor_data)
while not got:
    rclpy.spin_once(node, timeout_sec=0.5)
print("READY hosts_test_watch", flush=True)
"""


def _timeline(out: Path) -> tuple[list[tuple[int, str]], list[int]]:
    """(receive time, vmocap_markers' silent list) of each diagnostics message and the receive
    times of joint_states, from the recording."""
    with BagReader(out) as r:
        silent = [(m.log_time_ns, {v["key"]: v["value"] for v in s["values"]}["silent"]) for m in r.messages(["/diagnostics"])
                  for s in m.decode()["status"] if s["name"] == "vmocap_markers"]
        js = [m.log_time_ns for m in r.messages(["/vmocap/joint_states"])]
    return silent, js


def test_pcm_workers_on_another_host_and_a_worker_that_dies_and_returns(tmp_path: Path, hosts) -> None:
    host_a, host_b = hosts
    bag = tmp_path / "cams.mcap"
    rig, rig_path, kps = synthetic_bag(bag, frames=60, images=True, size=(320, 240))
    out = tmp_path / "out.mcap"
    workers = [f"vmocap_pcm_{c}" for c in rig.names]
    # the synthetic heatmaps' noise (6 px, false peaks, swaps) is harsher than the CNN's: a wider
    # skeleton-fit bound lets three views re-initialize too (this test is about the layout)
    extra = {"vmocap_camera": {"uri": str(bag), "loop": True, "restamp": True},
             "vmocap_skeleton": {"init_max_fit_error_m": 0.08},
             "vmocap_markers": {"sync_tolerance_ms": 8.0, "silent_after_ms": 300.0, "feedback_timeout_ms": 1000.0},
             **{w: {"cameras": [c], "threads": 1} for w, c in zip(workers, rig.names)}}
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_camera", *workers, "vmocap_markers", "vmocap_skeleton",
                                                             "vmocap_recorder"], output=out, extra=extra)
    text = cfg.read_text().replace("fastdds_shm.xml", "fastdds_udp.xml")
    cfg.write_text(text)
    env = domain_env(31)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET", FASTRTPS_DEFAULT_PROFILES_FILE=str(REPO / "config" / "fastdds_udp.xml"))
    env_a = dict(env, ROS_STATIC_PEERS=f"{SUBNET}.2")
    env_b = dict(env, ROS_STATIC_PEERS=f"{SUBNET}.1")
    tracker = _launch(host_b, cfg, ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"], env_b)
    cams = _launch(host_a, cfg, ["vmocap_camera", *workers[:3]], env_a)
    worker = _launch(host_a, cfg, [workers[3]], env_a)
    watch = subprocess.Popen(["ip", "netns", "exec", host_b, sys.executable, "-c", _WATCH], env=env_b,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    procs = [tracker, cams, worker, watch]
    try:
        assert wait_ready(tracker, ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"], 90), "".join(tracker._lines)
        assert wait_ready(cams, ["vmocap_camera"], 90) and wait_ready(worker, [workers[3]], 90)
        # discovery across the veth, then tracking on 4 views for a while (a slow machine takes
        # tens of seconds to the first output)
        assert wait_ready(watch, ["hosts_test_watch"], 120), "no joint_states within 120 s"
        time.sleep(3.0)
        stop(worker)  # cam3's worker dies
        time.sleep(4.0)
        worker = _launch(host_a, cfg, [workers[3]], env_a)  # ... and comes back
        procs[2] = worker
        assert wait_ready(worker, [workers[3]], 90)
        time.sleep(6.0)
    finally:
        logs = [stop(p) for p in reversed(procs)]
    assert tracker.returncode == 0, logs[-1]
    silent, js = _timeline(out)
    assert len(js) > 60, "tracked over the network"
    # the longest stretch of diagnostics naming cam3 silent (a loaded machine may also report a
    # short one while the worker lags), and the first report after it without cam3
    runs, start = [], None
    for (t, names), nxt in zip(silent, silent[1:] + [(None, None)]):
        if "cam3" in names and start is None:
            start = t
        if start is not None and (nxt[1] is None or "cam3" not in nxt[1]):
            runs.append((start, nxt[0]))
            start = None
    assert runs, "the dead worker's camera is reported missing"
    gone, back = max(runs, key=lambda r: (r[1] or silent[-1][0]) - r[0])
    assert back is not None, "the returning worker is used again"
    assert back - gone >= 2e9, "cam3 was silent while its worker was down"
    during = np.array([t for t in js if gone <= t <= back])
    after = np.array([t for t in js if t > back])
    # tracking went on with three views: output in most seconds of it, not a stall waiting for
    # cam3. No rate is asserted: with the slower class emulated (one loaded core for the camera,
    # 4 workers and the tracker) the worker's restart leaves every stage seconds-long gaps
    span = (back - gone) * 1e-9
    covered = len(np.unique((during - gone) // 1_000_000_000)) / np.ceil(span)
    print(f"joint_states on 3 views: {len(during) / span:.1f} Hz over {span:.1f} s, {covered:.0%} of its seconds; "
          f"after: {len(after)} messages")
    assert len(during) >= 2 * span and covered >= 0.5, (len(during), span, covered)
    assert len(after) >= 10, "tracking on 4 views again"
