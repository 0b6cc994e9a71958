"""`vmocap bench faults [--json] [--modes ...] [--only NAME ...]`: inject faults one at a time into
real runs (MCAP bags of a synthetic subject or of the Pose2Sim demo's videos, the node graph
started by `vmocap launch`, `vmocap play`, `vmocap process`, the camera node on Aravis' Fake
cameras) and report per fault whether it was survived, whether it was
diagnosed, and the frames lost. What each fault does and what the two words mean per fault:
docs/faults.md."""

from __future__ import annotations

import argparse
import ast
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import fault_harness as H
from .faults_camera import CAMERA_FAULTS, IMAGE_FAULTS, IMAGE_FRAMES, aravis_fault, image_fault
from .faults_output import OUTPUT_FAULTS, output_fault

BAG_FAULTS = ["truncated_bag:process", "truncated_bag:play", "corrupted_bag:process", "corrupted_bag:play",
              "damaged_chunk:process", "damaged_chunk:play"]
PCM_FAULTS = ["heatmaps_nan", "heatmaps_inf", "heatmaps_negative", "person_leaves", "camera_pause", "calibration_rotated",
              "calibration_moved", "camera_late"]
GRAPH_FAULTS = ["launcher_sigint", "launcher_sigterm", "recorder_sigkill", "node_killed", "node_restarted",
                "recorder_restarted"]
# one process: killing a node kills the graph (that is recorder_sigkill), and nothing restarts it
PROCESSES_ONLY = {"node_killed", "node_restarted", "recorder_restarted"}
PCM_TOPICS = ("heatmaps", "camera_info")
PLAYERS_START_S = 8.0  # from the graph's READY to the players' common start (their start-up and discovery: 2-4 s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--modes", nargs="+", default=["default", "single_process"], choices=("default", "single_process"))
    parser.add_argument("--only", nargs="+", default=None, metavar="FAULT",
                        help=f"run only these faults (of {', '.join(BAG_FAULTS + OUTPUT_FAULTS + CAMERA_FAULTS + PCM_FAULTS + GRAPH_FAULTS + IMAGE_FAULTS)})")
    parser.add_argument("--workdir", default=None, help="where bags, configs and recordings go (default: a temp dir)")


# ------------------------------------------------------------------------- damaged bags
def bag_fault(name: str, work: Path, bag: Path, rig_path: Path, kps: list[str], env: dict[str, str]) -> dict:
    """Without --recover the tool must fail naming the file (damaged_chunk: and the chunk); with
    --recover it must read what is readable (damaged_chunk: the chunks after the damaged one too).
    frames_lost: frame sets of the intact bag that the tool did not get."""
    kind, tool = name.split(":")
    bad = work / f"{kind}.mcap"
    stamps = H.frame_stamps(bag)
    total = len(stamps)
    named, at_most = "", total  # what the error must name; the frame sets the damage may cost
    if kind == "damaged_chunk":
        k, start, end = H.damage_chunk(bag, bad)
        named, at_most = f"chunk {k} of", sum(start <= s <= end for s in stamps)
    else:
        H.damage(bag, bad, kind.split("_")[0])
    cfg = H.write_config(work / f"{kind}_{tool}.yaml", rig_path, kps, ["vmocap_markers"], "single_process", work / "unused.mcap")
    if tool == "process":
        def cmd(*extra: str) -> list[str]:  # --overwrite: the fault's own output of an earlier run (--workdir)
            return H.vmocap_cmd("process", str(bad), "-o", str(work / f"{kind}_out.mcap"), "--config", str(cfg),
                                "--no-progress", "--json", "--overwrite", *extra)
    else:
        def cmd(*extra: str) -> list[str]:
            return H.vmocap_cmd("play", str(bad), "--rate", "0", "--no-clock", "--wait-subscribers", "0.2", *extra)
    plain = subprocess.run(cmd(), env=env, capture_output=True, text=True, timeout=300)
    rec = subprocess.run(cmd("--recover"), env=env, capture_output=True, text=True, timeout=300)
    said = plain.stdout + plain.stderr
    diagnosed = plain.returncode != 0 and bad.name in said and named in said
    got = 0
    if rec.returncode == 0:
        if tool == "process":
            got = int(json.loads(rec.stdout.strip().splitlines()[-1])["frames"])
        else:  # the player publishes exactly what the recovering reader yields
            got = len(H.frame_stamps(bad, recover=True))
    # a damaged chunk costs that chunk only: the frame sets after it are read too
    return {"survived": rec.returncode == 0 and got > 0 and total - got <= at_most, "diagnosed": diagnosed,
            "frames_lost": total - got,
            "detail": (plain.stderr or plain.stdout).strip().splitlines()[-1:] + (rec.stderr or "").strip().splitlines()[-1:]}


