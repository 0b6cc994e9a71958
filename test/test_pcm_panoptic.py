"""Real multi-view check on CMU Panoptic frames (5 calibrated HD views with lens distortion,
3 people): PCM peaks of the person nearest a 3D seed, triangulated, reproject into every view;
left and right agree across views. Data: ../shared/data/panoptic_demo (skips when absent)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vmocap_core.cameras.projection import Camera, Rig
from vmocap_core.cameras.rig_file import load_panoptic_cameras
from vmocap_core.errors import ModelError
from vmocap_core.keypoints import INDEX, KEYPOINTS, LOWER_BODY, MIRROR
from vmocap_core.method.triangulation import triangulate
from vmocap_core.pcm import fetch
from vmocap_core.pcm.blazepose import BlazePoseLandmark, rotated_crops
from vmocap_core.pcm.choice import others_near
from vmocap_core.pcm.crops import Crops, crops_from_skeleton
from vmocap_core.pcm.detector import PoseDetector
from vmocap_core.pcm.peaks import camera_keypoints
from vmocap_core.pcm.pipeline import BlazePosePcm

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "panoptic_demo"
NAMES = ["00_03", "00_06", "00_12", "00_13", "00_23"]
FRAME = "00004500"
# Panoptic world (metres after conversion): -y is up, the floor is y = 0. The seed is the hip
# centre of the person walking in front of camera 00_03 in this frame (from a two-view
# triangulation of the detector's hip keypoint).
SEED = np.array([0.87, -0.93, -0.35])


@pytest.fixture(scope="module")
def scene():
    if not (DATA / "camera_parameters.json").exists():
        pytest.skip(f"{DATA} is absent")
    try:
        lm, det = BlazePoseLandmark(), PoseDetector()
    except ModelError:
        try:
            fetch.fetch(quiet=True)
        except ModelError as exc:
            pytest.skip(f"PCM models unavailable (no network?): {exc}")
        lm, det = BlazePoseLandmark(), PoseDetector()
    rig = load_panoptic_cameras(DATA / "camera_parameters.json", NAMES)
    images = [cv2.imread(str(DATA / n / f"{n}_{FRAME}.jpg")) for n in NAMES]
    assert all(im is not None for im in images)
    return rig, images, lm, det


def _standing_body(seed: np.ndarray) -> np.ndarray:
    """A crude upright body at the seed (only pelvis, neck, nose, ankles): enough for crops."""
    kp = np.full((len(KEYPOINTS), 3), np.nan)
    for name, height in {"nose": 1.65, "neck": 1.45, "pelvis": 0.95, "left_ankle": 0.08, "right_ankle": 0.08}.items():
        kp[INDEX[name]] = [seed[0], -height, seed[2]]
    return kp


def _reprojection(rig, pv) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    uv, w = pv.centroids()
    w = w * (pv.presence[:, None] > 0.5)
    X, _ = triangulate(rig, uv, w)
    proj, _ = rig.project(X)
    err = np.where(w > 0, np.linalg.norm(proj - uv, axis=-1), np.nan)  # (C, J)
    return X, err, uv, w


def _report(tag: str, err: np.ndarray) -> None:
    per_view = dict(zip(NAMES, np.nanmedian(err, axis=1).round(1)))
    print(f"{tag}: reprojection error median {np.nanmedian(err):.1f} px, p90 {np.nanpercentile(err, 90):.1f} px, per view {per_view}")


def test_triangulated_pcm_peaks_reproject_and_sides_agree(scene) -> None:
    rig, images, lm, _ = scene
    centre, side, rot, usable = crops_from_skeleton(rig, _standing_body(SEED))
    assert usable.all()
    pv = lm.infer(images, Crops(np.arange(5), centre, side, rot))
    assert (pv.presence > 0.9).all()
    X, err, uv, w = _reprojection(rig, pv)
    _report("crops from a seed body", err)
    assert np.nanmedian(err) < 20.0
    assert (np.nanmedian(err, axis=1) < 45.0).all()
    # the reconstruction is a plausible person around the seed
    assert np.isfinite(X[pv.valid.any(axis=0)]).all()
    assert np.nanmax(np.linalg.norm(X[:, [0, 2]] - SEED[[0, 2]], axis=1)) < 0.6
    assert X[INDEX["nose"], 1] < X[INDEX["left_hip"], 1] < X[INDEX["left_ankle"], 1]  # -y up
    # left/right consistency: mirroring the labels of any one view makes the fit worse
    base = np.nanmean(err)
    for v in range(len(NAMES)):
        uv2, w2 = uv.copy(), w.copy()
        uv2[v], w2[v] = uv[v][MIRROR], w[v][MIRROR]
        X2, _ = triangulate(rig, uv2, w2)
        p2, _ = rig.project(X2)
        swapped = np.nanmean(np.where(w2 > 0, np.linalg.norm(p2 - uv2, axis=-1), np.nan))
        print(f"view {NAMES[v]} left/right mirrored: mean error {swapped:.1f} px vs {base:.1f} px")
        assert swapped > base + 3.0


def test_tracking_crops_from_the_triangulated_skeleton(scene) -> None:
    """Second frame of tracking: crops from the reconstructed skeleton, no detector."""
    rig, images, lm, _ = scene
    centre, side, rot, _ = crops_from_skeleton(rig, _standing_body(SEED))
    X, _, _, _ = _reprojection(rig, lm.infer(images, Crops(np.arange(5), centre, side, rot)))
    X[INDEX["neck"]] = (X[INDEX["left_shoulder"]] + X[INDEX["right_shoulder"]]) / 2
    X[INDEX["pelvis"]] = (X[INDEX["left_hip"]] + X[INDEX["right_hip"]]) / 2
    centre, side, rot, usable = crops_from_skeleton(rig, X)
    assert usable.all() and (np.abs(rot) < 0.6).all()  # people stand: small trunk tilts
    pv = lm.infer(images, Crops(np.arange(5), centre, side, rot))
    _, err, _, _ = _reprojection(rig, pv)
    _report("crops from the triangulated skeleton", err)
    assert np.nanmedian(err) < 20.0


def test_detector_finds_the_seed_person(scene) -> None:
    rig, images, _, det = scene
    hip, _ = rig.project(SEED)  # (C, 2)
    _, side, _, _ = crops_from_skeleton(rig, _standing_body(SEED))  # ~1.25 x the projected height
    found = det.detect(images)
    hits = 0
    for c, dets in enumerate(found):
        d = min((np.linalg.norm(x.keypoints[0] - hip[c]) for x in dets), default=np.inf)
        print(f"{NAMES[c]}: {len(dets)} detection(s), nearest hip centre {d:.0f} px from the seed ({d / side[c]:.2f} x crop side)")
        hits += d < 0.25 * side[c]  # the seed is approximate: within a quarter of the body size
    assert hits >= 4


def _flipped_camera(cam: Camera) -> Camera:
    """The same camera rolled by 180 deg about its optical axis: its image is the original
    rotated by 180 deg, so every person in it is upside down (a real 'inverted' input)."""
    K = cam.K.copy()
    K[0, 2], K[1, 2] = cam.width - 1 - K[0, 2], cam.height - 1 - K[1, 2]
    dist = cam.dist.copy()
    dist[2:4] *= -1  # tangential terms are even in (x, y)
    roll = np.diag([-1.0, -1.0, 1.0])
    return Camera(cam.name, K, dist, roll @ cam.R, roll @ cam.t, cam.width, cam.height)


def test_input_rotation_variants_on_upside_down_views(scene) -> None:
    """Paper III-B on real frames: the 5 views rotated by 180 deg, crops from the skeleton.
    Reference: the reconstruction from the upright views. Measured, not assumed: which
    variant recovers the person (this decides blazepose.DEFAULT_ROTATION)."""
    rig, images, lm, _ = scene
    centre, side, rot, _ = crops_from_skeleton(rig, _standing_body(SEED))
    uv, w = camera_keypoints(lm.infer(images, Crops(np.arange(5), centre, side, rot)), 5)
    X, _ = triangulate(rig, uv, w)
    X[INDEX["neck"]] = (X[INDEX["left_shoulder"]] + X[INDEX["right_shoulder"]]) / 2
    X[INDEX["pelvis"]] = (X[INDEX["left_hip"]] + X[INDEX["right_hip"]]) / 2
    centre, side, rot, _ = crops_from_skeleton(rig, X)
    ref, _ = triangulate(rig, *camera_keypoints(lm.infer(images, Crops(np.arange(5), centre, side, rot)), 5))
    flipped_rig = Rig([_flipped_camera(c) for c in rig])
    flipped = [cv2.rotate(im, cv2.ROTATE_180) for im in images]
    centre, side, tilt, _ = crops_from_skeleton(flipped_rig, X)
    assert (np.abs(tilt) > 2.5).all()  # the trunk points down in every flipped view
    lower = np.isin(np.array(KEYPOINTS), LOWER_BODY)
    scored = np.isfinite(ref).all(axis=1)
    result = {}
    # min_presence=0: measure the heatmaps themselves, even where presence says "nobody"
    raw = BlazePoseLandmark(min_presence=0.0)
    for mode in ("none", "all", "lower_body"):
        pv = raw.infer(flipped, rotated_crops(np.arange(5), centre, side, tilt, mode))
        Xm, _ = triangulate(flipped_rig, *camera_keypoints(pv, 5, min_presence=0.0))
        d = np.linalg.norm(Xm - ref, axis=1) * 100  # cm
        result[mode] = {
            "views": pv.n_views,
            "min_presence": round(float(pv.presence.min()), 3),
            "upper_cm": round(float(np.nanmean(d[scored & ~lower])), 1),
            "lower_cm": round(float(np.nanmean(d[scored & lower])), 1),
        }
    print(f"upside-down Panoptic views, mean 3D distance to the upright reconstruction: {result}")
    assert result["all"]["upper_cm"] < 1.0 and result["all"]["lower_cm"] < 1.0
    assert result["all"]["min_presence"] > 0.9
    assert result["none"]["lower_cm"] > 10.0 and result["none"]["min_presence"] < 0.2
    assert result["lower_body"]["lower_cm"] < 1.0  # the rotated view serves the lower body
    assert result["lower_body"]["upper_cm"] > result["all"]["upper_cm"]


def test_a_camera_mounted_upside_down_among_upright_ones(scene) -> None:
    """Issue 30's bad input: one camera of the rig rolled by 180 deg (its calibration says so),
    the others upright. The pipeline finds the seed person in that view too when it initializes
    from the detector, and crops it turned by the trunk's direction in that image when it
    tracks: its keypoints triangulate with the other views', left and right included."""
    rig, images, _, _ = scene
    turned = 2
    cams = [(_flipped_camera(c) if k == turned else c) for k, c in enumerate(rig)]
    mixed_rig = Rig(cams)
    mixed = [cv2.rotate(im, cv2.ROTATE_180) if k == turned else im for k, im in enumerate(images)]
    pcm = BlazePosePcm(mixed_rig, threads=2)
    found = pcm.infer(mixed, seed=SEED)
    assert turned in found.camera.tolist(), found.camera
    tracked = pcm.infer(mixed, _standing_body(SEED))
    uv, w = camera_keypoints(tracked, len(rig))
    X, _ = triangulate(mixed_rig, uv, w)
    ok = np.isfinite(X).all(axis=1)
    assert ok.sum() >= 15
    # the turned camera's keypoints, each where the others' triangulation projects into its image
    proj = mixed_rig[turned].project(X[ok])[0]
    err = np.linalg.norm(uv[turned][ok] - proj, axis=1)
    print(f"camera {NAMES[turned]} upside down: median reprojection error {np.nanmedian(err):.1f} px")
    assert np.nanmedian(err) < 25.0
    # not mirrored: its left keypoints lie where the left ones project, not where the right ones
    # do (the pairs that camera shows: a keypoint it sees hidden has no peak there)
    shown = ok & np.isfinite(uv[turned]).all(axis=1)
    pairs = [(i, int(MIRROR[i])) for i, a in enumerate(KEYPOINTS) if a.startswith("left") and shown[i] and shown[MIRROR[i]]]
    left, right = (np.array(x) for x in zip(*pairs))
    at = mixed_rig[turned].project(X)[0]
    direct = np.linalg.norm(uv[turned][left] - at[left], axis=1) + np.linalg.norm(uv[turned][right] - at[right], axis=1)
    swapped = np.linalg.norm(uv[turned][left] - at[right], axis=1) + np.linalg.norm(uv[turned][right] - at[left], axis=1)
    print(f"left/right pairs: {len(pairs)}, direct {np.median(direct):.1f} px, swapped {np.median(swapped):.1f} px")
    assert len(pairs) >= 4 and np.median(direct) < np.median(swapped)


