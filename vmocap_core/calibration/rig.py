"""Whole-rig calibration: intrinsics per camera, pairwise initialization, bundle adjustment,
optional scene points with known world coordinates."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..cameras.projection import Camera, Rig
from ..errors import CalibrationError
from .boards import Board, Detection
from .geometry import (
    BoardPose,
    Intrinsics,
    SceneObservations,
    board_poses,
    build_problem,
    bundle_adjust,
    calibrate_intrinsics,
    compose,
    initial_rig,
    intr_matrices,
    intr_vector,
    invert,
    rigid_align,
    rotation_angle_deg,
)
from .observe import CameraViews, explain_no_board


@dataclass
class CameraReport:
    name: str
    size: tuple[int, int]
    frames_read: int
    board_views: int  # frames with enough board corners
    mirrored_views: int  # of which decoded in the mirrored image (board seen from behind)
    intrinsics_rms: float | None  # Zhang RMS (px); None when intrinsics were given
    intrinsics_views: int
    rms: float | None  # final reprojection RMS in the joint adjustment (px)
    points: int  # observations in the joint adjustment
    pnp_rms: float | None = None  # median single-view PnP RMS (px), a check of given intrinsics

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class CalibrationResult:
    rig: Rig
    cameras: list[CameraReport]
    warnings: list[str] = field(default_factory=list)
    frames: int = 0  # board poses in the joint adjustment
    rms_before: float | None = None
    rms_after: float | None = None


def calibrate_rig(
    views: list[CameraViews],
    board: Board,
    intrinsics: dict[str, Camera] | None = None,
    scene: SceneObservations | None = None,
    origin: str | None = None,
    min_views: int = 8,
    fix_k3: bool = True,
    refine_intrinsics: bool = False,
    intrinsics_only: bool = False,
    max_views: int = 40,
) -> CalibrationResult:
    """Calibrate the cameras whose board detections are `views` (frame keys synchronized).

    `intrinsics` fixes K and distortion of the cameras it names (e.g. from an earlier
    calibration); the others get Zhang's method on their own views. The world frame is the
    camera `origin` (default: the first), or the scene points' frame when `scene` is given.
    """
    intrinsics = intrinsics or {}
    names = [v.name for v in views]
    warnings: list[str] = []
    usable = [v.usable(board.min_corners) for v in views]
    scene_n = {n: int(np.all(np.isfinite(scene.uv[n]), axis=1).sum()) if scene and n in scene.uv else 0 for n in names}

    intr: list[Intrinsics] = []
    for v in views:
        given = intrinsics.get(v.name)
        if given is not None and (given.width, given.height) != v.size:
            raise CalibrationError(
                f"camera {v.name}: images are {v.size[0]}x{v.size[1]} but the given intrinsics are for "
                f"{given.width}x{given.height}")
    for v, u in zip(views, usable):
        if not u and scene_n[v.name] < 4:
            raise CalibrationError(f"camera {v.name}: {explain_no_board(v, board)}")
        if 0 < len(u) < min_views:
            warnings.append(f"camera {v.name}: only {len(u)} board views (fewer than {min_views}); its calibration may be poor")
        given = intrinsics.get(v.name)
        if given is not None:
            intr.append(Intrinsics(given.K.copy(), given.dist[:5].copy(), float("nan"), 0))
        else:
            intr.append(calibrate_intrinsics(v.name, u, board, v.size, fix_k3=fix_k3, max_views=max_views))
            if intr[-1].rejected:
                warnings.append(f"camera {v.name}: {intr[-1].rejected} board views dropped as outliers")

    def report(c: int, rms=None, points=0, pnp=None) -> CameraReport:
        v = views[c]
        given = v.name in intrinsics
        return CameraReport(v.name, v.size, v.frames_read, len(usable[c]), v.mirrored_views,
                            None if given else intr[c].rms, intr[c].views, rms, points, pnp)

    def make_rig(poses) -> Rig:
        return Rig([Camera(v.name, it.K, it.dist, R, t, v.size[0], v.size[1]) for v, it, (R, t) in zip(views, intr, poses)])

    if intrinsics_only or len(views) == 1:
        ident = [(np.eye(3), np.zeros(3))] * len(views)
        return CalibrationResult(make_rig(ident), [report(c) for c in range(len(views))], warnings)

    ref = names.index(origin) if origin else 0
    if origin and origin not in names:
        raise CalibrationError(f"origin camera '{origin}' is not one of {names}")
    poses = [board_poses(u, board, it.K, it.dist) for u, it in zip(usable, intr)]
    pnp_rms = [float(np.median([p.rms for p in ps.values()])) if ps else None for ps in poses]
    if not poses[ref] and scene is None:
        raise CalibrationError(f"camera {names[ref]} (the world origin): no board view gave a pose with its intrinsics; "
                               f"choose another --origin")
    cams = initial_rig(poses, names, ref, board.flip) if poses[ref] else [None] * len(views)
    if board.flip is not None:
        usable = _unify_numbering(usable, poses, cams, board)

    if scene is not None:
        cams = _place_with_scene(cams, poses, intr, views, scene)
    missing = [names[c] for c in range(len(views)) if cams[c] is None]
    if missing:
        placed = [n for n, p in zip(names, cams) if p is not None]
        raise CalibrationError(
            f"camera {missing[0]}: never sees the board in the same frame as the already placed cameras {placed}"
            + ("" if scene is None else " and sees fewer than 4 scene points"))

    # Board poses in the world: one per frame seen by >= 2 cameras (>= 1 when refining
    # intrinsics, where single views still constrain the lens).
    need = 1 if refine_intrinsics else 2
    frame_keys, frames = [], []
    for f in sorted(set().union(*[set(p) for p in poses])):
        seen = [(poses[c][f].n, c) for c in range(len(views)) if f in poses[c]]
        if len(seen) >= need:
            _n, c = max(seen)
            frame_keys.append(f)
            frames.append(compose(invert(cams[c]), (poses[c][f].R, poses[c][f].t)))
    problem = build_problem([{f: u[f] for f in u if f in p} for u, p in zip(usable, poses)], board, frame_keys, scene, names)
    it0 = np.array([intr_vector(i.K, i.dist) for i in intr])
    fixed = None if scene is not None else ref
    ba = bundle_adjust(problem, cams, frames, it0, fixed, refine_intrinsics=refine_intrinsics, fix_k3=fix_k3)
    for c in range(len(views)):
        intr[c].K, intr[c].dist = intr_matrices(ba.intr[c])
    reports = [report(c, float(ba.rms[c]), int(ba.n_obs[c]), pnp_rms[c]) for c in range(len(views))]
    return CalibrationResult(make_rig(ba.cameras), reports, warnings, ba.frames, ba.cost_before, ba.cost_after)


def _unify_numbering(usable, poses, cams, board: Board):
    """Renumber chessboard views so that every camera numbers a frame's corners like the
    frame's first placed camera does (the detector may start from either end)."""
    F = board.flip
    usable = [dict(u) for u in usable]
    for f in sorted(set().union(*[set(p) for p in poses])):
        seen = [c for c in range(len(poses)) if f in poses[c] and cams[c] is not None]
        if len(seen) < 2:
            continue
        c0 = seen[0]
        board_w = compose(invert(cams[c0]), (poses[c0][f].R, poses[c0][f].t))  # board -> world
        for c in seen[1:]:
            pred = compose(cams[c], board_w)
            p = poses[c][f]
            alt = compose((p.R, p.t), F)
            if rotation_angle_deg(pred[0], alt[0]) < rotation_angle_deg(pred[0], p.R):
                poses[c][f] = BoardPose(alt[0], alt[1], p.rms, p.n)
                det = usable[c][f]
                usable[c][f] = Detection(board.flip_ids(det.ids), det.uv, det.markers, det.mirrored)
    return usable