# ------------------------------------------------------------------ faults in the PCM stream
def pcm_fault(name: str, mode: str, work: Path, bag: Path, rig_path: Path, kps: list[str], env: dict[str, str],
              probe) -> dict:
    """vmocap_markers + vmocap_skeleton + vmocap_recorder fed by `vmocap play` with the bag's
    heatmaps (bag stamps; deep queues: every frame set is processed)."""
    frames, bad_views = 150, ["cam1"]
    window = range(50, 110)
    if name == "person_leaves":
        bad_views = ["cam0", "cam1", "cam2", "cam3"]
    src = bag
    if name.startswith("heatmaps_") or name == "person_leaves":
        how = "absent" if name == "person_leaves" else name.split("_", 1)[1]
        src = H.alter_heatmaps(bag, work / f"{name}.mcap", window, bad_views, how, len(kps))
    if name.startswith("calibration_"):  # the bag is right, the rig the graph is given is not
        rig_path = H.miscalibrated(rig_path, work / "wrong.rig.yaml", "cam2", name.split("_")[1])
    if name == "camera_late":  # cam2's images two frame sets late; long enough for a timing probe after tracking starts
        frames = 240
        _, rig_path, kps = H.synthetic_bag(work / "in_step.mcap", frames, images=False, size=(1024, 768))
        src = H.delay_view(work / "in_step.mcap", work / f"{name}.mcap", "cam2", 2)
    out = work / f"{name}_{mode}_out.mcap"
    # silent after 1 s of stamp time: the two players of camera_pause start up to ~1 s apart, and
    # a camera whose stamps trail the others by more than that is never used again (sync.py)
    extra = {"vmocap_markers": {"queue_depth": 100, "silent_after_ms": 1000.0, "feedback_timeout_ms": 1000.0},
             "vmocap_skeleton": {"queue_depth": 100}}
    nodes = ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    cfg = H.write_config(work / f"{name}_{mode}.yaml", rig_path, kps, nodes, H.launch_mode(mode), out,
                         groups=[nodes[:2]], extra=extra)
    cams = ["cam0", "cam1", "cam2", "cam3"]
    feeds = [cams[:3], cams[3:]] if name == "camera_pause" else [cams]
    launch = H.Proc.start(H.vmocap_cmd("launch", str(cfg)), env)
    players = []
    pause = (0, 0)
    try:
        H.wait_ready(launch, nodes)
        # camera_pause's two players start in step: a player ahead of the other by more than
        # silent_after makes the other's frames late for good, and then no frame set goes out
        start_at = time.time() + PLAYERS_START_S
        for feed in feeds:
            topics = [f"/vmocap/pcm/{c}/{k}" for c in feed for k in PCM_TOPICS]
            players.append(H.Proc.start(H.vmocap_cmd("play", str(src), "--no-clock", "--quiet", "--topics", *topics,
                                                     "--expect", *topics, "--wait-subscribers", "60",
                                                     "--start-at", f"{start_at:.3f}"), env))
        if name == "camera_pause":  # once tracking, cam3's frames withheld for 2.5 s, then sent again
            probe.recording = False
            probe.spin_for(0.5)  # drain what an earlier run left queued
            probe.clear(all_=True)
            probe.min_stamp, probe.recording = 0, True
            if not H.wait_for(lambda: probe.spin_for(0.1) or len(probe.samples["joint_states"]) > 10, 60.0):
                raise RuntimeError("no output before the pause")
            os.kill(players[1].popen.pid, signal.SIGSTOP)
            pause = (time.time_ns(), 0)
            probe.spin_for(2.5)
            os.kill(players[1].popen.pid, signal.SIGCONT)
            pause = (pause[0], time.time_ns())
            probe.recording = False
        for p in players:
            if p.popen.wait(timeout=120) != 0:
                raise RuntimeError(f"player failed:\n{p.text}")
        time.sleep(2.0)  # backlog + one diagnostics period
    finally:
        for p in players:
            p.stop()
        rc = launch.stop()
    o = H.Outputs.read(out)
    got = {round((st - H.T0) * H.FPS / 1e9) for _, st in o.joint_states}
    first = min(got, default=frames)
    # frame sets that should have given output: all after the first, but those without the person
    present = [k for k in range(first, frames) if name != "person_leaves" or k not in window]
    lost = sum(k not in got for k in present)
    after = [k for k in range(window.stop, frames) if k in got]
    r: dict = {"frames_lost": lost, "launcher_rc": rc, "frames_out": len(got)}
    if name == "person_leaves":
        statuses = [v.get("status") for _, _, _, v in o.diag.get("vmocap_skeleton", [])]
        seen_lost = "tracking" in statuses and any(s in ("lost", "initializing", "identifying")
                                                     for s in statuses[statuses.index("tracking"):])
        from vmocap_core.method.config import MarkersConfig
        # the tracker declares "lost" after lost_frames frame sets of low marker weight: up to
        # that many outputs after leaving are the documented detection delay
        coast = sum(k in got for k in window)
        r.update(survived=rc == 0 and bool(after) and coast < MarkersConfig().lost_frames, diagnosed=seen_lost,
                 output_while_absent=sum(k in got for k in window), tracked_after_return=len(after))
    elif name == "camera_pause":
        silent = [(t, ast.literal_eval(v.get("silent", "[]"))) for t, _, _, v in o.diag.get("vmocap_markers", [])]
        gone = next((t for t, s in silent if "cam3" in s), None)
        back = gone is not None and any(t > gone and "cam3" not in s for t, s in silent)
        during = sum(pause[0] <= t <= pause[1] for t, _ in o.joint_states)
        r.update(survived=rc == 0 and back and during >= 10 * (pause[1] - pause[0]) / 1e9, diagnosed=gone is not None,
                 outputs_while_paused=during)
    elif name == "camera_late":
        r.update(survived=rc == 0 and len(got) >= 0.5 * frames,
                 diagnosed=o.warned("vmocap_markers", "camera out of step: cam2: images lag the others by +"))
    elif name.startswith("calibration_"):
        # vmocap_markers' per-camera reprojection residuals and a WARN naming the camera
        res = [v.get("residual_px:cam2") for _, _, _, v in o.diag.get("vmocap_markers", []) if "residual_px:cam2" in v]
        r.update(survived=rc == 0 and len(got) >= 0.5 * frames, diagnosed=bool(res) and o.warned("vmocap_markers", "cam2"),
                 residual_px_cam2=res[-1] if res else None)
    else:
        r.update(survived=rc == 0 and len(after) >= 0.5 * (frames - window.stop),
                 diagnosed=any(o.warned(n) for n in ("vmocap_markers", "vmocap_skeleton")), tracked_after=len(after))
    return r


