"""The people look's detector searches (people_look.py): what a search looks at and what it
finds, apart from when it runs, so that it can run in the frame set's own time (offline, lockstep)
or beside the frame sets (a free-running graph: pcm/background.py), on a copy of their images.

The detector, a one-person model, finds the most prominent people of an image: the people
already tracked are greyed out of the images first (`hidden`), and a second look ("again") greys
the people the first look just found (`detections_greyed`). A detection that a tracked person's
pelvis projects onto is theirs (`explained`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Sequence

import cv2
import numpy as np

from ..cameras.projection import Rig
from ..pcm.choice import AGREE_FRACTION, choose_subject, detection_arrays
from ..pcm.detector import Detection, PoseDetector, nms
from .occlusion import GREY, others_greyed

SearchKind = Literal["waiting", "newcomers", "glance", "counting", "again"]  # what a search is for (PeopleLook._plan)
# a detection found again in a later frame set (found_again) lies within this many of its hip-to-head
# lengths (about half a body height) of where it was: a walker's half second, not the next person
REFIND_REACH = 1.5
# images, turned, closer -> per image the people found (PoseDetector.find_people)
Detect = Callable[[Sequence[np.ndarray | None], bool, bool], list[list[Detection]]]


@dataclass
class Search:
    """One search: the frame set's images (copies when it runs beside the frame sets), the tracked
    bodies to grey, whose detections are theirs, and how closely to look."""

    kind: SearchKind
    stamp_ns: int
    images: list
    skeletons: np.ndarray  # (P, 25, 3) the tracked bodies, greyed out of the images
    pelvises: np.ndarray  # (Q, 3) the people whose detections are theirs (explained)
    turned: bool  # the turned look where nobody is found (a lying person)
    closer: bool  # the closer look where nobody or a small person is found
    fill: bool = False  # the closer look only in the cameras that found nobody while another found someone
    # "again": per camera the first look's detections left and those given out; the people found
    # before it who were given none (they may be whom the first look's people hid)
    first: list | None = None
    placed: list | None = None
    unplaced: frozenset[int] = frozenset()


def run_search(seen: Rig, detect: Detect, search: Search) -> list[list[Detection]]:
    """Per camera, the detections nobody tracked explains; for "again", merged into the first
    look's (the cameras it looked at again replaced)."""
    shown = hidden(seen, search.images, search.skeletons)
    left = explained(seen, detect(shown, search.turned, search.closer), search.pelvises)
    empty = [c for c, d in enumerate(left) if not d and shown[c] is not None]
    if search.fill and empty and len(empty) < sum(im is not None for im in shown):
        closer = explained(seen, detect([shown[c] if c in empty else None for c in range(len(shown))], False, True),
                           search.pelvises)
        left = [closer[c] if c in empty else d for c, d in enumerate(left)]
    if search.first is not None and search.placed is not None:
        left = [left[c] if search.placed[c] else d for c, d in enumerate(search.first)]
    return left


def explained(rig: Rig, found: Sequence[Sequence[Detection]], pelvises: np.ndarray) -> list[list[Detection]]:
    """Per camera, the detections no tracked person (pelvises (P, 3)) projects onto: the
    detection's hip within AGREE_FRACTION of its hip-to-head length of a projected pelvis
    (pcm/choice.py's rule for one person's detections in two cameras)."""
    if len(pelvises) == 0:
        return [list(d) for d in found]
    uv, front = rig.project(np.asarray(pelvises, dtype=np.float64))  # (C, P, 2), (C, P)
    out: list[list[Detection]] = []
    for c, (dets, hips, reach) in enumerate(zip(found, *detection_arrays(found)[:2])):
        if not dets:
            out.append([])
            continue
        dist = np.linalg.norm(hips[:, None] - uv[c][None], axis=-1)  # (n, P)
        taken = (front[c][None] & (dist < AGREE_FRACTION * np.maximum(reach[:, None], 1e-6))).any(axis=1)
        out.append([d for d, t in zip(dets, taken) if not t])
    return out


