"""`vmocap bench faults --json` on a subset of its faults (damaged bags and a damaged chunk through
`vmocap process` and `vmocap play`; `vmocap process` writing onto its input, onto an existing
output, killed while writing; a config the rig cannot satisfy; the person leaving every view and
returning through the node graph; an Aravis Fake camera unplugged and back): the JSON has the
documented shape and every fault tried is survived and diagnosed (camera_late: cam2's images two
frame sets late, found by vmocap_markers' periodic time-offset probe). Fast forms of two more: the launcher's restart policy on a killed
recorder, and vmocap_pcm with the CNN leaving out black and wrong-size images."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from graph_helpers import REPO, domain_env, synthetic_bag, vmocap, write_config

FAULTS = ["truncated_bag", "corrupted_bag", "damaged_chunk", "output_is_input", "output_exists", "output_killed",
          "min_cameras_above_rig", "person_leaves", "heatmaps_nan", "camera_late"]


def test_bench_faults_subset_survived_and_diagnosed(tmp_path: Path) -> None:
    env = domain_env(41)
    run = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "bench", "faults", "--json", "--modes", "default",
                          "--only", *FAULTS, "--workdir", str(tmp_path)], env=env, cwd=REPO,
                         capture_output=True, text=True, timeout=360)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    names = set(out["faults"])
    assert names == {"truncated_bag:process", "truncated_bag:play", "corrupted_bag:process", "corrupted_bag:play",
                     "damaged_chunk:process", "damaged_chunk:play", "output_is_input:path", "output_is_input:symlink",
                     "output_is_input:hardlink", "output_exists", "output_killed:new", "output_killed:replace",
                     "min_cameras_above_rig", "person_leaves:default", "heatmaps_nan:default", "camera_late:default"}, names
    assert out["tried"] == len(names)
    assert out["survived"] == sum(r["survived"] for r in out["faults"].values())
    for name, r in out["faults"].items():
        assert isinstance(r["survived"], bool) and isinstance(r["diagnosed"], bool) and isinstance(r["frames_lost"], int)
        assert r["survived"] and r["diagnosed"], (name, r)
    # damage at 60 % of the file: the frame sets before it are read, those after it lost
    for name in ("truncated_bag:process", "corrupted_bag:play"):
        assert 0 < out["faults"][name]["frames_lost"] < 150, out["faults"][name]
    # one damaged chunk of three: the chunks before and after it are read
    for name in ("damaged_chunk:process", "damaged_chunk:play"):
        assert 0 < out["faults"][name]["frames_lost"] < 75, out["faults"][name]
    assert out["faults"]["output_killed:new"]["output_after"] == "none", out["faults"]["output_killed:new"]
    assert out["faults"]["output_killed:replace"]["output_after"] == "earlier file", out["faults"]["output_killed:replace"]
    assert out["faults"]["min_cameras_above_rig"]["launch_exit"] == 2, out["faults"]["min_cameras_above_rig"]
    person = out["faults"]["person_leaves:default"]
    assert person["tracked_after_return"] > 0 and person["output_while_absent"] < 10, person


def test_bench_faults_aravis_camera_unplugged_and_back(tmp_path: Path) -> None:
    """`vmocap bench faults --only aravis_reconnect`: the camera node on Aravis' in-process Fake
    cameras (GigE/USB3 never enabled); cam1 is lost for 3 s: reported, reopened, the others go on."""
    from vmocap_core.cameras import aravis as arv

    if not arv.available():
        pytest.skip("Aravis 0.8 / PyGObject not installed")
    run = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "bench", "faults", "--json", "--only", "aravis_reconnect",
                          "--workdir", str(tmp_path)], env=domain_env(43), cwd=REPO, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    r = out["faults"]["aravis_reconnect"]
    assert r["survived"] and r["diagnosed"], r
    assert r["disconnects"] == "{'cam0': 0, 'cam1': 1, 'cam2': 0, 'cam3': 0}", r
    assert r["reconnects"] == r["disconnects"], r
    assert r["frames_lost"] <= 2 and r["back_after_s"] < 2.0, r


def test_launcher_restarts_a_killed_node_within_its_limit(tmp_path: Path) -> None:
    """vmocap_launch.restart: a recorder killed with SIGKILL is reported and started again (its
    killed file kept aside, not overwritten); killed once more than restart_limit allows, the
    launcher stops the graph as without the option."""
    _, rig_path, kps = synthetic_bag(tmp_path / "s.mcap", frames=2)
    out = tmp_path / "rec.mcap"
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_recorder"], output=out)
    raw = yaml.safe_load(cfg.read_text())
    raw["vmocap_launch"].update(restart=["vmocap_recorder"], restart_limit=1)
    cfg.write_text(yaml.safe_dump(raw))
    launch = vmocap(["launch", str(cfg)], domain_env(44))
    lines: list[str] = []

    def wait_line(text: str, timeout: float = 30.0) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            line = launch.stdout.readline()
            lines.append(line)
            if text in line:
                return line
            if not line and launch.poll() is not None:
                break
        raise AssertionError(f"no {text!r} in:\n{''.join(lines)}")

    try:
        first = wait_line("processes: ")
        pid = int(first.rsplit("[", 1)[1].split("]")[0])
        wait_line("READY vmocap_recorder")
        os.kill(pid, signal.SIGKILL)
        again = wait_line("vmocap_recorder exited with -9; restarted as vmocap_recorder[")
        pid2 = int(again.split("restarted as vmocap_recorder[")[1].split("]")[0])
        assert pid2 != pid and "(restart 1 of 1)" in again
        wait_line("READY vmocap_recorder")
        assert (tmp_path / "rec.killed1.mcap.partial").exists()  # the killed recording, kept for --recover
        os.kill(pid2, signal.SIGKILL)
        wait_line("vmocap_recorder exited with -9; stopping the graph (restarted 1 times already)")
        assert launch.wait(timeout=30) == 256 - 9
    finally:
        if launch.poll() is None:
            launch.send_signal(signal.SIGINT)
            launch.wait(timeout=30)


def test_pcm_node_leaves_out_black_and_wrong_size_images(tmp_path: Path, monkeypatch) -> None:
    """The fast form of the image faults (the bench runs them through the whole graph): the
    real vmocap_pcm with the CNN on three frame sets of the Pose2Sim demo, cam02's image all
    black, then at half size, then intact. Its heatmaps of cam02 say nothing for the first two
    (presence 0, every channel NaN), the others' views are the CNN's, and the node WARNs
    naming cam02 and the reason."""
    import numpy as np

    from vmocap_core import graph_config
    from vmocap_core.apps.demo.data import bag_frame_sets
    from vmocap_core.bag import messages as M
    from vmocap_ros.bench import fault_harness as H

    demo = H.demo_bag(tmp_path / "demo.mcap", 3)
    if demo is None:
        pytest.skip("the Pose2Sim demo is not cached (make demo)")
    rig, rig_path = demo
    for k, v in domain_env(45).items():
        monkeypatch.setenv(k, v)
    from vmocap_ros.common import init_rclpy, msg_class, qos
    from vmocap_ros.nodes.pcm import PcmNode

    cfg = H.write_config(tmp_path / "g.yaml", rig_path, [""], ["vmocap_pcm"], "single_process", tmp_path / "x.mcap",
                         extra={"vmocap_pcm": {"source": "model", "model": "blazepose", "queue_depth": 10}})
    rclpy = init_rclpy()
    node = PcmNode(graph_config.load(cfg))
    probe = rclpy.create_node("test_probe")
    got: dict[str, list[np.ndarray]] = {}
    for cam in rig.names:
        probe.create_subscription(msg_class("sensor_msgs/msg/Image"), f"/vmocap/pcm/{cam}/heatmaps",
                                  lambda m, c=cam: got.setdefault(c, []).append(
                                      M.image_array({"encoding": m.encoding, "height": m.height, "width": m.width,
                                                     "step": m.step, "data": bytes(m.data)})), qos(10))
    try:
        def spin(until, timeout: float = 10.0) -> None:
            end = time.monotonic() + timeout
            while not until() and time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.02)
                rclpy.spin_once(probe, timeout_sec=0.02)

        spin(lambda: all(node.count_subscribers(f"/vmocap/pcm/{c}/heatmaps") for c in rig.names))
        sets = list(bag_frame_sets(tmp_path / "demo.mcap", rig))
        for k, (stamp, images) in enumerate(sets):
            images = list(images)
            if k == 0:
                images[1] = np.zeros_like(images[1])
            elif k == 1:
                images[1] = np.ascontiguousarray(images[1][::2, ::2])
            for cam, img in zip(rig.names, images):
                node._on_image(cam, M.image_msg(img, stamp + 1, cam))
            if k < 2:
                assert any("cam02: image all black" in p or "the rig is calibrated at" in p
                           for p in node.problems.values()), node.problems
        spin(lambda: len(got.get("cam02", [])) >= 3 and all(len(got.get(c, [])) >= 3 for c in rig.names))
    finally:
        probe.destroy_node()
        node.destroy_node()
        rclpy.shutdown()
    assert node.bad_images["cam02"] == 2 and sum(node.bad_images.values()) == 2, node.bad_images
    assert "cam02: image 540x960, the rig is calibrated at 1080x1920" in node.problems["image:cam02"]
    J = 25  # BlazePose's channels: the 25 keypoints, then the presence, then the landmark visibility
    assert got["cam02"][0].shape[-1] == J + 2
    for k in range(3):
        presence = {c: float(np.nanmax(got[c][k][..., J])) for c in rig.names}
        blank = bool(np.isnan(got["cam02"][k][..., :J]).all())
        assert blank == (k < 2) and (presence["cam02"] == 0.0) == (k < 2), (k, presence)
        assert all(presence[c] > 0.5 for c in ("cam01", "cam03", "cam04")), (k, presence)