# --------------------------------------------------------------- faults of processes
def graph_fault(name: str, mode: str, work: Path, bag: Path, rig_path: Path, kps: list[str], env: dict[str, str]) -> dict:
    """The graph fed by its camera node (the images+PCM bag looped, restamped; PCM from the bag),
    recorder apart in the default mode; one signal sent to one process."""
    from vmocap_core.bag import BagReader

    out = work / f"{name}_{mode}_out.mcap"
    nodes = ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    extra = {"vmocap_camera": {"source": "bag", "uri": str(bag), "loop": True, "restamp": True},
             "vmocap_pcm": {"source": "model", "model": str(bag)}}
    restart = {"node_restarted": ["vmocap_markers"], "recorder_restarted": ["vmocap_recorder"]}.get(name, [])
    # what killed recorders of an earlier run (--workdir) left: a new killed file must be .killed1
    for old in [Path(f"{out}.partial"), *work.glob(f"{out.stem}.killed*{out.suffix}.partial")]:
        old.unlink(missing_ok=True)
    cfg = H.write_config(work / f"{name}_{mode}.yaml", rig_path, kps, nodes, H.launch_mode(mode), out, groups=[nodes[:4]], extra=extra,
                         launch={"restart": restart, "restart_limit": 3})
    launch = H.Proc.start(H.vmocap_cmd("launch", str(cfg)), env)
    ref = None
    r: dict = {"frames_lost": 0}
    try:
        H.wait_ready(launch, nodes)
        if name in ("recorder_sigkill", "recorder_restarted"):  # a second recorder: what the killed one should have had
            ref = H.Proc.start(H.vmocap_cmd("record", "-o", str(work / f"ref_{mode}.mcap"), "--overwrite",
                                            "/vmocap/joint_states"), env)
        time.sleep(8.0)
        if name in ("launcher_sigint", "launcher_sigterm"):
            rc = launch.stop(signal.SIGINT if name.endswith("sigint") else signal.SIGTERM)
            o = H.Outputs.read(out)
            r.update(survived=rc == 0 and o.closed and len(o.joint_states) > 0, diagnosed=o.closed and not Path(f"{out}.partial").exists(),
                     launcher_rc=rc, joint_states=len(o.joint_states))
        elif name == "node_killed":
            group = next(g for g in launch.pids() if "vmocap_markers" in g)
            os.kill(launch.pids()[group], signal.SIGKILL)
            exited = H.wait_for(lambda: launch.popen.poll() is not None, 30.0)
            rc = launch.stop()
            o = H.Outputs.read(out)
            reported = f"{group} exited with -9" in launch.text
            r.update(survived=exited and o.closed, diagnosed=reported, launcher_rc=rc,
                     note="not in vmocap_launch.restart: the launcher stops the graph")
        elif name in ("node_restarted", "recorder_restarted"):
            r.update(_restarted(name, launch, ref, out, work / f"ref_{mode}.mcap"))
        else:  # recorder_sigkill
            victim = launch.pids().get("vmocap_recorder", launch.popen.pid)
            t_kill = time.time_ns()
            os.kill(victim, signal.SIGKILL)
            time.sleep(0.5)
            ref.stop()
            launch.stop()
            partial = Path(f"{out}.partial")
            o = H.Outputs.read(partial, recover=True)
            with BagReader(work / f"ref_{mode}.mcap") as rr:
                from vmocap_core.bag import messages as M

                want = sorted(M.stamp_ns(m.decode()) for m in rr.messages() if m.log_time_ns < t_kill)
            have = sorted(st for _, st in o.joint_states)
            prefix = not have or set(want[: sum(s <= have[-1] for s in want)]) <= set(have)
            r.update(survived=prefix, diagnosed=not o.closed, frames_lost=max(len(want) - len(have), 0),
                     recorded_before_kill=len(want), recovered=len(have), file_bytes=partial.stat().st_size,
                     bound_bytes=_chunk_size())
    finally:
        if ref is not None and ref.popen.poll() is None:
            ref.stop()
        if launch.popen.poll() is None:
            launch.stop()
    return r


