"""Which detected person is the subject, in every camera alike, when several are in view.

The detector finds people per image; the crops of one frame set must all show the same person,
or the initialization's triangulation mixes bodies (it then stalls while both are in view, or
starts on whoever the views' best scores favoured). Each pair of cameras' detected hip centres
is triangulated into a candidate; a candidate is a person where its projection falls near a
detection (within AGREE_FRACTION of that detection's hip-to-head length) in at least two
cameras, with that detection's hip-to-head length a person's at the candidate's depth: two
people's hips seen by two cameras give rays that cross somewhere between them, and there the
detections say a body a fraction of a person, or several times one; and the detections' shoulder
centres, triangulated from the same views, lie a trunk's length from the hip centre there
(crossing rays of two people's hips give shoulders anywhere: on the hips, metres off). The
subject is the person nearest to a seed (the last tracked position) or, without one, the one
seen by the most cameras, then the highest summed score, each detection's lowered where its size
at that depth is far from a standing adult's (where such rays cross nearer, the sizes say a body
half a person).
Detections that are not the subject's are others in view.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Sequence

import numpy as np

from ..cameras.projection import Rig
from ..method.triangulation import triangulate
from .detector import Detection

AGREE_FRACTION = 0.5  # detected hip within this x the detection's hip-to-head length: the same person
SUBJECT_REACH_M = 0.9  # the detector's hip-to-head point distance on a standing adult, about
# a detection's hip-to-head length, back-projected to a candidate's depth, within these times
# SUBJECT_REACH_M: the same person (a child or a body foreshortened towards the camera, lying,
# down to a third; a box grown around outstretched arms up to 2.5 times)
REACH_RANGE = (1 / 3, 2.5)
# ranking people: a detection's score counts whole while its size there is within ADULT_BAND
# times an adult's either way, and falls off beyond, by SIZE_SPREAD (log scale; half an adult
# weighs 0.6); within the band the ranking is the detector's scores alone
ADULT_BAND = 4 / 3
SIZE_SPREAD = float(np.log(1.5))
# a person's hip centre to shoulder centre (the detector's keypoints 0 and 2), metres, in 3D: a
# young child's to a tall adult's (about 0.3-0.6), with the detector's keypoints' slack; the
# pose does not matter (lying, bent over), the length is the body's
TRUNK_RANGE_M = (0.2, 0.9)
SHOULDERS = 2  # the detector's keypoint at the shoulder centre


@dataclass
class Choice:
    """The subject's detection per camera (index into that camera's detections, -1: none of
    them is the subject) and the count of the other detections per camera."""

    index: np.ndarray  # (C,) int
    others: np.ndarray  # (C,) int
    point: np.ndarray | None  # (3,) the subject's triangulated hip centre (None: no two views agree)


def detection_arrays(found: Sequence[Sequence[Detection]]) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    hips = [np.array([d.keypoints[0] for d in dets]).reshape(-1, 2) for dets in found]
    reach = [np.array([np.linalg.norm(d.keypoints[1] - d.keypoints[0]) for d in dets]) for dets in found]
    scores = [np.array([d.score for d in dets]) for dets in found]
    return hips, reach, scores


def candidates(rig: Rig, hips: Sequence[np.ndarray]) -> np.ndarray:
    """(M, 3) hip centres triangulated from every pair of detections in every pair of cameras."""
    cams = [c for c, h in enumerate(hips) if len(h)]
    out = []
    for a, b in combinations(cams, 2):  # at most C(C-1)/2 pairs, each vectorized over its detections
        ia, ib = (g.ravel() for g in np.meshgrid(np.arange(len(hips[a])), np.arange(len(hips[b])), indexing="ij"))
        uv = np.zeros((len(rig), len(ia), 2))
        w = np.zeros((len(rig), len(ia)))
        uv[a], uv[b] = hips[a][ia], hips[b][ib]
        w[a] = w[b] = 1.0
        out.append(triangulate(rig, uv, w)[0])
    X = np.concatenate(out) if out else np.zeros((0, 3))
    return X[np.isfinite(X).all(axis=1)]


def _matches(rig: Rig, X: np.ndarray, hips: Sequence[np.ndarray], reach: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(C, M) index of the detection each candidate projects near in each camera (-1: none),
    and that detection's body at the candidate's depth in standing adults (NaN: none)."""
    proj, front = rig.project(X)
    depth = rig.to_camera_frames(X)[..., 2]  # (C, M)
    out = np.full((len(rig), len(X)), -1)
    sizes = np.full((len(rig), len(X)), np.nan)
    for c, (h, r) in enumerate(zip(hips, reach)):
        if len(h) == 0:
            continue
        d = np.linalg.norm(proj[c][:, None] - h[None], axis=-1) / np.maximum(r[None], 1e-6)  # (M, n)
        near = d.argmin(axis=1)
        size = r[near] * depth[c] / (rig[c].focal * SUBJECT_REACH_M)  # the near detection's body at this depth, in adults
        ok = front[c] & (d[np.arange(len(X)), near] < AGREE_FRACTION) & (size >= REACH_RANGE[0]) & (size <= REACH_RANGE[1])
        out[c] = np.where(ok, near, -1)
        sizes[c] = np.where(ok, size, np.nan)
    return out, sizes


