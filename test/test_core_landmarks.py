"""Landmark offsets (landmarks.py): a PCM model whose keypoints are not joint centres."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from vmocap_core.apps.bench.accuracy import default_motions, prepare
from vmocap_core.keypoints import INDEX
from vmocap_core.method.config import ConfigError, PipelineConfig
from vmocap_core.method.init import fit_skeleton, frame_poses
from vmocap_core.method.landmarks import SEGMENT, from_left, learn_offsets, load_landmarks
from vmocap_core.method.pipeline import Pipeline
from vmocap_core.pcm.synthetic import SyntheticPcmSource, benchmark_rig

# Offsets of the size BlazePose's have (mm, left side, segment frames): hips forward and out,
# shoulders inward and down, knees and ankles up their segment.
OFFSETS_MM = {"left_hip": [35, 12, 15], "left_shoulder": [20, -25, -35], "left_knee": [0, 0, 15],
              "left_ankle": [0, 0, 25], "left_elbow": [0, 0, 0], "left_wrist": [0, 0, 0]}


@pytest.fixture(scope="module")
def walk_with_landmarks():
    """The walk clip's joint centres, and landmarks at OFFSETS_MM from them on the segments of
    our skeleton fitted to those centres."""
    m = prepare(next(f for f in default_motions() if f.stem == "walk"))
    truth = m.positions[:130]
    fitted = fit_skeleton(truth, 1.0)
    assert fitted is not None
    sk, fit = fitted
    poses = frame_poses(sk, truth, fit.q)
    model = from_left("test", OFFSETS_MM)
    landmarks = np.array([p + model.correction(sk, q) for p, q in zip(truth, poses)])
    landmarks[:, ~m.present] = np.nan
    return m, truth, landmarks, sk, poses, model


def test_learnt_offsets_are_the_offsets_put_in(walk_with_landmarks):
    _, truth, landmarks, sk, poses, _ = walk_with_landmarks
    samples = learn_offsets(sk, np.array(poses), landmarks, truth)
    for k, v in samples.items():
        assert np.abs(np.median(v, axis=0) * 1e3 - OFFSETS_MM[k]).max() < 0.5, k


def test_tracker_with_the_landmark_model_outputs_joint_centres(tmp_path, walk_with_landmarks):
    """Synthetic PCMs drawn at the landmarks: without the model the output sits on the
    landmarks; with it, on the joint centres, as well as when the PCMs are drawn at the joint
    centres. The feedback (raw keypoints) stays on the landmarks, where the lattice search
    must look."""
    m, truth, landmarks, _, _, _ = walk_with_landmarks
    path = tmp_path / "lm.yaml"
    path.write_text(yaml.safe_dump({"name": "test", "offsets_mm": OFFSETS_MM}))
    rig = benchmark_rig(np.nanmean(truth[:, 0], axis=0))
    scored = [INDEX[k] for k in SEGMENT if m.present[INDEX[k]]]
    err, feedback_err = {}, {}
    for spec, drawn in (("centres", truth), ("none", landmarks), (str(path), landmarks)):
        src = SyntheticPcmSource(rig, drawn, m.present, seed=1)
        tracker = Pipeline(rig, PipelineConfig.of(fps=60.0, landmarks="none" if spec == "centres" else spec))
        out, raw = [], []
        for t in range(len(truth)):
            r = tracker.step(src.render(t)).skeleton
            out.append(r.keypoints if r.status == "tracking" else np.full_like(truth[0], np.nan))
            raw.append(r.raw_keypoints if r.status == "tracking" else np.full_like(truth[0], np.nan))
        ok = np.isfinite(np.array(out)[:, scored]).all(axis=(1, 2))
        assert ok.sum() > 60, spec
        e = np.linalg.norm(np.array(out)[ok][:, scored] - truth[ok][:, scored], axis=-1)
        f = np.linalg.norm(np.array(raw)[ok][:, scored] - drawn[ok][:, scored], axis=-1)
        err[spec], feedback_err[spec] = e.mean() * 1e3, f.mean() * 1e3
    # the model brings the output within 3 mm of the PCMs-at-the-joint-centres run (the noise
    # model's own error, ~25 mm), which a model-less tracker misses by the offsets (~10 mm here)
    assert err[str(path)] < err["centres"] + 3.0 < err["none"] - 5.0, err
    assert feedback_err[str(path)] < feedback_err["centres"] + 3.0, feedback_err


def test_landmark_models_load_or_say_why(tmp_path):
    assert load_landmarks("none") is None
    shipped = load_landmarks("blazepose")
    assert shipped is not None and np.abs(shipped.offsets).max() < 0.1  # centimetres, not metres
    with pytest.raises(ConfigError, match="no such file"):
        PipelineConfig.of(landmarks=str(tmp_path / "missing.yaml"))
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"offsets_mm": {"nose": [0, 0, 0]}}))
    with pytest.raises(ConfigError, match="left_"):
        PipelineConfig.of(landmarks=str(bad))


def test_a_pipeline_takes_the_landmarks_of_its_pcm_source():
    from vmocap_core.pcm.providers import SyntheticPcmProvider

    m = next(f for f in default_motions() if f.stem == "walk")
    rig = benchmark_rig(np.zeros(3))

    class Cnn(SyntheticPcmProvider):
        landmarks = "blazepose"

    assert Pipeline(rig, PipelineConfig.of(fps=60.0), SyntheticPcmProvider(rig, m, 60.0)).config.skeleton.landmarks == "none"
    assert Pipeline(rig, PipelineConfig.of(fps=60.0), Cnn(rig, m, 60.0)).config.skeleton.landmarks == "blazepose"
    assert Pipeline(rig, PipelineConfig.of(fps=60.0, landmarks="none"), Cnn(rig, m, 60.0)).config.skeleton.landmarks == "none"
    assert Pipeline(rig, PipelineConfig.of(fps=60.0)).skeleton._landmarks is None  # markers from elsewhere: "auto" = none


def _waist_angle_deg(sk, q) -> float:
    j = sk.model.joints[sk.model.getJointId("waist")]
    x, y, z, w = q[j.idx_q:j.idx_q + 4]
    return float(np.degrees(2 * np.arctan2(np.linalg.norm([x, y, z]), abs(w))))


def test_identification_on_landmarks_keeps_the_trunk_straight(walk_with_landmarks):
    """A CNN without a neck landmark: the skeleton identified on its landmarks puts the
    shoulder joint centres where they are and stands straight (the walk's trunk is), rather
    than bending its waist to bring shoulders placed too high back to the data."""
    _, truth, landmarks, sk_truth, poses, model = walk_with_landmarks
    cnn = landmarks[:40].copy()
    cnn[:, [INDEX["neck"], INDEX["pelvis"]]] = np.nan
    fitted = fit_skeleton(cnn, 0.05, landmarks=model)
    assert fitted is not None
    sk, fit = fitted
    shoulders = [INDEX["left_shoulder"], INDEX["right_shoulder"]]
    err = np.linalg.norm(fit.keypoints[shoulders] - truth[39, shoulders], axis=1)
    assert err.max() < 0.01, err
    assert _waist_angle_deg(sk, fit.q) < _waist_angle_deg(sk_truth, poses[39]) + 5.0


def test_trunk_landmarks_do_not_follow_the_waist_bend():
    """A trunk shorter than the skeleton's is fitted by bending the waist forwards or
    backwards: both bends put pelvis, hips, neck and shoulders in the same places, so the hip
    and shoulder landmarks, which ride on trunk frames of those keypoints, must not move."""
    from vmocap_core.method.skeleton import BodyDimensions, Skeleton

    sk = Skeleton(BodyDimensions(shoulder_drop=0.0, shoulder_forward=0.0))
    model = from_left("test", OFFSETS_MM)
    root = sk.model.joints[sk.model.getJointId("root")].idx_q + 3
    waist = sk.model.joints[sk.model.getJointId("waist")].idx_q
    bends = []
    for phi in (0.4, -0.4):  # root pitched by phi, waist bent by -2 phi: the same neck
        q = sk.neutral()
        q[root:root + 4] = [0.0, np.sin(phi / 2), 0.0, np.cos(phi / 2)]
        q[waist:waist + 4] = [0.0, np.sin(-phi), 0.0, np.cos(-phi)]
        bends.append((sk.keypoint_positions(q), model.correction(sk, q)))
    trunk = [INDEX[k] for k in ("pelvis", "neck", "left_hip", "right_hip", "left_shoulder", "right_shoulder")]
    np.testing.assert_allclose(bends[0][0][trunk], bends[1][0][trunk], atol=1e-9)
    rows = [INDEX[k] for k in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")]
    assert np.abs(bends[0][1][rows]).max() > 0.02
    np.testing.assert_allclose(bends[0][1][rows], bends[1][1][rows], atol=1e-9)