# ------------------------------------------------------------- bad camera images, the CNN
def _restarted(name: str, launch: H.Proc, ref: H.Proc | None, out: Path, ref_path: Path) -> dict:
    """SIGKILL to the tracker group (node_restarted) or the recorder (recorder_restarted), both
    in vmocap_launch.restart: the launcher must report it and start the process again, and the
    graph go on. frames_lost: node_restarted: joint_states periods without output between the
    last one before the kill and the first after the restart; recorder_restarted: joint_states
    of the reference recorder (from the first that either recording has to the last) that
    neither the killed recording (recovered) nor the restarted one holds."""
    from vmocap_core.bag import BagReader
    from vmocap_core.bag import messages as M

    group = next(g for g in launch.pids() if ("vmocap_markers" if name == "node_restarted" else "vmocap_recorder") in g)
    old_pid = launch.pids()[group]
    t_kill = time.time_ns()
    os.kill(old_pid, signal.SIGKILL)
    restarted = H.wait_for(lambda: launch.pids().get(group, old_pid) != old_pid, 10.0)
    alive = launch.popen.poll() is None
    time.sleep(10.0)  # the new process starts (~3-5 s) and works
    if ref is not None:
        ref.stop()
    rc = launch.stop()
    o = H.Outputs.read(out)
    reported = f"{group} exited with -9; restarted as" in launch.text
    r: dict = {"launcher_rc": rc, "restarted": restarted, "launcher_alive_after_kill": alive}
    if name == "node_restarted":
        before = [t for t, _ in o.joint_states if t < t_kill]
        after = [t for t, _ in o.joint_states if t > t_kill]
        gap = (after[0] - before[-1]) / 1e9 if before and after else float("inf")
        r.update(survived=restarted and alive and rc == 0 and o.closed and len(after) > 30, diagnosed=reported,
                 frames_lost=round(gap * H.FPS) - 1 if after and before else -1, outage_s=round(gap, 2),
                 joint_states_before=len(before), joint_states_after=len(after))
        return r
    kept = out.with_name(f"{out.stem}.killed1{out.suffix}.partial")
    k = H.Outputs.read(kept, recover=True) if kept.exists() else H.Outputs([], {}, False)
    have = {st for _, st in k.joint_states} | {st for _, st in o.joint_states}
    with BagReader(ref_path) as rr:
        want = sorted(M.stamp_ns(m.decode()) for m in rr.messages())
    span = [s for s in want if have and min(have) <= s <= max(have)]
    lost = [s for s in span if s not in have]
    kept_warned = o.warned("vmocap_recorder", "kept as")
    r.update(survived=restarted and alive and rc == 0 and o.closed and kept.exists() and len(o.joint_states) > 30,
             diagnosed=reported and kept_warned, frames_lost=len(lost), killed_file_recovered=len(k.joint_states),
             restarted_file=len(o.joint_states), reference=len(span),
             lost_s=round(len(lost) / H.FPS, 2), recorder_warned_kept=kept_warned,
             # the open chunk of the killed recorder, and the restart (process start, discovery)
             unwritten_before_kill_s=round((t_kill - max((st for _, st in k.joint_states), default=t_kill)) / 1e9, 2),
             restart_gap_s=round((min((st for _, st in o.joint_states), default=t_kill) - t_kill) / 1e9, 2))
    return r