def _trunk_length_ok(rig: Rig, found: Sequence[Sequence[Detection]], hips: Sequence[np.ndarray],
                     match: np.ndarray) -> np.ndarray:
    """(M,) whether each candidate's matched detections (match (C, M); hips from
    detection_arrays) put the shoulder centre TRUNK_RANGE_M from the hip centre, both
    triangulated from those views."""
    if match.shape[1] == 0:
        return np.zeros(0, bool)
    w = (match >= 0).astype(float)
    idx = np.maximum(match, 0)
    shoulders = [np.array([d.keypoints[SHOULDERS] for d in dets]).reshape(-1, 2) for dets in found]
    ends = []
    for per_cam in (hips, shoulders):  # (C, M, 2): each camera's matched detection (any, where none: weight 0)
        uv = np.stack([p[idx[c]] if len(p) else np.zeros((match.shape[1], 2)) for c, p in enumerate(per_cam)])
        ends.append(triangulate(rig, uv, w)[0])
    trunk = np.linalg.norm(ends[1] - ends[0], axis=1)
    with np.errstate(invalid="ignore"):
        return (trunk >= TRUNK_RANGE_M[0]) & (trunk <= TRUNK_RANGE_M[1])


def choose_subject(rig: Rig, found: Sequence[Sequence[Detection]], seed: np.ndarray | None = None) -> Choice:
    """The subject's detection in each camera (see the module doc). Fewer than two cameras
    agreeing on anyone: each camera's detection nearest to the seed's projection, or its best."""
    hips, reach, scores = detection_arrays(found)
    X = candidates(rig, hips)
    match, sizes = _matches(rig, X, hips, reach)
    views = (match >= 0).sum(axis=0)
    person = (views >= 2) & _trunk_length_ok(rig, found, hips, match)
    index = np.full(len(rig), -1)
    point = None
    if person.any():
        if seed is not None:
            key = np.where(person, np.linalg.norm(X - np.asarray(seed, dtype=np.float64).reshape(3), axis=1), np.inf)
            best = int(np.argmin(key))
        else:
            beyond = np.maximum(np.abs(np.log(np.where(match >= 0, sizes, 1.0))) - np.log(ADULT_BAND), 0.0)
            prior = np.exp(-0.5 * (beyond / SIZE_SPREAD) ** 2)  # (C, M)
            total = sum(np.where(match[c] >= 0, s[np.maximum(match[c], 0)] * prior[c], 0.0)
                        for c, s in enumerate(scores) if len(s))
            best = int(np.lexsort((-np.asarray(total), -views))[0])  # most views, then the highest summed score
        index = match[:, best].copy()
        # the point from all its views (the candidate came from one pair of them)
        uv = np.stack([hips[c][i] if i >= 0 else np.zeros(2) for c, i in enumerate(index)])[:, None]
        point = triangulate(rig, uv, (index >= 0).astype(float)[:, None])[0][0]
    else:
        for c, h in enumerate(hips):
            if len(h) == 0:
                continue
            if seed is not None:
                uv, front = rig.project(np.asarray(seed, dtype=np.float64).reshape(3))
                index[c] = int(np.argmin(np.linalg.norm(h - uv[c], axis=1))) if front[c] else 0
            else:
                index[c] = 0  # the detector's list is best first
    others = np.array([_distinct_others(h, r, (h[i], r[i]) if i >= 0 else None) for h, r, i in zip(hips, reach, index)])
    return Choice(index, others, point)


def _distinct_others(hips: np.ndarray, reach: np.ndarray, subject: tuple[np.ndarray, float] | None) -> int:
    """People among one camera's detections (hips (n, 2), hip-to-head lengths (n,)) who are
    not the subject (its hip (2,) and hip-to-head length): the detector's passes find one person
    more than once (a whole body, a part of it), hips up to about half the larger hip-to-head
    length apart, so detections that close are one person."""
    near = np.linalg.norm(hips[:, None] - hips[None], axis=-1) < AGREE_FRACTION * np.maximum(reach[:, None], reach[None])
    left = np.ones(len(hips), bool)
    if subject is not None:
        left &= np.linalg.norm(hips - subject[0], axis=1) >= AGREE_FRACTION * np.maximum(reach, subject[1])
    n = 0
    while left.any():  # one pass per distinct person (a handful), each removing its detections
        left &= ~near[np.argmax(left)]
        n += 1
    return n


def others_near(rig: Rig, camera: int, dets: Sequence[Detection], pelvis: np.ndarray) -> int:
    """People among one camera's detections who are not the tracked subject (its pelvis (3,)
    in the world; everyone when it is behind the camera). The subject's hip-to-head length in
    the image is taken as that of SUBJECT_REACH_M upright."""
    uv, front = rig.project(np.stack([pelvis, pelvis + [0.0, 0.0, SUBJECT_REACH_M]]))
    hips, reach, _ = detection_arrays([dets])
    subject = (uv[camera, 0], float(np.linalg.norm(uv[camera, 1] - uv[camera, 0]))) if front[camera].all() else None
    return _distinct_others(hips[0], reach[0], subject)