def test_pipeline_initializes_with_the_detector_then_tracks(scene) -> None:
    """BlazePosePcm: no skeleton -> detector crops; skeleton -> projected crops, no detector."""
    rig, images, lm, _ = scene
    pcm = BlazePosePcm(rig, threads=2)
    first = pcm.infer(images, stamp_ns=1)
    assert first.n_views >= 4 and (first.presence > 0.9).all() and first.stamp_ns == 1
    # with a seed, every camera's crop is on the seed person: their peaks triangulate together
    seeded = pcm.infer(images, seed=SEED)
    uv, w = camera_keypoints(seeded, len(rig))
    X, resid = triangulate(rig, uv, w)
    print(f"detector crops, seeded: {seeded.n_views} views, median triangulation residual {np.nanmedian(resid):.1f} px")
    assert seeded.n_views >= 4 and np.nanmedian(resid) < 25.0
    assert np.linalg.norm(X[INDEX["left_hip"], [0, 2]] - SEED[[0, 2]]) < 0.4
    body = _standing_body(SEED)
    tracked = pcm.infer(images, body, stamp_ns=2)
    assert tracked.camera.tolist() == [0, 1, 2, 3, 4]  # "all": one view per camera
    uv, w = camera_keypoints(tracked, len(rig))
    X, resid = triangulate(rig, uv, w)
    print(f"pipeline tracking frame: median triangulation residual {np.nanmedian(resid):.1f} px")
    assert np.nanmedian(resid) < 25.0  # 1920x1080 views, people occluding each other
    # explicit tilt (e.g. tracker.trunk_tilt) and the paper's variant: 2 views where tilted
    paper = BlazePosePcm(rig, rotation="lower_body", threads=1)
    pv = paper.infer(images, body, tilt=np.array([0.0, np.pi, 0.0, 0.0, 1.0]))
    assert pv.camera.tolist() == [0, 1, 2, 3, 4, 1, 4]
    # a camera without a frame in this set: no view for it, the others still work
    partial = list(images)
    partial[2] = None
    assert pcm.infer(partial, body).camera.tolist() == [0, 1, 3, 4]
    assert 2 not in pcm.infer(partial).camera.tolist()
    with pytest.raises(ModelError):
        pcm.infer(images[:3], body)
    # nobody in view: zero views, not an error
    black = [np.zeros_like(im) for im in images]
    assert pcm.infer(black).n_views == 0
    with pytest.raises(ModelError):
        BlazePosePcm(rig, rotation="upside")