# ------------------------------------------------------------- a camera unplugged and back
def _chunk_size() -> int:
    """The recorder's MCAP chunk size: what a SIGKILL can lose at most (plus the OS buffer)."""
    from vmocap_core.graph_config import NODE_PARAMS

    return next(int(p.default) for p in NODE_PARAMS["vmocap_recorder"] if p.name == "chunk_kb") << 10


# ------------------------------------------------------------------------------ driver
def run(args: argparse.Namespace) -> int:
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="vmocap_faults_"))
    work.mkdir(parents=True, exist_ok=True)
    env = H.env_for(100 + os.getpid() % 100)
    plan = [(f, None) for f in BAG_FAULTS + OUTPUT_FAULTS]
    from vmocap_core.cameras import aravis as arv

    if arv.available():
        plan += [(f, None) for f in CAMERA_FAULTS]
    elif not args.only or set(args.only) & set(CAMERA_FAULTS):
        print("bench faults: Aravis 0.8 / PyGObject not installed: aravis_reconnect left out", file=sys.stderr)
    plan += [(f, m) for m in args.modes for f in PCM_FAULTS + GRAPH_FAULTS + IMAGE_FAULTS
             if not (f in PROCESSES_ONLY and m != "default")]
    if args.only:
        plan = [(f, m) for f, m in plan if f in args.only or f.split(":")[0] in args.only]
        if not plan:
            print(f"bench faults: no fault named {args.only}", file=sys.stderr)
            return 2
    pcm_bag = H.synthetic_bag(work / "pcm.mcap", 150, images=False)
    cam_bag = H.synthetic_bag(work / "cams.mcap", 30, images=True) if any(f in GRAPH_FAULTS for f, _ in plan) else None
    demo = H.demo_bag(work / "demo.mcap", IMAGE_FRAMES) if any(f in IMAGE_FAULTS for f, _ in plan) else None
    probe = _probe(env) if any(m is not None for _, m in plan) else None
    faults: dict[str, dict] = {}
    try:
        _run_plan(plan, work, env, probe, pcm_bag, cam_bag, demo, faults, args.json)
    finally:
        if probe is not None:
            probe.close()
            probe.rclpy.shutdown()
    out = {"faults": faults, "tried": len(faults), "survived": sum(r["survived"] for r in faults.values()),
           "diagnosed": sum(r["diagnosed"] for r in faults.values()), "workdir": str(work)}
    print(json.dumps(out) if args.json else f"{out['survived']} of {out['tried']} faults survived, {out['diagnosed']} diagnosed")
    return 0 if all(r.get("error") is None for r in faults.values()) else 1


