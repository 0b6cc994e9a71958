"""The demo's report: reprojection errors, overlays of the skeleton on the videos, plots,
report.md and summary.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...cameras.projection import Rig
from ...keypoints import INDEX, KEYPOINTS
from .data import FPS, bag_frame_sets

# Lines drawn for the overlay (pairs of keypoint names).
LIMBS = (
    ("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"), ("left_shoulder", "left_hip"),
    ("right_shoulder", "right_hip"), ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
    ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"), ("left_hip", "left_knee"),
    ("left_knee", "left_ankle"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
    ("left_ankle", "left_heel"), ("left_heel", "left_toe"), ("left_ankle", "left_toe"),
    ("right_ankle", "right_heel"), ("right_heel", "right_toe"), ("right_ankle", "right_toe"),
    ("neck", "nose"), ("nose", "left_eye"), ("nose", "right_eye"), ("left_eye", "left_ear"),
    ("right_eye", "right_ear"), ("pelvis", "neck"),
)


# ------------------------------------------------------------------------------ report
def reprojection_errors(rig: Rig, rec: dict, min_weight: float = 0.5, which: str = "keypoints") -> np.ndarray:
    """(N, C, 25) pixel distance between the projected output skeleton (or `which` = "raw" /
    "markers") and the CNN's 2D keypoints (PCM centroids) where the CNN is confident; NaN
    elsewhere or when not tracking."""
    kp = rec[which]  # (N, 25, 3)
    proj, front = rig.project(np.nan_to_num(kp))  # (C, N, 25, 2)
    proj = proj.transpose(1, 0, 2, 3)
    err = np.linalg.norm(proj - rec["uv"], axis=-1)  # (N, C, 25)
    ok = (rec["w"] >= min_weight) & np.isfinite(err) & front.transpose(1, 0, 2) & np.isfinite(kp).all(axis=-1)[:, None, :]
    return np.where(ok, err, np.nan)


def free_triangulation_errors(rig: Rig, rec: dict, min_weight: float = 0.5) -> np.ndarray:
    """Reference for the reprojection error: per frame, the CNN's 2D keypoints triangulated
    freely (weighted DLT, no skeleton, no filter, the worst view dropped above 20 px), reprojected.
    (N, C, 25) like reprojection_errors."""
    from ...method.triangulation import triangulate_robust

    n = len(rec["uv"])
    pts = np.full((n, len(KEYPOINTS), 3), np.nan)
    for f in range(n):
        pts[f], _ = triangulate_robust(rig, np.nan_to_num(rec["uv"][f]), rec["w"][f])
    return reprojection_errors(rig, {**rec, "free": pts}, min_weight, which="free")


def draw_skeleton(img: np.ndarray, uv: np.ndarray, color=(0, 255, 0), thickness: int = 4) -> None:
    import cv2

    for a, b in LIMBS:
        pa, pb = uv[INDEX[a]], uv[INDEX[b]]
        if np.isfinite(pa).all() and np.isfinite(pb).all():
            cv2.line(img, tuple(int(x) for x in pa), tuple(int(x) for x in pb), color, thickness, cv2.LINE_AA)
    for p in uv:
        if np.isfinite(p).all():
            cv2.circle(img, tuple(int(x) for x in p), thickness + 2, (0, 0, 255), -1, cv2.LINE_AA)


def render_overlays(bag: Path, rig: Rig, rec: dict, out_dir: Path, scale: float = 0.25) -> dict:
    """MP4 of the 4 views side by side with the reprojected skeleton, and a contact sheet."""
    import cv2

    kp = rec["keypoints"]
    proj, _ = rig.project(np.nan_to_num(kp))  # (C, N, 25, 2)
    proj = np.where(np.isfinite(kp).all(axis=-1)[None, ..., None], proj, np.nan)
    n = len(kp)
    sheet_idx = set(np.linspace(0, n - 1, 4).round().astype(int).tolist())
    sheet_rows = []
    writer = None
    mp4 = out_dir / "overlay.mp4"
    for f, (ns, images) in enumerate(bag_frame_sets(bag, rig)):
        if f >= n:
            break
        tiles = []
        for c, img in enumerate(images):
            img = img.copy()
            draw_skeleton(img, proj[c, f])
            status = rec["status"][f]
            cv2.putText(img, f"{rig[c].name} t={ns / 1e9:.2f}s {status}", (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.6,
                        (255, 255, 255), 4, cv2.LINE_AA)
            h, w = img.shape[:2]
            tile = cv2.resize(img, (int(1088 * scale), int(1920 * scale)))
            tiles.append(tile)
        row = np.hstack(tiles)
        if writer is None:
            writer = cv2.VideoWriter(str(mp4), cv2.VideoWriter.fourcc(*"mp4v"), FPS, (row.shape[1], row.shape[0]))
        writer.write(row)
        if f in sheet_idx:
            sheet_rows.append(row)
    if writer is not None:
        writer.release()
    sheet = out_dir / "contact_sheet.png"
    if sheet_rows:
        cv2.imwrite(str(sheet), np.vstack(sheet_rows))
    return {"mp4": mp4.name, "contact_sheet": sheet.name, "mp4_ok": mp4.exists() and mp4.stat().st_size > 0}


def write_report(rig: Rig, rec: dict, out_dir: Path, info: dict) -> dict:
    import matplotlib

    from ...method.landmarks import CNN_LANDMARKS, resolve

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...method.skeleton import BONES

    landmarks = resolve(info.get("tracker_settings", {}).get("landmarks", "auto"), CNN_LANDMARKS)  # the CNN ran
    t = (rec["stamp"] - rec["stamp"][0]) / 1e9
    tracking = np.array([s == "tracking" for s in rec["status"]])
    kp = rec["keypoints"]
    err = reprojection_errors(rig, rec)
    # Reprojection error per camera and keypoint.
    per_cam = {rig[c].name: float(np.nanmedian(err[:, c])) for c in range(len(rig))}
    per_kp = {KEYPOINTS[j]: float(np.nanmedian(err[:, :, j])) for j in range(len(KEYPOINTS)) if np.isfinite(err[:, :, j]).any()}
    median_all = float(np.nanmedian(err)) if np.isfinite(err).any() else float("nan")
    free = free_triangulation_errors(rig, rec)
    both = np.isfinite(err) & np.isfinite(free)  # same samples for the comparison
    median_free = float(np.median(free[both])) if both.any() else float("nan")
    median_same = float(np.median(err[both])) if both.any() else float("nan")
    face = np.array([INDEX[n] for n in ("nose", "left_eye", "right_eye", "left_ear", "right_ear")])
    body = np.setdiff1d(np.arange(len(KEYPOINTS)), face)
    median_body = float(np.nanmedian(err[:, :, body])) if np.isfinite(err[:, :, body]).any() else float("nan")
    median_body_free = float(np.nanmedian(free[:, :, body])) if np.isfinite(free[:, :, body]).any() else float("nan")
    free_kp = {KEYPOINTS[j]: float(np.nanmedian(free[:, :, j])) for j in range(len(KEYPOINTS)) if np.isfinite(free[:, :, j]).any()}
    raw = reprojection_errors(rig, rec, which="raw")
    median_raw = float(np.nanmedian(raw)) if np.isfinite(raw).any() else float("nan")
    # Bone lengths of the output skeleton.
    bones = {}
    for name, (a, b) in BONES.items():
        L = np.linalg.norm(kp[:, INDEX[a]] - kp[:, INDEX[b]], axis=-1)[tracking]
        L = L[np.isfinite(L)]
        if L.size:
            bones[name] = {"mean_m": float(L.mean()), "std_mm": float(L.std() * 1000), "range_mm": float(np.ptp(L) * 1000)}
    # Timing.
    if rec.get("node_timing"):
        timing = {f"node {k}": {"mean_ms": v["mean_ms"], "median_ms": v["median_ms"], "p95_ms": v["p95_ms"]}
                  for k, v in rec["node_timing"].items()}
    else:
        timing = {k[2:]: {"mean_ms": float(np.mean(rec[k]) * 1000), "median_ms": float(np.median(rec[k]) * 1000),
                          "p95_ms": float(np.percentile(rec[k], 95) * 1000)}
                  for k in ("t_decode", "t_pcm", "t_markers", "t_skeleton")}

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, rec["score"], label="mean PCM score per view (marker weights)")
    ax.fill_between(t, 0, 1, where=~tracking, color="0.85", label="not tracking")
    ax.set_xlabel("time (s)"); ax.set_ylabel("score"); ax.set_ylim(0, 1); ax.legend(); fig.tight_layout()
    fig.savefig(out_dir / "pcm_score.png", dpi=100); plt.close(fig)

    fig = plt.figure(figsize=(7, 7))
    ax3 = fig.add_subplot(projection="3d")
    for name in ("pelvis", "nose", "left_wrist", "right_wrist", "left_ankle", "right_ankle"):
        p = kp[:, INDEX[name]]
        ax3.plot(p[:, 0], p[:, 1], p[:, 2], label=name)
    last = np.nonzero(np.isfinite(kp).all(axis=(1, 2)))[0]
    if last.size:
        q = kp[last[-1]]
        for a, b in LIMBS:
            ax3.plot(*np.stack([q[INDEX[a]], q[INDEX[b]]]).T, color="k", lw=1)
    ax3.set_xlabel("x (m)"); ax3.set_ylabel("y (m)"); ax3.set_zlabel("z (m)"); ax3.legend(fontsize=7)
    fig.tight_layout(); fig.savefig(out_dir / "trajectories_3d.png", dpi=100); plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    for name, (a, b) in BONES.items():
        L = np.linalg.norm(kp[:, INDEX[a]] - kp[:, INDEX[b]], axis=-1)
        ax.plot(t, L * 100, label=name)
    ax.set_xlabel("time (s)"); ax.set_ylabel("length (cm)"); ax.legend(fontsize=6, ncol=3); fig.tight_layout()
    fig.savefig(out_dir / "bone_lengths.png", dpi=100); plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 3.5))
    kps = list(per_kp)
    mat = np.array([[np.nanmedian(err[:, c, INDEX[k]]) if np.isfinite(err[:, c, INDEX[k]]).any() else np.nan for k in kps]
                    for c in range(len(rig))])
    im = ax.imshow(mat, cmap="viridis", aspect="auto")
    ax.set_xticks(range(len(kps)), kps, rotation=70, fontsize=7); ax.set_yticks(range(len(rig)), rig.names)
    fig.colorbar(im, label="median px"); fig.tight_layout(); fig.savefig(out_dir / "reprojection_error.png", dpi=100)
    plt.close(fig)

    from ...method.time_offsets import camera_time_offsets

    offsets = camera_time_offsets(rig, rec["uv"], rec["w"])
    summary = {
        "frames": int(len(t)),
        "tracking_frames": int(tracking.sum()),
        "first_tracking_s": float(t[tracking][0]) if tracking.any() else None,
        "median_reprojection_px": median_all,
        "median_reprojection_px_first_ik": median_raw,
        "landmarks": landmarks,
        "median_reprojection_px_free_triangulation": median_free,
        "median_reprojection_px_same_samples": median_same,
        "median_reprojection_px_body_no_face": median_body,
        "median_reprojection_px_body_no_face_free_triangulation": median_body_free,
        "reprojection_px_per_camera": per_cam,
        "reprojection_px_per_keypoint": per_kp,
        "bone_lengths": bones,
        "time_offsets_frames": {o.camera: o.frames for o in offsets},
        "out_of_step": [o.describe(FPS) for o in offsets if o.out_of_step],
        "timing": timing,
        **info,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    np.savez_compressed(out_dir / "recording.npz",
                        **{k: np.asarray(v) for k, v in rec.items() if k not in ("links", "node_timing")})
    md = [
        "# vmocap demo: Pose2Sim Demo_SinglePerson", "",
        f"{summary['frames']} frame sets at {FPS:.0f} fps, 4 cameras 1088x1920 (cam01/cam02 videos are "
        "stored 1080 wide, cropped at the right). Tracking in "
        f"{summary['tracking_frames']} frames (from t = {summary['first_tracking_s']} s). Run: "
        f"{info.get('mode', 'in-process pipeline')}; frame sets processed: {info.get('processed_frames', summary['frames'])}.", "",
        f"**Median reprojection error** against the CNN's confident 2D keypoints (PCM centroids, peak >= 0.5), "
        f"all cameras and keypoints, of the skeleton at the CNN's landmarks (the first IK, before the low-pass "
        f"filter: the skeleton fed back): **{median_raw:.1f} px** (target <= 12 px); of the output: {median_all:.1f} px"
        + (f" (its keypoints are joint centres, which the landmark model `{landmarks}` puts 2-4 cm from where the CNN "
           "puts its keypoints). " if landmarks != "none" else ". ")
        + f"Reference on the same samples: free "
        f"per-frame triangulation of the same 2D keypoints (no skeleton, no filter) reprojects with "
        f"{median_free:.1f} px (ours {median_same:.1f} px). Without the 5 face keypoints: ours "
        f"{median_body:.1f} px, free triangulation {median_body_free:.1f} px (the face keypoints hang on a "
        "rigid head that pivots at the shoulder midpoint, BlazePose having no neck keypoint).", "",
        "| camera | median px | time offset (frame sets, from the 2D keypoints) |", "|---|---|---|",
        *[f"| {k} | {v:.1f} | {o.frames:+.1f} |" for (k, v), o in zip(per_cam.items(), offsets)], "",
        *([f"Out of step? {line}." for line in summary["out_of_step"]] + [""] if summary["out_of_step"] else []),
        "| keypoint | median px | free triangulation px |", "|---|---|---|",
        *[f"| {k} | {v:.1f} | {free_kp.get(k, float('nan')):.1f} |" for k, v in per_kp.items()], "",
        "Bone lengths of the output while tracking (the skeleton keeps its links constant):", "",
        "| bone | mean (m) | std (mm) | range (mm) |", "|---|---|---|---|",
        *[f"| {k} | {v['mean_m']:.3f} | {v['std_mm']:.2f} | {v['range_mm']:.2f} |" for k, v in bones.items()], "",
        "Time per frame set (this machine, shared CPU):", "",
        "| stage | mean ms | median ms | p95 ms |", "|---|---|---|---|",
        *[f"| {k} | " + " | ".join(f"{v[c]:.1f}" if np.isfinite(v[c]) else "n/a" for c in ("mean_ms", "median_ms", "p95_ms")) + " |"
          for k, v in timing.items()], "",
        "Files: " + ", ".join(sorted(p.name for p in out_dir.iterdir() if p.is_file())) + ".",
    ]
    (out_dir / "report.md").write_text("\n".join(md) + "\n")
    return summary
