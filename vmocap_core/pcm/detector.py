"""BlazePose person detector (pose_detection): first-frame crops for the landmark model.

Input: the whole image letterboxed into 224 x 224 (padding split evenly), RGB in [-1, 1].
Outputs: `Identity` (2254 x 12: box centre/size + 4 keypoints, raw offsets) and `Identity_1`
(2254 score logits) for MediaPipe's SSD anchors of this model: feature strides 8, 16, 32, 32, 32
with 2 fixed-size anchors per layer, the three stride-32 layers sharing one 7 x 7 grid
(28*28*2 + 14*14*2 + 7*7*6 = 2254). Decoding (x first): centre = raw / 224 + anchor centre,
size = raw / 224, in letterbox-normalized units. Several anchors fire per person, hence NMS.
Keypoint 0 is the hip centre, keypoint 1 a point above the head that fixes scale and rotation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ModelError
from . import fetch
from .crops import tilt_from_points
from .model import DEFAULT_THREADS, check_image, letterbox_affine, read_model, with_uint8_input
from .runner import DEFAULT_PARALLEL, Runner
from .views import invert_affine

INPUT = 224
STRIDES = (8, 16, 32, 32, 32)
ANCHORS_PER_LAYER = 2
CROP_SCALE = 1.25  # MediaPipe's ROI enlargement around 2 * |kp1 - kp0|
TILE_FRACTION = 2.0 / 3.0  # tile side / shorter image side of the zoomed pass (detect_zoomed)


def ssd_anchors(size: int = INPUT, strides: Sequence[int] = STRIDES, per_layer: int = ANCHORS_PER_LAYER) -> np.ndarray:
    """(N, 2) anchor centres (x, y) in [0, 1], in the order of the model's outputs."""
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:  # layers of one stride share a grid
            j += 1
        n = -(-size // strides[i])
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        out.append(np.repeat(grid, per_layer * (j - i), axis=0))
        i = j
    return np.concatenate(out)


@dataclass
class Detection:
    """One detected person in one image (pixels, OpenCV convention)."""

    score: float  # sigmoid of the logit
    box: np.ndarray  # (4,) x0, y0, x1, y1
    keypoints: np.ndarray  # (4, 2); 0 = hip centre, 1 = scale/rotation point above the head

    def crop(self) -> tuple[np.ndarray, float, float]:
        """MediaPipe's landmark crop: centre kp0, side 2 * |kp1 - kp0| * 1.25, rotation such
        that kp0 -> kp1 points up in the crop. Returns centre (2,), side, rotation."""
        kp0, kp1 = self.keypoints[0], self.keypoints[1]
        side = 2.0 * float(np.linalg.norm(kp1 - kp0)) * CROP_SCALE
        return kp0.copy(), side, float(tilt_from_points(kp0, kp1))


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one (4,) box with (N, 4) boxes (x0, y0, x1, y1)."""
    lt = np.maximum(box[:2], boxes[:, :2])
    rb = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
    area = lambda b: np.prod(np.clip(b[..., 2:] - b[..., :2], 0, None), axis=-1)  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-12)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, best first."""
    order = np.argsort(-scores)
    keep = []
    while order.size:  # loops once per kept person, not per anchor
        i = order[0]
        keep.append(i)
        order = order[1:][iou(boxes[i], boxes[order[1:]]) <= iou_threshold]
    return np.array(keep, dtype=np.intp)


def turned(A: np.ndarray, quarter_turns: np.ndarray) -> np.ndarray:
    """(N, 2, 3) image -> input affines followed by a turn of the input by quarter_turns[n] x 90
    degrees counter-clockwise (as seen on screen, y down) about the input's centre."""
    k = np.asarray(quarter_turns) % 4
    cos, sin = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
    R = np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], -2)  # (N, 2, 2), y down
    c = (INPUT - 1) / 2.0
    out = np.empty_like(A)
    out[:, :, :2] = R @ A[:, :, :2]
    out[:, :, 2] = np.einsum("nij,nj->ni", R, A[:, :, 2] - c) + c
    return out


def tiles(width: int, height: int, fraction: float = TILE_FRACTION) -> np.ndarray:
    """(K, 4) square tiles x0, y0, x1, y1 covering a width x height image, side `fraction` of
    the shorter image side, overlapping by half a tile (a person up to half a tile tall lies
    wholly inside one of them)."""
    side = max(int(round(min(width, height) * fraction)), 1)
    step = side / 2

    def starts(extent: int) -> np.ndarray:
        n = int(np.ceil(max(extent - side, 0) / step)) + 1
        return np.round(np.linspace(0, max(extent - side, 0), n)).astype(np.int64)

    y0, x0 = np.meshgrid(starts(height), starts(width), indexing="ij")
    x0, y0 = x0.ravel(), y0.ravel()
    return np.stack([x0, y0, x0 + side, y0 + side], axis=1)


