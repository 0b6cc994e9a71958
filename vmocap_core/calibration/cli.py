"""`vmocap calibrate`: intrinsics and extrinsics of a camera rig from board images or videos.

Examples::

    # whole rig from synchronized ChArUco videos, intrinsics fixed from an earlier calibration
    vmocap calibrate --board charuco.toml --camera 0=cam_0.mp4 --camera 1=cam_1.mp4 ... \\
        --intrinsics camera_array.toml --out rig.yaml --camera-info-dir camera_info/
    # intrinsics only, from checkerboard images (7x4 inner corners, 6 cm squares)
    vmocap calibrate --board checkerboard:7x4:0.06 --camera cam01=int_cam01_img/ --intrinsics-only
    # compare against a reference calibration (prints errors; --check fails above thresholds)
    vmocap calibrate ... --reference camera_array.toml --check --json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

from ..errors import CalibrationError, RigFileError
from .boards import load_board
from .geometry import SceneObservations
from .observe import detect_camera
from .reference import compare_extrinsics, compare_intrinsics, load_reference
from .rig import CalibrationResult, calibrate_rig


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = __doc__.split("\n\n")[0]
    p.epilog = __doc__.split("\n\n", 1)[1]
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--board", required=True,
                   help="checkerboard:COLSxROWS:SQUARE_M (inner corners) | charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:inverted] | charuco .toml")
    p.add_argument("--camera", action="append", default=[], metavar="NAME=PATH",
                   help="a camera and its video file, image folder or glob (repeat per camera)")
    p.add_argument("--offset", action="append", default=[], metavar="NAME=FRAMES",
                   help="frame offset of a camera's video relative to the others (synchronization)")
    p.add_argument("--every", type=int, default=1, help="use every N-th frame")
    p.add_argument("--max-frames", type=int, default=None, help="read at most this many frames per camera")
    p.add_argument("--intrinsics", default=None,
                   help="fix K and distortion from this rig file (vmocap .yaml, caliscope .toml) for the cameras it names")
    p.add_argument("--intrinsics-only", action="store_true", help="calibrate each camera's intrinsics only")
    p.add_argument("--refine-intrinsics", action="store_true", help="also refine intrinsics in the bundle adjustment")
    p.add_argument("--k3", action="store_true", help="estimate the 3rd radial distortion term (default: fixed at 0)")
    p.add_argument("--origin", default=None, help="camera whose frame is the world frame (default: the first)")
    p.add_argument("--scene-points", default=None,
                   help="YAML with `points: [[x,y,z],...]` (metres, world) and `pixels: {camera: [[u,v] or null,...]}`")
    p.add_argument("--min-views", type=int, default=8, help="warn for cameras with fewer board views")
    p.add_argument("--out", default=None, help="write the rig file here")
    p.add_argument("--camera-info-dir", default=None, help="write one ROS camera_info YAML per camera here")
    p.add_argument("--overwrite", action="store_true", help="replace the rig file and camera_info files if they exist")
    p.add_argument("--reference", default=None, help="compare with this calibration (caliscope .toml, Qualisys .qca.txt, vmocap .yaml)")
    p.add_argument("--check", action="store_true", help="exit 1 when the reference comparison exceeds the thresholds")
    p.add_argument("--max-position-err", type=float, default=0.02, help="metres, relative camera positions")
    p.add_argument("--max-rotation-err", type=float, default=1.0, help="degrees, relative camera orientations")
    p.add_argument("--max-focal-err", type=float, default=1.0, help="percent, focal lengths")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--no-progress", action="store_true")


def _pairs(items: list[str], what: str) -> list[tuple[str, str]]:
    out = []
    for it in items:
        if "=" not in it:
            raise CalibrationError(f"{what} '{it}': expected NAME=VALUE")
        k, v = it.split("=", 1)
        out.append((k, v))
    return out


def load_scene(path: str, names: list[str]) -> SceneObservations:
    try:
        d = yaml.safe_load(Path(path).read_text())
        pts = np.asarray(d["points"], dtype=np.float64).reshape(-1, 3)
        uv = {}
        for name, rows in (d.get("pixels") or {}).items():
            if len(rows) != len(pts):
                raise RigFileError(path, f"pixels.{name}", f"{len(rows)} entries for {len(pts)} points")
            uv[str(name)] = np.array([[np.nan, np.nan] if r is None else r for r in rows], dtype=np.float64).reshape(-1, 2)
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise RigFileError(path, "points/pixels", str(exc)) from None
    unknown = sorted(set(uv) - set(names))
    if unknown:
        raise RigFileError(path, "pixels", f"cameras {unknown} are not calibrated here ({names})")
    return SceneObservations(pts, uv)


def _match(names: list[str], ref_names: list[str]) -> list[str] | None:
    """Reference camera per calibrated camera: by name, else by order when counts agree."""
    if all(n in ref_names for n in names):
        return names
    if len(names) == len(ref_names):
        return list(ref_names)
    return None


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except (CalibrationError, RigFileError) as exc:
        print(f"vmocap calibrate: error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    cams = _pairs(args.camera, "--camera")
    if not cams:
        raise CalibrationError("no camera given (use --camera NAME=PATH)")
    names = [n for n, _ in cams]
    _check_outputs(args, names, [p for _, p in cams])  # before the videos are read: a refusal costs nothing
    offsets = dict((k, int(v)) for k, v in _pairs(args.offset, "--offset"))
    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    log(f"board: {board.describe()}")
    views = [detect_camera(n, p, board, args.every, args.max_frames, offsets.get(n, 0), not args.no_progress) for n, p in cams]

    fixed = {}
    if args.intrinsics:
        ref_rig = load_reference(args.intrinsics)
        m = _match(names, ref_rig.names)
        if m is None:
            raise CalibrationError(f"--intrinsics {args.intrinsics}: cameras {ref_rig.names} do not match {names}")
        fixed = {n: ref_rig[r] for n, r in zip(names, m)}
    scene = load_scene(args.scene_points, names) if args.scene_points else None
    res = calibrate_rig(views, board, fixed, scene, args.origin, args.min_views, fix_k3=not args.k3,
                        refine_intrinsics=args.refine_intrinsics, intrinsics_only=args.intrinsics_only)
    out = {"board": board.describe(), "cameras": [c.as_dict() for c in res.cameras], "warnings": res.warnings,
           "frames": res.frames, "rms_before_px": res.rms_before, "rms_after_px": res.rms_after}
    for w in res.warnings:
        print(f"WARNING: {w}", file=sys.stderr)
    _print_result(res, log)
    _write(res, args, log)
    ok = True
    if args.reference:
        ok, out["reference"] = _compare(res, args, log)
    if args.json:
        print(json.dumps(out, indent=1))
    return 0 if ok or not args.check else 1


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def _print_result(res: CalibrationResult, log) -> None:
    log(f"{'camera':<14}{'size':>11}{'frames':>8}{'views':>7}{'mirr':>6}{'Zhang px':>10}{'BA px':>8}{'points':>8}"
        f"{'fx':>10}{'fy':>10}")
    for r, cam in zip(res.cameras, res.rig):
        log(f"{r.name:<14}{r.size[0]:>6}x{r.size[1]:<4}{r.frames_read:>8}{r.board_views:>7}{r.mirrored_views:>6}"
            f"{_fmt(r.intrinsics_rms):>10}{_fmt(r.rms):>8}{r.points:>8}{cam.K[0, 0]:>10.2f}{cam.K[1, 1]:>10.2f}")
    if res.rms_after is not None:
        log(f"bundle adjustment: {res.frames} board poses, RMS {res.rms_before:.3f} -> {res.rms_after:.3f} px")


def _inputs(args: argparse.Namespace, videos: list[str]) -> list[str]:
    return [p for p in (args.board, args.intrinsics, args.reference, args.scene_points, *videos) if p]


def _check_outputs(args: argparse.Namespace, names: list[str], videos: list[str]) -> None:
    from ..files import check_output

    inputs = _inputs(args, videos)
    if args.out:
        check_output(args.out, inputs, args.overwrite)
    if args.camera_info_dir:
        for n in names:
            check_output(Path(args.camera_info_dir) / f"{n}.yaml", inputs, args.overwrite)


def _write(res: CalibrationResult, args: argparse.Namespace, log) -> None:
    from ..cameras.rig_file import camera_info_dict, save_rig
    from ..files import write_text

    inputs = _inputs(args, [p for _, p in _pairs(args.camera, "--camera")])
    if args.out:
        save_rig(res.rig, args.out, args.overwrite, inputs)
        log(f"wrote {args.out}")
    if args.camera_info_dir:
        d = Path(args.camera_info_dir)
        for cam in res.rig:
            write_text(d / f"{cam.name}.yaml", yaml.safe_dump(camera_info_dict(cam), sort_keys=False), inputs, args.overwrite)
        log(f"wrote {len(res.rig)} camera_info files to {d}")


def _compare(res: CalibrationResult, args: argparse.Namespace, log) -> tuple[bool, dict]:
    ref = load_reference(args.reference)
    m = _match(res.rig.names, ref.names)
    if m is None:
        raise CalibrationError(f"--reference {args.reference}: cameras {ref.names} do not match {res.rig.names}")
    ok = True
    out: dict = {"file": args.reference, "intrinsics": {}}
    log(f"reference {args.reference} (cameras {m}):")
    for cam, rn, rep in zip(res.rig, m, res.cameras):
        ci = compare_intrinsics(cam, ref[rn])
        out["intrinsics"][cam.name] = ci
        log(f"  {cam.name}: fx {ci['fx']:.1f} fy {ci['fy']:.1f} vs {ci['ref_fx']:.1f} {ci['ref_fy']:.1f}: "
            f"focal error {ci['focal_err_pct']:.2f} %, principal point {ci['principal_err_px']:.1f} px")
        if rep.intrinsics_rms is not None or args.refine_intrinsics:  # estimated here, not given
            ok &= ci["focal_err_pct"] <= args.max_focal_err
    if not args.intrinsics_only and len(res.rig) > 1:
        ce = compare_extrinsics(res.rig, ref.subset(m))
        out["extrinsics"] = ce
        for n in res.rig.names:
            log(f"  {n}: worst relative position error {100 * ce['per_camera_position_err_m'][n]:.2f} cm, "
                f"rotation error {ce['per_camera_rotation_err_deg'][n]:.3f} deg")
        log(f"  max over camera pairs: position {100 * ce['max_position_err_m']:.2f} cm, rotation {ce['max_rotation_err_deg']:.3f} deg")
        ok &= ce["max_position_err_m"] <= args.max_position_err and ce["max_rotation_err_deg"] <= args.max_rotation_err
    out["pass"] = bool(ok)
    log("reference check: " + ("PASS" if ok else "FAIL"))
    return ok, out
