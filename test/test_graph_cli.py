"""vmocap play / record / launch / process as a user runs them: /clock and start offset,
SIGTERM finalizes the recorder's MCAP, the camera node replays a bag, a truncated input bag
gives a clear error and --recover processes what is readable."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from graph_helpers import REPO, domain_env, stop, synthetic_bag, vmocap, wait_for, wait_ready, write_config

from vmocap_core.bag import BagReader
from vmocap_core.bag import messages as M


def test_play_clock_offset_and_record_sigterm(tmp_path: Path) -> None:
    bag = tmp_path / "in.mcap"
    synthetic_bag(bag, frames=20, images=False)
    env = domain_env(11)
    out = tmp_path / "rec.mcap"
    rec = vmocap(["record", "-o", str(out), "/vmocap/cam0/camera_info", "/clock"], env)
    start_at = time.time() + 4.0  # --start-at: nothing is sent before that wall-clock time
    try:
        play = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--rate", "0", "--start-offset", "0.3",
                               "--topics", "/vmocap/cam0/camera_info", "--expect", "/vmocap/cam0/camera_info", "/clock",
                               "--wait-subscribers", "30", "--start-at", str(start_at)],
                              env=env, capture_output=True, text=True, timeout=60)
        assert play.returncode == 0, play.stdout + play.stderr
        assert wait_for(lambda: Path(str(out) + ".partial").exists(), 5)
    finally:
        log = stop(rec, signal.SIGTERM)
    assert rec.returncode == 0, log
    assert out.exists() and not Path(str(out) + ".partial").exists()
    with BagReader(out) as r:
        infos = [M.stamp_ns(m.decode()) for m in r.messages(["/vmocap/cam0/camera_info"])]
        received = [m.log_time_ns for m in r.messages(["/vmocap/cam0/camera_info"])]
        clocks = [M.stamp_ns(m.decode()["clock"]) for m in r.messages(["/clock"])]
    t0 = 1_000_000_000_000
    expected = [t0 + int(round(k * 1e9 / 30)) for k in range(20) if k * 1e9 / 30 >= 0.3e9]
    assert sorted(infos) == expected  # nothing before the offset, nothing lost after it
    assert min(clocks) >= t0 + 0.3e9 and max(clocks) == expected[-1]
    assert min(received) >= start_at * 1e9


def test_camera_node_replays_bag_and_launcher_sigterm_flushes(tmp_path: Path) -> None:
    bag = tmp_path / "cams.mcap"
    rig, rig_path, kps = synthetic_bag(bag, frames=12, images=True, size=(64, 48))
    out = tmp_path / "cams_out.mcap"
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_camera", "vmocap_recorder"], mode="single_process",
                       output=out, extra={"vmocap_camera": {"uri": str(bag), "rate": 4.0},
                                          "vmocap_recorder": {"topics": ["/vmocap/cam1/image_raw", "/vmocap/cam1/camera_info"]}})
    env = domain_env(12)
    launch = vmocap(["launch", str(cfg)], env)
    try:
        # the camera plays once the recorder subscribes (12 frames at 4x = 0.1 s): wait for the
        # nodes (tens of seconds on one loaded core), the play, then a margin
        assert wait_ready(launch, ["vmocap_camera", "vmocap_recorder"], 90), "".join(launch._lines)
        assert wait_for(lambda: "playing" in "".join(launch._lines), 30), "".join(launch._lines)
        time.sleep(2.0)
    finally:
        log = stop(launch, signal.SIGTERM)
    assert launch.returncode == 0, log
    assert out.exists() and not Path(str(out) + ".partial").exists(), log
    with BagReader(bag) as r:
        src = {M.stamp_ns(d := m.decode()): M.image_array(d) for m in r.messages(["/vmocap/cam1/image_raw"])}
    with BagReader(out) as r:
        got = [m.decode() for m in r.messages(["/vmocap/cam1/image_raw"])]
        infos = [m.decode() for m in r.messages(["/vmocap/cam1/camera_info"])] if "/vmocap/cam1/camera_info" in r.topics else []
    assert got, log
    for d in got:  # every recorded frame is bit-identical to the bag's frame of that stamp
        assert np.array_equal(M.image_array(d), src[M.stamp_ns(d)])
    assert infos and M.camera_info_mismatch(infos[0], rig["cam1"]) is None


def test_process_cli_truncated_bag(tmp_path: Path) -> None:
    bag = tmp_path / "in.mcap"
    _, rig_path, kps = synthetic_bag(bag, frames=40)  # what is readable is long enough to track
    data = bag.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_markers"])
    base = [sys.executable, "-m", "vmocap_core.cli", "process", str(cut), "-o", str(tmp_path / "o.mcap"), "--config", str(cfg), "--no-progress"]
    r = subprocess.run(base, capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0 and str(cut) in (r.stderr + r.stdout) and "truncated" in (r.stderr + r.stdout)
    r = subprocess.run(base + ["--recover", "--json"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    import json

    stats = json.loads(r.stdout.strip().splitlines()[-1])
    assert 3 <= stats["frames"] < 40 and stats["tracking"] > 0, stats


def test_process_cli_says_why_nothing_was_tracked(tmp_path: Path) -> None:
    """A recording in which no subject ever initializes (three of four cameras turned since
    calibration) is an empty result: `vmocap process` exits 1 and says why, as the graph's
    WARN does; --offline stops with the same reason."""
    from test_init_diagnosis import _miscalibrated

    bag = tmp_path / "in.mcap"
    _, rig_path, kps = synthetic_bag(bag, frames=30)
    wrong = _miscalibrated(rig_path, tmp_path / "wrong.rig.yaml")
    cfg = write_config(tmp_path / "g.yaml", wrong, kps, ["vmocap_markers"])
    base = [sys.executable, "-m", "vmocap_core.cli", "process", str(bag), "--config", str(cfg), "--no-progress"]
    for k, extra in enumerate(([], ["--offline"])):
        r = subprocess.run(base + extra + ["-o", str(tmp_path / f"o{k}.mcap")], capture_output=True, text=True, cwd=REPO)
        assert r.returncode != 0 and "no frame set of 30 tracked" in r.stderr, (extra, r.stdout, r.stderr)
        assert "views disagree" in r.stderr or "do not fit one skeleton" in r.stderr, r.stderr


def test_silent_camera_graph_continues_and_reports(tmp_path: Path) -> None:
    """cam3's heatmaps never arrive: every frame set still comes out (3 views >= min 2) and
    vmocap_markers lists cam3 as silent on /diagnostics."""
    bag = tmp_path / "in.mcap"
    rig, rig_path, kps = synthetic_bag(bag, frames=30)
    out = tmp_path / "out.mcap"
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"],
                       mode="single_process", output=out,
                       extra={"vmocap_markers": {"queue_depth": 100, "silent_after_ms": 200.0, "feedback_timeout_ms": 5000.0},
                              "vmocap_skeleton": {"queue_depth": 100}})
    env = domain_env(13)
    launch = vmocap(["launch", str(cfg)], env)
    topics = [f"/vmocap/pcm/{c}/{k}" for c in ("cam0", "cam1", "cam2") for k in ("heatmaps", "camera_info")]
    try:
        assert wait_for(lambda: Path(str(out) + ".partial").exists() or launch.poll() is not None, 60.0)
        import time

        time.sleep(1.0)
        play = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--topics", *topics,
                               "--expect", *topics, "/vmocap/pcm/cam3/heatmaps", "--wait-subscribers", "60"],
                              env=env, capture_output=True, text=True, timeout=90)
        assert play.returncode == 0, play.stdout + play.stderr
        import time

        time.sleep(4.0)  # processing backlog + at least one diagnostics period
    finally:
        log = stop(launch)
    assert launch.returncode == 0, log
    with BagReader(out) as r:
        n_kp = r.message_counts.get("/vmocap/keypoints", 0)
        status = [s for m in r.messages(["/diagnostics"]) for s in m.decode()["status"] if s["name"] == "vmocap_markers"]
    assert n_kp == 30, log
    last = {v["key"]: v["value"] for v in status[-1]["values"]}
    assert "cam3" in last["silent"] and last["frames"] == "30"
    level = status[-1]["level"][0] if isinstance(status[-1]["level"], (bytes, bytearray)) else int(status[-1]["level"])
    assert level == 1 and "silent view: cam3" in status[-1]["message"], status[-1]["message"]


def test_markers_falling_behind_warn_and_say_how_many_were_dropped(tmp_path: Path) -> None:
    """Heatmaps played 10x faster than vmocap_markers takes them with a queue of 1: frame sets
    are dropped (freshness over completeness) and its /diagnostics turn WARN saying how many,
    from the gaps in the stamps of what it processed (wherever they were lost)."""
    bag = tmp_path / "in.mcap"
    rig, rig_path, kps = synthetic_bag(bag, frames=60)
    out = tmp_path / "out.mcap"
    cfg = write_config(tmp_path / "g.yaml", rig_path, kps, ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"],
                       mode="single_process", output=out,
                       extra={"vmocap_markers": {"queue_depth": 1, "feedback_timeout_ms": 5000.0}})
    env = domain_env(14)
    launch = vmocap(["launch", str(cfg)], env)
    topics = [f"/vmocap/pcm/{c}/{k}" for c in ("cam0", "cam1", "cam2", "cam3") for k in ("heatmaps", "camera_info")]
    try:
        assert wait_for(lambda: Path(str(out) + ".partial").exists() or launch.poll() is not None, 60.0)
        time.sleep(1.0)
        play = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--topics", *topics, "--rate", "10",
                               "--expect", *topics, "--wait-subscribers", "60"], env=env, capture_output=True, text=True, timeout=90)
        assert play.returncode == 0, play.stdout + play.stderr
        time.sleep(2.5)  # at least one diagnostics period after the drops (the WARN is held 5 s)
    finally:
        log = stop(launch)
    assert launch.returncode == 0, log
    with BagReader(out) as r:
        status = [s for m in r.messages(["/diagnostics"]) for s in m.decode()["status"] if s["name"] == "vmocap_markers"]
    last = {v["key"]: v["value"] for v in status[-1]["values"]}
    missing, frames = int(last["missing"]), int(last["frames"])
    # lost in DDS's queue of 1 or in the node's own: every stamp gap counts
    assert missing > 0 and frames + missing <= 60, last
    warned = [s["message"] for s in status if "falling behind" in s["message"]]
    assert warned and f"({missing} in all" in warned[-1], [s["message"] for s in status]


def test_process_image_bag_runs_the_cnn(tmp_path: Path) -> None:
    """A bag with camera images only: `vmocap process` runs the CNN per synchronized frame set
    (random textures: no person, so nothing is tracked, but every frame set goes through)."""
    import pytest

    try:
        from vmocap_core.pcm.fetch import model_path

        model_path("pose_landmark_full")
        model_path("pose_detection")
    except Exception as exc:  # noqa: BLE001 - models not built on this machine
        pytest.skip(f"PCM models not available ({exc})")
    from vmocap_core.apps.process import process_bag
    from vmocap_core.bag.synth import write_synthetic_bag
    from vmocap_core.pcm.synthetic import benchmark_rig

    rig = benchmark_rig(width=160, height=120)
    bag = tmp_path / "imgs.mcap"
    write_synthetic_bag(bag, rig, np.zeros((5, 25, 3)), np.ones(25, bool), 5, images=True, pcm=False)
    stats = process_bag(bag, tmp_path / "o.mcap", rig, config={"fps": 30.0}, progress=False)
    assert stats["frames"] == 5 and stats["pcm"].startswith("blazepose") and stats["sync"]["complete"] == 5
    with BagReader(tmp_path / "o.mcap") as r:
        assert r.message_counts["/vmocap/keypoints"] == 5
    # an all-black image and one of another size mid-stream are left out of their frame sets
    # and counted; a rig whose size no image has stops it, naming the camera
    from vmocap_core.bag import BagWriter
    from vmocap_core.errors import BagError

    odd = tmp_path / "odd.mcap"
    with BagReader(bag) as r, BagWriter(odd) as w:
        for m in r.messages():
            d = m.decode()
            if m.type == "sensor_msgs/msg/Image":
                k = round((M.stamp_ns(d) - r.start_ns) * 30 / 1e9)
                cam = d["header"]["frame_id"]
                if (cam, k) == (rig.names[1], 2):
                    d = M.image_msg(np.zeros_like(M.image_array(d)), M.stamp_ns(d), cam)
                elif (cam, k) == (rig.names[2], 3):
                    d = M.image_msg(M.image_array(d)[:60], M.stamp_ns(d), cam)
            w.write(m.topic, m.type, d, m.log_time_ns)
    stats = process_bag(odd, tmp_path / "o2.mcap", rig, config={"fps": 30.0}, progress=False)
    assert stats["frames"] == 5 and stats["bad_images"] == {rig.names[0]: 0, rig.names[1]: 1, rig.names[2]: 1, rig.names[3]: 0}
    with pytest.raises(BagError, match=f"{rig.names[0]}: images of 160x120, the rig's camera is 320x240"):
        process_bag(bag, tmp_path / "o3.mcap", benchmark_rig(width=320, height=240), config={"fps": 30.0}, progress=False)
