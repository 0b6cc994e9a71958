"""The camera-side faults of `vmocap bench faults` (faults.py): bad images through the
CNN graph, and an Aravis camera unplugged and plugged back. What each fault does and what
survived / diagnosed mean: docs/faults.md."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import time
from pathlib import Path

from . import fault_harness as H

CAMERA_FAULTS = ["aravis_reconnect"]  # the camera node alone, on Aravis' Fake cameras (no launch mode)
IMAGE_FAULTS = ["image_black", "image_white", "image_size_midstream", "image_size_wrong"]
IMAGE_FRAMES, IMAGE_WINDOW, IMAGE_CAMERA = 45, range(15, 30), "cam02"  # Pose2Sim demo frame sets; the bad ones


def image_fault(name: str, mode: str, work: Path, bag: Path, rig_path: Path, env: dict[str, str]) -> dict:
    """The graph (camera node playing the Pose2Sim demo's JPEGs at 0.05 x real time, the CNN in
    vmocap_pcm, markers, skeleton, recorder) with IMAGE_CAMERA's images all black, all white, or
    at half size in IMAGE_WINDOW (image_size_wrong: in every frame set)."""
    from vmocap_core.apps.demo.runs import TRACKER_SETTINGS
    from vmocap_core.graph_config import stage_sections

    how = {"image_black": "black", "image_white": "white"}.get(name, "half")
    window = range(IMAGE_FRAMES) if name == "image_size_wrong" else IMAGE_WINDOW
    src = H.alter_images(bag, work / f"{name}.mcap", IMAGE_CAMERA, window, how)
    out = work / f"{name}_{mode}_out.mcap"
    nodes = ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    stages = stage_sections(TRACKER_SETTINGS)
    extra = {"/**": {"pcm_keypoints": [""], **stages["/**"]},
             "vmocap_camera": {"source": "bag", "uri": str(src), "rate": 0.05, "loop": False, "wait_subscribers": 60.0},
             "vmocap_pcm": {"source": "model", "model": "blazepose", "min_cameras": 2, "silent_after_ms": 5000.0,
                            "queue_depth": 50},
             "vmocap_markers": {"min_cameras": 2, "silent_after_ms": 5000.0, "feedback_timeout_ms": 2000.0,
                                "queue_depth": 100, **stages["vmocap_markers"]},
             "vmocap_skeleton": {"queue_depth": 100, **stages["vmocap_skeleton"]}}
    cfg = H.write_config(work / f"{name}_{mode}.yaml", rig_path, [""], nodes, H.launch_mode(mode), out, groups=[nodes[:4]], extra=extra)
    launch = H.Proc.start(H.vmocap_cmd("launch", str(cfg)), env)
    try:
        H.wait_ready(launch, nodes, timeout=180.0)
        if not H.wait_for(lambda: "playing" in launch.text, 120.0):
            raise RuntimeError(f"the camera node did not start playing:\n{launch.text[-3000:]}")
        time.sleep(IMAGE_FRAMES / H.DEMO_FPS / 0.05 + 10.0)  # the playback, then the last frame sets through the CNN
    finally:
        rc = launch.stop()
    o = H.Outputs.read(out)
    got = {round(st * H.DEMO_FPS / 1e9) for _, st in o.joint_states}
    first = min(got, default=IMAGE_FRAMES)
    lost = sum(k not in got for k in range(first, IMAGE_FRAMES))
    during = sum(k in got for k in window)
    after = sum(k in got for k in range(window.stop, IMAGE_FRAMES))
    reason = "the rig is calibrated at" if how == "half" else f"image all {how}"
    pcm_warned = any(lvl >= 1 and f"{IMAGE_CAMERA}: image " in msg and reason in msg
                     for _, lvl, msg, _ in o.diag.get("vmocap_pcm", []))
    cam_warned = o.warned("vmocap_camera", f"{IMAGE_CAMERA}: frames of")
    bad = [ast.literal_eval(v["bad_images"]).get(IMAGE_CAMERA, 0) for _, _, _, v in o.diag.get("vmocap_pcm", [])
           if "bad_images" in v]
    # tracking from the other cameras during the bad images, and after them
    return {"survived": rc == 0 and bool(got) and during >= 0.5 * sum(k >= first for k in window)
            and (after >= 0.5 * (IMAGE_FRAMES - window.stop) if window.stop < IMAGE_FRAMES else True),
            "diagnosed": pcm_warned and (cam_warned or how != "half"), "frames_lost": lost, "launcher_rc": rc,
            "frames_out": len(got), "first_tracked": first, "tracked_during": during, "tracked_after": after,
            "images_not_used": max(bad, default=0), "camera_warned": cam_warned,
            # vmocap_markers' per-camera reprojection residual (camera_check), its highest over
            # the run: how far cam02's heatmap peaks lay from the markers (None: no figure)
            "residual_px_cam02_max": max((float(v[f"residual_px:{IMAGE_CAMERA}"]) for _, _, _, v in o.diag.get("vmocap_markers", [])
                                          if f"residual_px:{IMAGE_CAMERA}" in v), default=None),
            "markers_warned_cam02": o.warned("vmocap_markers", IMAGE_CAMERA)}


def aravis_fault(work: Path, env: dict[str, str]) -> dict:
    """vmocap_camera with 4 Aravis Fake cameras (15 fps, mono8 512x512); cam1 unplugged after
    4 s for 3 s (fault_harness.aravis_camera_run). survived: cam1 delivers again after it is
    back and the other cameras go on meanwhile; diagnosed: a WARN naming cam1 as disconnected
    while it is away and one saying it reconnected. frames_lost: frames of the other cameras
    missing by their stamps (cam1's frames while unplugged are reported apart: camera_away_s,
    its longest gap between two frames)."""
    import numpy as np

    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm.synthetic import benchmark_rig

    fps, cam, after, away, total = 15.0, "cam1", 4.0, 3.0, 12.0
    rig_path = work / "fake512.rig.yaml"
    save_rig(benchmark_rig(width=512, height=512), rig_path)
    extra = {"vmocap_camera": {"source": "aravis", "uri": f"Fake_1?fps={fps:g}&pixel_format=Mono8&mono=true",
                               "rate": 0.0, "reconnect_s": 0.5, "reconnect_attempts": 20}}
    cfg = H.write_config(work / "aravis.yaml", rig_path, [], ["vmocap_camera"], "single_process", work / "unused.mcap",
                         extra=extra)
    run = subprocess.run([sys.executable, "-m", "vmocap_ros.bench.fault_harness", "aravis", str(cfg), cam, str(after), str(away),
                          str(total)], env=env, cwd=H.REPO, capture_output=True, text=True, timeout=120)
    if run.returncode != 0:
        raise RuntimeError(f"the camera node's run failed (rc {run.returncode}):\n{run.stderr[-3000:]}")
    rec = json.loads(run.stdout.strip().splitlines()[-1])
    unplug, plug = rec["marks"]["unplug"], rec["marks"]["plug"]
    by_cam: dict[str, list[tuple[int, int]]] = {}
    for t, c, st in rec["frames"]:
        by_cam.setdefault(c, []).append((t, st))
    lost, during = 0, {}
    for c, fr in by_cam.items():
        if c == cam:
            continue
        st = np.sort(np.array([s for _, s in fr], dtype=np.int64))
        d = np.diff(st)
        period = float(np.median(d)) if d.size else 1e9 / fps
        lost += int(sum(round(x / period) - 1 for x in d if x > 1.5 * period))
        during[c] = sum(unplug <= t <= plug for t, _ in fr)
    mine = by_cam.get(cam, [])
    back = [t for t, _ in mine if t > plug]
    msgs = [(t, lvl, m) for t, lvl, m, _ in rec["diags"]]
    warned_gone = any(lvl >= 1 and f"{cam}: disconnected" in m for t, lvl, m in msgs if unplug <= t <= plug + 1e9)
    warned_back = any(lvl >= 1 and f"{cam}: reconnected" in m for t, lvl, m in msgs if t > plug)
    last = rec["diags"][-1][3] if rec["diags"] else {}
    return {"survived": len(back) >= fps and all(n >= 0.8 * fps * away for n in during.values()) and len(during) == 3,
            "diagnosed": warned_gone and warned_back, "frames_lost": lost,
            "back_after_s": round((back[0] - plug) / 1e9, 2) if back else None,
            "camera_away_s": round(float(np.diff(sorted(t for t, _ in mine)).max(initial=0)) / 1e9, 2), "others_frames_while_away": during,
            "frames_after_back": len(back), "disconnects": last.get("disconnects"), "reconnects": last.get("reconnects")}
