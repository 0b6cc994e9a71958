"""The output faults of `vmocap bench faults` (faults.py): `vmocap process` told to write onto
its own input, onto an existing file, and killed while writing; `vmocap launch` given a config
that cannot work with its rig. What each does and what survived / diagnosed mean:
docs/faults.md."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from . import fault_harness as H

OUTPUT_FAULTS = ["output_is_input:path", "output_is_input:symlink", "output_is_input:hardlink", "output_exists",
                 "output_killed:new", "output_killed:replace", "min_cameras_above_rig"]
KILL_AFTER_S = 0.2  # from the output's .partial appearing (the writer open) to the SIGKILL


def output_fault(name: str, work: Path, bag: Path, rig_path: Path, kps: list[str], env: dict[str, str]) -> dict:
    """One output fault on the PCM bag (`bag`, its rig and keypoints). frames_lost: frame sets of
    the file the fault puts at risk (the input, or the earlier output) no longer readable at its
    path afterwards."""
    if name == "min_cameras_above_rig":
        return _config_refused(work, rig_path, kps, env)
    cfg = H.write_config(work / "process.yaml", rig_path, kps, ["vmocap_markers"], "single_process", work / "unused.mcap")

    def process(src: Path, out: Path, *extra: str) -> list[str]:
        return H.vmocap_cmd("process", str(src), "-o", str(out), "--config", str(cfg), "--no-progress", "--json", *extra)

    kind, _, how = name.partition(":")
    if kind == "output_is_input":
        return _onto_input(how, work, bag, process, env)
    # the earlier output a user would not want to lose: a real (small) recording
    earlier = work / "earlier.mcap"
    H.synthetic_bag(earlier, 5, images=False)
    out = work / "out.mcap"
    for old in (out, Path(f"{out}.partial")):  # this fault's own files of an earlier run (--workdir)
        old.unlink(missing_ok=True)
    if kind == "output_exists" or how == "replace":
        shutil.copyfile(earlier, out)
    if kind == "output_exists":
        return _exists(out, earlier, bag, process, env)
    return _killed(how, out, earlier, bag, process, env)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _one_line(p: subprocess.CompletedProcess, *words: str) -> bool:
    """Refused as bad input: exit 2, one line on stderr naming `words`."""
    lines = p.stderr.strip().splitlines()
    return p.returncode == 2 and len(lines) == 1 and all(w in lines[0] for w in words)


def _onto_input(how: str, work: Path, bag: Path, process, env: dict[str, str]) -> dict:
    """`vmocap process IN -o TARGET --overwrite` with TARGET the input itself, a symlink to it or a
    hard link of it: refused even with --overwrite, the input (and the link) as they were."""
    src = work / "in.mcap"
    shutil.copyfile(bag, src)  # a copy: a failure must not destroy the bag the other faults read
    target = {"path": src, "symlink": work / "link.mcap", "hardlink": work / "hard.mcap"}[how]
    if how == "symlink":
        target.unlink(missing_ok=True)
        target.symlink_to(src.name)
    elif how == "hardlink":
        target.unlink(missing_ok=True)
        os.link(src, target)
    before = _digest(src)
    run = subprocess.run(process(src, target, "--overwrite"), env=env, capture_output=True, text=True, timeout=300)
    intact = _digest(src) == before and (how != "symlink" or target.is_symlink()) and os.path.samefile(src, target)
    return {"survived": intact, "diagnosed": _one_line(run, str(target), "refusing to write onto it"),
            "frames_lost": 0 if intact else _lost(bag, src), "exit": run.returncode,
            "detail": run.stderr.strip().splitlines()[-1:]}


def _exists(out: Path, earlier: Path, bag: Path, process, env: dict[str, str]) -> dict:
    """An existing output: refused without --overwrite (the file as it was), replaced with it
    (a closed recording of every frame set of the input)."""
    plain = subprocess.run(process(bag, out), env=env, capture_output=True, text=True, timeout=300)
    kept = _digest(out) == _digest(earlier)
    again = subprocess.run(process(bag, out, "--overwrite"), env=env, capture_output=True, text=True, timeout=300)
    o = H.Outputs.read(out)
    replaced = again.returncode == 0 and o.closed and _digest(out) != _digest(earlier) and len(o.joint_states) > 0
    return {"survived": kept and replaced, "diagnosed": _one_line(plain, str(out), "exists", "--overwrite"),
            "frames_lost": 0 if kept else len(H.frame_stamps(earlier)), "refused_exit": plain.returncode,
            "overwrite_exit": again.returncode, "joint_states_after_overwrite": len(o.joint_states),
            "detail": plain.stderr.strip().splitlines()[-1:]}


def _killed(how: str, out: Path, earlier: Path, bag: Path, process, env: dict[str, str]) -> dict:
    """`vmocap process` (with --overwrite over an earlier output, `replace`, or onto no file,
    `new`) killed with SIGKILL while its output is open: at OUT the earlier file byte for byte, or
    nothing; the unfinished recording only as OUT.partial, which reads as not closed."""
    partial = Path(f"{out}.partial")
    before = _digest(out) if out.exists() else None
    proc = subprocess.Popen(process(bag, out, *(["--overwrite"] if how == "replace" else [])), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        if not H.wait_for(lambda: partial.exists() or proc.poll() is not None, 120.0, step=0.01) or not partial.exists():
            raise RuntimeError(f"the output was never opened (exit {proc.poll()}): {proc.communicate()[1][-2000:]}")
        time.sleep(KILL_AFTER_S)
        if proc.poll() is not None:
            raise RuntimeError(f"vmocap process finished (exit {proc.returncode}) before the kill: nothing was killed mid-write")
        written = partial.stat().st_size
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()  # type: ignore[union-attr]
    intact = (_digest(out) == before) if before is not None else not os.path.lexists(out)
    unfinished = not H.Outputs.read(partial).closed if partial.exists() else False
    return {"survived": intact, "diagnosed": unfinished,
            "frames_lost": 0 if intact or before is None else len(H.frame_stamps(earlier)), "exit": proc.returncode,
            "partial_bytes_at_kill": written, "output_after": "earlier file" if before is not None and intact
            else ("none" if not os.path.lexists(out) else "another file")}


def _config_refused(work: Path, rig_path: Path, kps: list[str], env: dict[str, str]) -> dict:
    """A graph config asking vmocap_markers for more cameras (5) than the rig has (4):
    `vmocap config check` and `vmocap launch` refuse it naming the parameter, before any node
    starts (no READY line, no process started, the recorder's output never created)."""
    out = work / "min_cameras_out.mcap"
    for old in (out, Path(f"{out}.partial")):
        old.unlink(missing_ok=True)
    nodes = ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    cfg = H.write_config(work / "min_cameras.yaml", rig_path, kps, nodes, "processes", out, groups=[nodes[:2]],
                         extra={"vmocap_markers": {"min_cameras": 5}})
    check = subprocess.run(H.vmocap_cmd("config", "check", str(cfg)), env=env, capture_output=True, text=True, timeout=120)
    launch = H.Proc.start(H.vmocap_cmd("launch", str(cfg)), env)
    try:
        ended = H.wait_for(lambda: launch.popen.poll() is not None, 60.0)
    finally:
        rc = launch.stop()
    text = launch.text
    started = "READY" in text or "processes:" in text or out.exists() or Path(f"{out}.partial").exists()
    words = ("vmocap_markers.min_cameras", "more than the 4")
    return {"survived": ended and rc == 2 and not started,
            "diagnosed": _one_line(check, *words) and all(w in text for w in words), "frames_lost": 0,
            "launch_exit": rc, "check_exit": check.returncode, "detail": text.strip().splitlines()[-1:]}


def _lost(bag: Path, copy: Path) -> int:
    """Frame sets of `bag` that its copy no longer holds."""
    try:
        return len(H.frame_stamps(bag) - H.frame_stamps(copy, recover=True))
    except Exception:  # noqa: BLE001 - not an MCAP file any more: everything is lost
        return len(H.frame_stamps(bag))