def _place_with_scene(cams, poses, intr, views, scene: SceneObservations):
    """Move the board-calibrated rig into the scene frame (triangulated scene points aligned
    rigidly to their known coordinates) and place cameras that only see scene points by PnP."""
    from ..method.triangulation import triangulate

    names = [v.name for v in views]
    placed = [c for c in range(len(views)) if cams[c] is not None]
    if len(placed) >= 2:
        rig = Rig([Camera(names[c], intr[c].K, intr[c].dist, *cams[c], *views[c].size) for c in placed])
        P = len(scene.points)
        uv = np.full((len(placed), P, 2), np.nan)
        for i, c in enumerate(placed):
            if names[c] in scene.uv:
                uv[i] = scene.uv[names[c]]
        w = np.all(np.isfinite(uv), axis=2).astype(float)
        pts, _res = triangulate(rig, np.nan_to_num(uv), w)
        ok = np.all(np.isfinite(pts), axis=1)
        if ok.sum() >= 3:
            S = rigid_align(pts[ok], scene.points[ok])  # old world -> scene world
            cams = [None if p is None else compose(p, invert(S)) for p in cams]
        else:
            cams = [None] * len(cams)  # board frame unknown in the scene: place all by PnP
    for c in range(len(views)):
        if cams[c] is None and names[c] in scene.uv:
            seen = np.all(np.isfinite(scene.uv[names[c]]), axis=1)
            if seen.sum() >= 4:
                ok, rvec, tvec = cv2.solvePnP(scene.points[seen], scene.uv[names[c]][seen], intr[c].K, intr[c].dist,
                                              flags=cv2.SOLVEPNP_SQPNP)
                if ok:
                    cams[c] = (cv2.Rodrigues(rvec)[0], tvec.ravel())
    return cams