def test_the_census_of_others_runs_beside_the_frame_sets(scene) -> None:
    """pcm/census.py, as vmocap_pcm runs it: while tracking, the detector's look for people
    besides the subject runs in a low-priority thread on a copy of one camera's image, the
    cameras in turn; a look offered while the last one runs is skipped and the camera keeps its
    turn. Three people on real images: the two others are counted."""
    rig, images, _, _ = scene
    pcm = BlazePosePcm(rig, threads=2, census_every=1, census_background=True)
    body = _standing_body(SEED)
    pelvis = body[INDEX["pelvis"]]
    try:
        pcm.census.offer(images, pelvis)  # the look at the first camera starts (its thread loads a detector)
        pcm.census.offer(images, pelvis)  # offered while that one runs: skipped
        assert pcm.census.wait(60)
        assert pcm.census.looks == 1 and pcm.others_in_view[1:].tolist() == [0] * (len(rig) - 1)
        pcm.infer(images, body)  # as tracking offers them: the cameras in turn
        assert pcm.census.wait(60)
        for _ in range(len(rig) - 2):
            pcm.census.offer(images, pelvis)
            assert pcm.census.wait(60)
    finally:
        pcm.close()
    print(f"others in view per camera: {pcm.others_in_view.tolist()}")
    assert pcm.census.error == "" and pcm.census.looks == len(rig)
    # the same as a look inside the frame set with a detector like the thread's (the detector sees
    # 1 or 2 of the 3 per view here)
    detector = PoseDetector(threads=1)
    inline = [others_near(rig, c, detector.find_people([images[c]], turned=False)[0], pelvis) for c in range(len(rig))]
    assert pcm.others_in_view.tolist() == inline and max(inline) >= 1, (pcm.others_in_view.tolist(), inline)


def test_three_people_tracked_on_real_images(scene) -> None:
    """`vmocap eval panoptic` at the instant where every person is seen by most views: the
    multi-person tracker (issue 32, item 5) tracks all three, each skeleton within 15 px of its
    own views' confident PCM peaks (1920x1080 images)."""
    from vmocap_core.apps.evaluation import panoptic

    res = panoptic.evaluate(DATA, 3, 120, ["00009348"])
    row = res["instants"][0]
    print(row)
    assert row["tracked"] == 3, row
    assert all(e is not None and e < 15.0 for e in row["reprojection_px"]), row
