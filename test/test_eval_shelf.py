"""Shelf evaluation: file readers, PCM rendering, multi-person tracking, scoring (real data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vmocap_core.apps.evaluation import shelf_data
from vmocap_core.apps.evaluation.pcp import PARTS, ShelfScore, part_correct, to_shelf15
from vmocap_core.errors import DetectionFileError
from vmocap_core.keypoints import INDEX

SHELF = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "shelf"
needs_shelf = pytest.mark.skipif(not (SHELF / "gt.txt").exists(), reason="../shared/data/shelf not present")


def _first_frames_text(n_frames: int) -> list[str]:
    """Lines of the header and the first `n_frames` frames of camera 0 (parsed for their
    extent, so the test does not depend on a hard-coded line count)."""
    lines = (SHELF / "detection" / "0.txt").read_text().splitlines()
    frames = shelf_data.read_detections(SHELF / "detection" / "0.txt", 1032, 776, max_frames=n_frames)
    # Count the non-blank lines the frames use: per joint 1 + (3 if n else 0), per limb nA rows.
    used = 1
    for fr in frames:
        used += sum(1 + (3 if len(c) else 0) for c in fr.candidates)
        used += sum(m.shape[0] if m.shape[1] else 0 for m in fr.paf)
    out, count = [], 0
    for ln in lines:
        if count == used:
            break
        out.append(ln)
        count += bool(ln.strip())
    return out


@needs_shelf
def test_truncated_line_names_file_and_line(tmp_path: Path) -> None:
    lines = _first_frames_text(2)
    lines[0] = "4 2"
    # Truncate the x row of the first joint that has two candidates in the second frame.
    first = _first_frames_text(1)
    i = len(first)
    while len(lines[i].split()) != 1 or lines[i].strip() != "2":
        i += 1
    lines[i + 1] = lines[i + 1].split()[0]
    bad = tmp_path / "0.txt"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(DetectionFileError) as err:
        shelf_data.read_detections(bad, 1032, 776)
    msg = str(err.value)
    assert str(bad) in msg and f"line {i + 2}:" in msg and "truncated" in msg


@needs_shelf
def test_missing_frame_is_reported(tmp_path: Path) -> None:
    lines = _first_frames_text(2)
    lines[0] = "4 3"  # the header promises a third frame that is not there
    bad = tmp_path / "1.txt"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(DetectionFileError, match=r"1\.txt: line \d+: file ends where frame 2 of 3"):
        shelf_data.read_detections(bad, 1032, 776)
    # Intact frames parse, with pixels scaled by (size - 1).
    good = tmp_path / "2.txt"
    good.write_text("\n".join(["4 2"] + lines[1:]) + "\n")
    frames = shelf_data.read_detections(good, 1032, 776)
    assert len(frames) == 2 and len(frames[0].paf) == 26
    xy = np.concatenate([c[:, :2] for c in frames[0].candidates])
    assert xy.min() >= 0 and xy[:, 0].max() <= 1031 and xy[:, 1].max() <= 775


@needs_shelf
def test_ground_truth_ids_and_frames() -> None:
    gt = shelf_data.read_gt(SHELF / "gt.txt")
    ids = np.concatenate([g.ids for g in gt])
    assert len(gt) == 301
    assert np.bincount(ids).tolist() == [279, 37, 161, 33]  # README


def test_rendered_pcm_peaks_at_the_detection() -> None:
    from vmocap_core.method.people import PcmRenderer

    kps = np.array([INDEX["left_wrist"], INDEX["nose"]])
    r = PcmRenderer([(1032, 776)] * 2, kps, stride=8, sigma_cells=2.0, radius=6)
    uv = np.zeros((2, 25, 2))
    score = np.zeros((2, 25))
    uv[0, INDEX["left_wrist"]] = (500.3, 301.7)
    score[0, INDEX["left_wrist"]] = 0.8
    uv[1, INDEX["nose"]] = (3.0, 770.0)  # near the border: clipped, still peaks there
    score[1, INDEX["nose"]] = 1.3  # scores above 1 are clipped to the PCM range
    pcm = r.render(uv, score, np.array([True, False]))
    assert pcm.maps.shape == (2, 2, 97, 129)
    peak_uv, peak_val = pcm.peaks()
    assert np.linalg.norm(peak_uv[0, 0] - uv[0, INDEX["left_wrist"]]) <= 8 * np.sqrt(0.5)
    assert 0.7 < peak_val[0, 0] <= 0.8
    assert pcm.maps[1, 1].max() <= 1.0 and pcm.maps[1, 1].max() > 0.9
    assert pcm.valid.tolist() == [[True, True], [False, False]]
    centroid, _ = pcm.centroids(threshold=0.1)
    assert np.linalg.norm(centroid[0, 0] - uv[0, INDEX["left_wrist"]]) < 2.0


def test_pcp_criterion_and_head_mapping() -> None:
    gt = np.zeros((15, 3))
    gt[:, 2] = np.arange(15) * 0.1  # parts of length 0.1 (and longer for non-adjacent joints)
    pred = gt.copy()
    assert part_correct(pred, gt).all()
    pred[11] += [0.3, 0, 0]  # left wrist far off: left lower arm (10-11) wrong only
    ok = part_correct(pred, gt)
    assert not ok[list(PARTS).index("l_lower_arm")] and ok.sum() == 9
    pred[11] = np.nan  # a missing joint makes its parts wrong
    assert not part_correct(pred, gt)[list(PARTS).index("l_lower_arm")]
    # Head joints: upright person facing +x, ears 0.2 m above the shoulders.
    kp = np.full((25, 3), np.nan)
    kp[INDEX["left_shoulder"]] = (0, 0.2, 1.4)
    kp[INDEX["right_shoulder"]] = (0, -0.2, 1.4)
    kp[INDEX["left_ear"]] = (0, 0.08, 1.6)
    kp[INDEX["right_ear"]] = (0, -0.08, 1.6)
    kp[INDEX["nose"]] = (0.1, 0, 1.6)
    s15 = to_shelf15(kp)
    np.testing.assert_allclose(s15[12], (0.015, 0, 1.5), atol=1e-9)
    np.testing.assert_allclose(s15[13], (0.04, 0, 1.66), atol=1e-9)
    score = ShelfScore()
    score.add_frame(np.zeros((0, 15, 3)), np.array([3]), gt[None], np.ones((1, 15), bool))
    assert score.summary()["pcp"]["3"] == 0.0 and score.summary()["missed_frames"]["3"] == 1


@needs_shelf
def test_shelf_30_frames_ours_and_baseline() -> None:
    from vmocap_core.apps.evaluation.shelf import evaluate

    data = shelf_data.load_shelf(SHELF, max_frames=30)
    res = evaluate(data, progress=False)
    # Ids 0 and 2 are in these frames; both must be found and mostly right.
    assert set(res["pcp"]) == {"0", "2", "mean"}
    assert res["pcp"]["mean"] >= 90.0, res["pcp"]
    assert res["baseline"]["pcp"]["mean"] >= 85.0
    assert all(10.0 < v < 120.0 for v in res["mpjpe_mm"].values())
    assert res["person_frames"]["tracker"] > 30  # the lattice trackers took over after init
    assert res["tracks_started"] == 2
    json.dumps(res)


@needs_shelf
def test_person_who_leaves_ends_only_their_tracker() -> None:
    """Shelf's two first people tracked by the multi-person tracker with the detections' look;
    one of them is taken out of every view: the other stays tracked by the same stages, the one
    who left is ended after end_after_s, and nobody new is started."""
    from vmocap_core.apps.evaluation.shelf import FPS, make_tracker, people_per_view

    data = shelf_data.load_shelf(SHELF, max_frames=60)
    rig = data.rig
    tracker = make_tracker(data)
    for f in range(20):
        frame = tracker.step(people_per_view(data, f), int(f * 1e9 / FPS))
    assert len(frame.people) == 2 and all(p.status == "tracking" for p in frame.people)
    leaving, staying = sorted(frame.people, key=lambda p: p.number)
    ended = []
    for f in range(20, 60):
        people = people_per_view(data, f)
        # Remove from every view the 2D person nearest the leaving person's projection.
        uv, _ = rig.project(np.nan_to_num(leaving.last.skeleton.keypoints))
        for c in range(len(rig)):
            if len(people[c]):
                d = np.nanmean(np.where(people[c][..., 2:] > 0, np.linalg.norm(people[c][..., :2] - uv[c][None], axis=-1)[..., None], np.nan)[..., 0], axis=1)
                people[c] = np.delete(people[c], int(np.nanargmin(d)), axis=0)
        frame = tracker.step(people, int(f * 1e9 / FPS))
        ended += frame.ended
        assert [p.number for p in frame.people] == [staying.number], f  # the one who left is not stepped
        gt = data.gt[f]
        s15 = to_shelf15(frame.people[0].last.skeleton.keypoints)
        # The staying person is still tracked, by the same stages, close to one GT person.
        err = np.nanmean(np.linalg.norm(gt.joints - s15[None], axis=-1), axis=1).min()
        assert frame.people[0].status == "tracking" and err < 0.12
    assert ended == [leaving.number]
    assert [s.number for s in tracker.look.seats] == [staying.number]


@needs_shelf
def test_cli_reports_a_broken_detection_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    from vmocap_core.cli import main

    shutil.copy(SHELF / "calibration.json", tmp_path / "calibration.json")
    shutil.copy(SHELF / "gt.txt", tmp_path / "gt.txt")
    (tmp_path / "detection").mkdir()
    for cam in range(5):
        shutil.copy(SHELF / "detection" / f"{cam}.txt", tmp_path / "detection" / f"{cam}.txt")
    lines = (tmp_path / "detection" / "3.txt").read_text().splitlines()
    (tmp_path / "detection" / "3.txt").write_text("\n".join(lines[:1000]) + "\n")  # cut mid-file
    assert main(["eval", "shelf", "--data", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "detection/3.txt: line " in err and "file ends" in err