def _probe(env: dict[str, str]):
    """A node in this process receiving joint_states (probe.Probe), on the graph's domain."""
    from ..common import init_rclpy
    from .probe import Probe

    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION") if k in env})
    if "FASTRTPS_DEFAULT_PROFILES_FILE" in env:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTRTPS_DEFAULT_PROFILES_FILE"]
    return Probe(init_rclpy(), ["cam0"], input_topic=False)


def _run_plan(plan, work: Path, env: dict[str, str], probe, pcm_bag, cam_bag, demo, faults: dict[str, dict],
              quiet: bool) -> None:
    from tqdm import tqdm

    for f, m in tqdm(plan, desc="faults", disable=quiet, file=sys.stderr):
        key = f if m is None else f"{f}:{m}"
        d = work / key.replace(":", "_")
        d.mkdir(exist_ok=True)
        try:
            if f in CAMERA_FAULTS:
                faults[key] = aravis_fault(d, env)
            elif f in OUTPUT_FAULTS:
                faults[key] = output_fault(f, d, work / "pcm.mcap", pcm_bag[1], pcm_bag[2], env)
            elif m is None:
                faults[key] = bag_fault(f, d, work / "pcm.mcap", pcm_bag[1], pcm_bag[2], env)
            elif f in IMAGE_FAULTS:
                if demo is None:
                    raise RuntimeError("the Pose2Sim demo is not cached (models/pose2sim: `make demo` fetches it)")
                faults[key] = image_fault(f, m, d, work / "demo.mcap", demo[1], env)
            elif f in PCM_FAULTS:
                faults[key] = pcm_fault(f, m, d, work / "pcm.mcap", pcm_bag[1], pcm_bag[2], env, probe)
            else:
                faults[key] = graph_fault(f, m, d, work / "cams.mcap", cam_bag[1], cam_bag[2], env)
        except Exception as exc:  # noqa: BLE001 - a fault that breaks the harness is a failed fault, reported
            faults[key] = {"survived": False, "diagnosed": False, "frames_lost": -1, "error": f"{type(exc).__name__}: {exc}"[:2000]}
        if not quiet:
            r = faults[key]
            tqdm.write(f"{key:34s} survived {r['survived']!s:5s} diagnosed {r['diagnosed']!s:5s} "
                       f"frames lost {r['frames_lost']}  {r.get('error', '')}", file=sys.stderr)
