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