class PoseDetector:
    """pose_detection.onnx: `detect(images)` -> per image, detections sorted by score."""

    def __init__(self, path: Path | str | None = None, threads: int = DEFAULT_THREADS,
                 min_score: float = 0.5, iou_threshold: float = 0.3, parallel: str = DEFAULT_PARALLEL) -> None:
        self.path = Path(path or fetch.model_path("pose_detection"))
        model = with_uint8_input(read_model(self.path), True, 2.0 / 255.0, -1.0, True)
        self.runner = Runner(model, threads, parallel, self.path)
        self.min_score = float(min_score)
        self.iou_threshold = float(iou_threshold)
        self.anchors = ssd_anchors()

    def sample(self, images: Sequence[np.ndarray], regions: np.ndarray | None = None,
               quarter_turns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Letterboxed (N, 224, 224, 3) uint8 BGR batch and the (N, 2, 3) image -> input affines.
        regions (N, 4) integer x0, y0, x1, y1: the part of each image letterboxed (default: all);
        quarter_turns (N,): the input turned by that many quarter turns counter-clockwise about
        its centre (the square input holds a turned letterbox whole)."""
        import cv2

        checked = [check_image(im, i) for i, im in enumerate(images)]
        if regions is None:
            regions = np.array([[0, 0, im.shape[1], im.shape[0]] for im in checked])
        regions = np.asarray(regions, dtype=np.int64).reshape(len(checked), 4)
        A = np.array([letterbox_affine(int(x1 - x0), int(y1 - y0), INPUT, INPUT) for x0, y0, x1, y1 in regions])
        A[:, :, 2] -= np.einsum("nij,nj->ni", A[:, :, :2], regions[:, :2].astype(np.float64))  # region origin
        if quarter_turns is not None:
            A = turned(A, np.asarray(quarter_turns))
        batch = np.empty((len(checked), INPUT, INPUT, 3), dtype=np.uint8)
        for k, im in enumerate(checked):
            cv2.warpAffine(im, A[k], (INPUT, INPUT), dst=batch[k], flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
        return batch, A

    def preprocess(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Float input of the original network (RGB in [-1, 1]), for reference implementations."""
        batch, A = self.sample(images)
        return np.ascontiguousarray(batch[..., ::-1].astype(np.float32) * np.float32(2.0 / 255.0) - np.float32(1.0)), A

    def detect(self, images: Sequence[np.ndarray], regions: np.ndarray | None = None,
               quarter_turns: np.ndarray | None = None) -> list[list[Detection]]:
        """Per image (H, W, 3) uint8 BGR / (H, W) mono: people found, best first (maybe none).
        regions (N, 4): look only in this part of each image (x0, y0, x1, y1; see sample);
        quarter_turns (N,): look at each image turned (see sample); results in image pixels."""
        if len(images) == 0:
            return []
        x, A = self.sample(images, regions, quarter_turns)
        raw, logits = self.runner.run(["Identity", "Identity_1"], x)
        if raw.shape[1:] != (len(self.anchors), 12):
            raise ModelError(f"{self.path}: output shape {raw.shape}, expected (N, {len(self.anchors)}, 12)")
        scores = 1.0 / (1.0 + np.exp(-np.clip(logits[..., 0].astype(np.float64), -100.0, 100.0)))
        # letterbox-normalized -> input pixels (edge convention * 224 -> centre convention)
        pts = raw.reshape(len(x), -1, 6, 2).astype(np.float64) / INPUT
        pts[:, :, [0, 2, 3, 4, 5]] += self.anchors[None, :, None, :]
        centre, half = pts[:, :, 0], pts[:, :, 1] / 2
        corners = np.stack([centre - half, centre + half], axis=2)  # (B, N, 2, 2)
        allpts = np.concatenate([corners, pts[:, :, 2:]], axis=2) * INPUT - 0.5  # (B, N, 6, 2)
        out: list[list[Detection]] = []
        for k in range(len(x)):
            cand = np.flatnonzero(scores[k] >= self.min_score)
            inv = invert_affine(A[k])
            img_pts = allpts[k, cand] @ inv[:, :2].T + inv[:, 2]  # (n, 6, 2) image pixels
            boxes = np.concatenate([img_pts[:, :2].min(axis=1), img_pts[:, :2].max(axis=1)], axis=1)  # turned: corners swap
            keep = nms(boxes, scores[k, cand], self.iou_threshold) if cand.size else np.empty(0, np.intp)
            out.append([Detection(float(scores[k, cand[i]]), boxes[i], img_pts[i, 2:]) for i in keep])
        return out

    def detect_turned(self, images: Sequence[np.ndarray]) -> list[list[Detection]]:
        """A look at each image turned by one, two and three quarter turns, one batch: a body
        lying or upside down, which the upright pass misses (the paper turns the CNN's input for
        inverted bodies, III-B). Per image the detections merged by NMS, best first, in image
        pixels (their keypoints give the crop its rotation)."""
        checked = [check_image(im, i) for i, im in enumerate(images)]
        owner = np.repeat(np.arange(len(checked)), 3)
        dets = self.detect([checked[k] for k in owner], quarter_turns=np.tile([1, 2, 3], len(checked))) if checked else []
        return self._merge(dets, owner, len(checked))

    def _merge(self, dets: list[list[Detection]], owner: np.ndarray, n: int) -> list[list[Detection]]:
        """Per image k, the detections of the passes owner == k, merged by NMS, best first."""
        out: list[list[Detection]] = []
        for k in range(n):
            found = [d for i in np.flatnonzero(owner == k) for d in dets[i]]
            if found:
                found = [found[i] for i in nms(np.array([d.box for d in found]), np.array([d.score for d in found]),
                                                self.iou_threshold)]
            out.append(found)
        return out

    def detect_zoomed(self, images: Sequence[np.ndarray], near: Sequence[np.ndarray | None],
                      fraction: float = TILE_FRACTION) -> list[list[Detection]]:
        """A second, zoomed look, one batch: per image, square regions of side `fraction` of the
        shorter image side, i.e. twice the whole-image pass's resolution on a 4:3 image. Where
        `near[k]` (2,) is a point (a person found there by the whole-image pass) one region
        centred on it (kept inside the image); where it is None overlapping tiles covering the
        image (tiles: 6 on 4:3). Per image the detections merged by NMS, best first."""
        checked = [check_image(im, i) for i, im in enumerate(images)]
        regions = []
        for im, p in zip(checked, near):
            h, w = im.shape[:2]
            if p is None:
                regions.append(tiles(w, h, fraction))
                continue
            side = max(int(round(min(w, h) * fraction)), 1)
            x0 = int(np.clip(np.round(p[0] - side / 2), 0, max(w - side, 0)))
            y0 = int(np.clip(np.round(p[1] - side / 2), 0, max(h - side, 0)))
            regions.append(np.array([[x0, y0, x0 + side, y0 + side]]))
        owner = np.repeat(np.arange(len(checked)), [len(r) for r in regions])
        dets = self.detect([checked[k] for k in owner], np.concatenate(regions)) if checked else []
        return self._merge(dets, owner, len(checked))

    def find_people(self, images: Sequence[np.ndarray], turned: bool = True, closer: bool = True) -> list[list[Detection]]:
        """Per image (None: none), the people the detector finds, best first: the whole image,
        then (`closer`) a closer look where it found nobody or a small person, then (`turned`)
        the image turned where still nobody is found."""
        have = [c for c, im in enumerate(images) if im is not None]
        found: list[list] = [[] for _ in images]
        for c, dets in zip(have, self.detect([images[c] for c in have])):
            found[c] = dets
        # A person far from the camera is a few dozen pixels tall in the detector's 224 px input:
        # missed, or found with the hips tens of pixels off (and then a loose crop). Look again
        # at twice the resolution: in tiles over the image where a view found nobody, in one
        # region around the person where it found only one smaller than that region (one extra
        # run, not six: initialization stays cheap), and keep the best of both passes.
        again = [c for c in have if closer and (not found[c] or found[c][0].crop()[1] < TILE_FRACTION * min(images[c].shape[:2]))]
        near = [found[c][0].keypoints[0] if found[c] else None for c in again]
        for c, dets in zip(again, self.detect_zoomed([images[c] for c in again], near)):
            both = found[c] + dets
            if both:
                keep = nms(np.array([d.box for d in both]), np.array([d.score for d in both]), self.iou_threshold)
                found[c] = [both[i] for i in keep]
        # A body lying or upside down: where still nobody is found, look at the image turned.
        lying = [c for c in have if not found[c]] if turned else []
        for c, dets in zip(lying, self.detect_turned([images[c] for c in lying])):
            found[c] = dets
        return found