def hidden(rig: Rig, images: Sequence[np.ndarray | None], skeletons: np.ndarray) -> list:
    """The images with each skeleton's ((P, 25, 3) keypoints) silhouette greyed
    (occlusion.others_greyed): the person detector finds the most prominent people of an image
    and misses a smaller one beside them (the BlazePose detector is a one-person model), so the
    people already tracked are taken out of the search for others. Their silhouettes, not their
    boxes: from most cameras a person standing beside a tracked one lies inside that one's box."""
    if len(skeletons) == 0:
        return list(images)
    greyed = others_greyed(rig, images, skeletons, [None])
    return [greyed.get((0, c), im) for c, im in enumerate(images)]


BODY_WIDTH = 0.45  # a standing body's half-width over its hip-to-head length, arms down, with room to spare


def detections_greyed(images: Sequence[np.ndarray | None], found: Sequence[Sequence[Detection]]) -> list:
    """The images (copies where drawn on) with each of `found`'s detections (per camera)
    greyed where the body stands: people found, not tracked yet, have no skeleton whose silhouette
    `hidden` could grey. An ellipse about the detection's hip centre, along its hip-to-head axis,
    that axis' length either way and BODY_WIDTH of it across (not the detector's whole circle,
    which holds whoever stands behind or beside them too)."""
    out = list(images)
    for c, dets in enumerate(found):
        image = out[c]
        if image is None or not dets:
            continue
        im = image.copy()
        for d in dets:
            hip, axis = d.keypoints[0], d.keypoints[1] - d.keypoints[0]
            length = float(np.linalg.norm(axis))
            angle = float(np.degrees(np.arctan2(axis[1], axis[0])))
            cv2.ellipse(im, (int(round(hip[0])), int(round(hip[1]))),
                        (int(np.ceil(length)), int(np.ceil(BODY_WIDTH * length))), angle, 0, 360, (GREY,) * 3, -1)
        out[c] = im
    return out


def found_again(seen: Rig, detector: PoseDetector, images: Sequence[np.ndarray | None], skeletons: np.ndarray,
                pelvises: np.ndarray, left: list[list[Detection]], greyed: list | None = None) -> list[list[Detection]]:
    """A search's detections of an earlier frame set (made beside the frame sets), found again
    in `images`: one zoomed detector run per detection, in a region centred on it (a person
    walks out of a crop placed where they were a few frame periods ago; the whole search again
    would cost those periods again), the tracked bodies (`skeletons`) greyed and the detections
    `greyed` (per camera: those a second look was made without). The detection nearest where
    it was, within REFIND_REACH of its hip-to-head length, is theirs; one not found again is
    dropped (the next search looks again); those the tracked `pelvises` explain are theirs."""
    shown = hidden(seen, images, skeletons)
    if greyed is not None:
        shown = detections_greyed(shown, greyed)
    cams = [c for c, dets in enumerate(left) for _ in dets if shown[c] is not None]
    was = [d for c, dets in enumerate(left) for d in dets if shown[c] is not None]
    out: list[list[Detection]] = [[] for _ in left]
    if not cams:
        return out
    for c, d, dets in zip(cams, was, detector.detect_zoomed([shown[c] for c in cams], [d.keypoints[0] for d in was])):
        if not dets:
            continue
        moved = np.linalg.norm(np.array([e.keypoints[0] for e in dets]) - d.keypoints[0], axis=1)
        best = int(np.argmin(moved))
        if moved[best] <= REFIND_REACH * np.linalg.norm(d.keypoints[1] - d.keypoints[0]):
            out[c].append(dets[best])
    for c, dets in enumerate(out):  # two regions of a camera may find one person
        if len(dets) > 1:
            keep = nms(np.array([d.box for d in dets]), np.array([d.score for d in dets]), detector.iou_threshold)
            out[c] = [dets[i] for i in keep]
    return explained(seen, out, pelvises)


def people_in(seen: Rig, found: list[list[Detection]]) -> int:
    """How many people the detections make, grouped across cameras as newcomers are."""
    n = 0
    for _ in range(sum(len(d) for d in found)):  # each person takes at least one detection
        point = choose_subject(seen, found, None).point
        if point is None:
            break
        n += 1
        found = explained(seen, found, point[None])
    return n
