"""Conversions between vmocap's data and ROS 2 message dicts (see `cdr`), without ROS.

Both the rclpy nodes and the offline pipeline (`vmocap process`) use these functions, so the
graph and the offline run see bit-identical inputs.

The heatmap messages (PCM): heatmaps.py.

Point clouds (`sensor_msgs/PointCloud2`, markers and keypoints): one point per keypoint of
KEYPOINTS, fields x, y, z, score (FLOAT64, metres, world frame) and id (UINT32, index in
KEYPOINTS), point_step 40, NaN coordinates where a keypoint is unknown (is_dense False).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..cameras.projection import Camera
from ..errors import BagError
from ..keypoints import INDEX, KEYPOINTS

WORLD_FRAME = "world"
CLOUD_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("score", "<f8"), ("id", "<u4"), ("kind", "<u4")])
MARKER_KINDS = ("none", "triangulated", "lattice")
_CLOUD_FIELDS = [
    {"name": "x", "offset": 0, "datatype": 8, "count": 1},
    {"name": "y", "offset": 8, "datatype": 8, "count": 1},
    {"name": "z", "offset": 16, "datatype": 8, "count": 1},
    {"name": "score", "offset": 24, "datatype": 8, "count": 1},
    {"name": "id", "offset": 32, "datatype": 6, "count": 1},
    {"name": "kind", "offset": 36, "datatype": 6, "count": 1},
]
# Virtual markers carry two more fields per keypoint, what a stalled initialization is diagnosed
# from: the triangulation residual (px; NaN where not triangulated) and the cameras whose peaks
# went into it (bit c = camera c of the rig).
MARKERS_DTYPE = np.dtype(CLOUD_DTYPE.descr + [("residual_px", "<f8"), ("cameras", "<u4")])
_MARKERS_FIELDS = _CLOUD_FIELDS + [
    {"name": "residual_px", "offset": 40, "datatype": 8, "count": 1},
    {"name": "cameras", "offset": 48, "datatype": 6, "count": 1},
]
# Lattice markers that follow a fed-back skeleton carry that skeleton's check against the images
# (method/consistency.py): per keypoint the fraction of agreeing views and the cameras that
# disagree and agree, in every point the others in view the census counted + 1 (0: not
# known), and per keypoint the cameras in whose image the lattice centre lay (`inside`);
# recordings made before the `agree`, `others` or `inside` field still read, without it.
CHECKED_V1_DTYPE = np.dtype(MARKERS_DTYPE.descr + [("confidence", "<f8"), ("disagree", "<u4")])
CHECKED_V2_DTYPE = np.dtype(CHECKED_V1_DTYPE.descr + [("agree", "<u4")])
CHECKED_V3_DTYPE = np.dtype(CHECKED_V2_DTYPE.descr + [("others", "<u4")])
CHECKED_DTYPE = np.dtype(CHECKED_V3_DTYPE.descr + [("inside", "<u4")])
_CHECKED_FIELDS = _MARKERS_FIELDS + [
    {"name": "confidence", "offset": 52, "datatype": 8, "count": 1},
    {"name": "disagree", "offset": 60, "datatype": 6, "count": 1},
    {"name": "agree", "offset": 64, "datatype": 6, "count": 1},
    {"name": "others", "offset": 68, "datatype": 6, "count": 1},
    {"name": "inside", "offset": 72, "datatype": 6, "count": 1},
]
# Several people (method/people_stages.py): the markers of one person carry, in every point,
# that person's number + 1 (`person`) after the fields above.
MARKERS_PERSON_DTYPE = np.dtype(MARKERS_DTYPE.descr + [("person", "<u4")])
CHECKED_PERSON_DTYPE = np.dtype(CHECKED_DTYPE.descr + [("person", "<u4")])
_MARKERS_PERSON_FIELDS = _MARKERS_FIELDS + [{"name": "person", "offset": MARKERS_DTYPE.itemsize, "datatype": 6, "count": 1}]
_CHECKED_PERSON_FIELDS = _CHECKED_FIELDS + [{"name": "person", "offset": CHECKED_DTYPE.itemsize, "datatype": 6, "count": 1}]
_CHECKED_ANY = (CHECKED_PERSON_DTYPE, CHECKED_DTYPE, CHECKED_V3_DTYPE, CHECKED_V2_DTYPE, CHECKED_V1_DTYPE)
_INSIDE = (CHECKED_DTYPE, CHECKED_PERSON_DTYPE)  # the layouts with `inside`


# ------------------------------------------------------------------------------- stamps
def stamp(ns: int) -> dict[str, int]:
    ns = int(ns)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def stamp_ns(msg: dict) -> int:
    """Capture time of a message with a header (or a Time dict)."""
    t = msg["header"]["stamp"] if "header" in msg else msg
    return int(t["sec"]) * 1_000_000_000 + int(t["nanosec"])


def header(ns: int, frame_id: str = "") -> dict:
    return {"stamp": stamp(ns), "frame_id": frame_id}


def clock_msg(ns: int) -> dict:
    return {"clock": stamp(ns)}


# ------------------------------------------------------------------------------- images
_IMAGE_ENC = {"mono8": (np.uint8, 1), "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "mono16": (np.uint16, 1)}


def image_msg(image: np.ndarray, ns: int, frame_id: str, encoding: str | None = None, copy: bool = True) -> dict:
    """copy=False: `data` is a read-only byte view of the image (no copy of its megabytes), for
    a caller that never writes to the image again (camera frames, a freshly built stack)."""
    img = np.ascontiguousarray(image)
    if encoding is None:
        encoding = "bgr8" if img.ndim == 3 else "mono8"
    h, w = img.shape[:2]
    return {
        "header": header(ns, frame_id),
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": img.strides[0],
        "data": img.tobytes() if copy else memoryview(img).cast("B").toreadonly(),
    }


def image_array(msg: dict) -> np.ndarray:
    """Image message -> (H, W[, C]) array; rgb8 is converted to BGR; 32FC<N> -> (H, W, N) float32."""
    enc, h, w, step = msg["encoding"], msg["height"], msg["width"], msg["step"]
    dtype: np.dtype
    if enc.startswith("32FC"):
        dtype, ch = np.dtype("<f4"), int(enc[4:])
    elif enc in _IMAGE_ENC:
        dtype, ch = np.dtype(_IMAGE_ENC[enc][0]), _IMAGE_ENC[enc][1]
    else:
        raise BagError(f"unsupported image encoding {enc!r}")
    if msg.get("is_bigendian"):
        dtype = dtype.newbyteorder(">")
    row = w * ch * dtype.itemsize
    data = msg["data"]
    if step < row or len(data) < step * h:
        raise BagError(f"image {w}x{h} {enc}: step {step} / {len(data)} bytes do not fit")
    arr: np.ndarray = np.frombuffer(data, dtype=np.uint8, count=step * h).reshape(h, step)[:, :row]
    arr = arr.view(dtype).reshape(h, w, ch) if ch > 1 or enc.startswith("32FC") else arr.view(dtype).reshape(h, w)
    if enc == "rgb8":
        arr = arr[..., ::-1]
    return arr


def camera_info_msg(camera: Camera, ns: int, K: np.ndarray | None = None, size: tuple[int, int] | None = None,
                    binning: int = 1) -> dict:
    """CameraInfo of a rig camera (or, with K/size, of a heatmap seen as a camera); binning > 1:
    its images come reduced that many times (REP 104: size and K stay the calibration's)."""
    rational = bool(camera.dist[5:].any())
    K = camera.K if K is None else np.asarray(K, dtype=np.float64)
    w, h = (camera.width, camera.height) if size is None else size
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "header": header(ns, camera.name),
        "height": int(h),
        "width": int(w),
        "distortion_model": "rational_polynomial" if rational else "plumb_bob",
        "d": camera.dist if rational else camera.dist[:5],
        "k": K.ravel(),
        "r": np.eye(3).ravel(),
        "p": P.ravel(),
        "binning_x": binning if binning > 1 else 0,
        "binning_y": binning if binning > 1 else 0,
    }


def camera_info_binning(msg: dict) -> tuple[int, int]:
    """(binning_x, binning_y) of a CameraInfo; REP 104: 0 means 1."""
    return max(int(msg.get("binning_x") or 1), 1), max(int(msg.get("binning_y") or 1), 1)


def camera_info_mismatch(msg: dict, camera: Camera, rtol: float = 1e-6, binning: int = 1) -> str | None:
    """Why a received CameraInfo disagrees with the rig and the expected binning (None when it agrees)."""
    bx, by = camera_info_binning(msg)
    if (bx, by) != (binning, binning):
        return f"{camera.name}: CameraInfo says binning {bx}x{by}, the graph's binning is {binning}"
    if (msg["width"], msg["height"]) != (camera.width, camera.height):
        return f"{camera.name}: CameraInfo is {msg['width']}x{msg['height']}, rig says {camera.width}x{camera.height}"
    K = np.asarray(msg["k"], dtype=np.float64).reshape(3, 3)
    if not np.allclose(K, camera.K, rtol=rtol, atol=1e-9):
        return f"{camera.name}: CameraInfo K differs from the rig's"
    d = np.zeros(8)
    given = np.asarray(msg["d"], dtype=np.float64)[:8]
    d[: given.size] = given
    if not np.allclose(d, camera.dist, rtol=rtol, atol=1e-12):
        return f"{camera.name}: CameraInfo D differs from the rig's"
    return None


# ------------------------------------------------------------------------------- clouds
def keypoint_cloud(ns: int, positions: np.ndarray | None, scores: np.ndarray | None = None, kind: str = "none",
                   residual_px: np.ndarray | None = None, cameras: np.ndarray | None = None,
                   frame_id: str = WORLD_FRAME, check: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                   others: int = -1, inside: np.ndarray | None = None, person: int = -1) -> dict:
    """PointCloud2 of the 25 KEYPOINTS (positions None: an empty cloud, e.g. 'lost'); with
    `residual_px` and `cameras` the virtual markers' layout (MARKERS_DTYPE), with `check` too
    (confidence, disagree, agree), `others` (-1: not known) and `inside` (camera bit masks; None:
    not known, written as 0) that of checked markers (CHECKED_DTYPE); markers of one of several
    people (`person` >= 0) with their number after those fields."""
    markers = residual_px is not None
    checked = markers and check is not None
    if markers and person >= 0:
        dtype, fields = (CHECKED_PERSON_DTYPE, _CHECKED_PERSON_FIELDS) if checked else (MARKERS_PERSON_DTYPE,
                                                                                        _MARKERS_PERSON_FIELDS)
    else:
        dtype, fields = ((CHECKED_DTYPE, _CHECKED_FIELDS) if checked else (MARKERS_DTYPE, _MARKERS_FIELDS) if markers
                         else (CLOUD_DTYPE, _CLOUD_FIELDS))
    if positions is None:
        pts = np.zeros(0, dtype=dtype)
    else:
        P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        pts = np.zeros(len(P), dtype=dtype)
        pts["x"], pts["y"], pts["z"] = P[:, 0], P[:, 1], P[:, 2]
        pts["score"] = 0.0 if scores is None else np.asarray(scores, dtype=np.float64)
        pts["id"] = np.arange(len(P))
        pts["kind"] = MARKER_KINDS.index(kind)
        if markers:
            pts["residual_px"] = np.asarray(residual_px, dtype=np.float64)
            pts["cameras"] = 0 if cameras is None else np.asarray(cameras, dtype=np.uint32)
        if checked:
            assert check is not None  # checked implies it
            pts["confidence"] = np.asarray(check[0], dtype=np.float64)
            pts["disagree"] = np.asarray(check[1], dtype=np.uint32)
            pts["agree"] = np.asarray(check[2], dtype=np.uint32)
            pts["others"] = max(int(others), -1) + 1
            pts["inside"] = 0 if inside is None else np.asarray(inside, dtype=np.uint32)
        if markers and person >= 0:
            pts["person"] = person + 1
    return {
        "header": header(ns, frame_id),
        "height": 1,
        "width": len(pts),
        "fields": fields,
        "is_bigendian": False,
        "point_step": dtype.itemsize,
        "row_step": dtype.itemsize * len(pts),
        "data": pts.tobytes(),
        "is_dense": bool(len(pts) == 0 or np.isfinite(np.stack([pts["x"], pts["y"], pts["z"]])).all()),
    }


def _cloud_points(msg: dict) -> np.ndarray:
    n = msg["width"] * msg["height"]
    names = [f["name"] for f in msg["fields"]]
    for dtype in (CLOUD_DTYPE, MARKERS_DTYPE, MARKERS_PERSON_DTYPE, *_CHECKED_ANY):
        if names == list(dtype.names) and msg["point_step"] == dtype.itemsize:
            return np.frombuffer(msg["data"], dtype=dtype, count=n)
    raise BagError(f"point cloud fields {names} are not vmocap's keypoint layout")


def cloud_keypoints(msg: dict) -> tuple[np.ndarray | None, np.ndarray, str]:
    """Inverse of `keypoint_cloud`: positions (25, 3) in KEYPOINTS order (None when empty),
    scores (25,), kind."""
    if msg["width"] * msg["height"] == 0:
        return None, np.zeros(len(KEYPOINTS)), "none"
    pts = _cloud_points(msg)
    P = np.full((len(KEYPOINTS), 3), np.nan)
    S = np.zeros(len(KEYPOINTS))
    ids = pts["id"].astype(np.intp)
    P[ids] = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)
    S[ids] = pts["score"]
    return P, S, MARKER_KINDS[int(pts["kind"][0])]


def image_keypoints_msg(ns: int, camera: str, uv: np.ndarray, w: np.ndarray) -> dict:
    """One camera's 2D keypoints (the PCM centroids of II-C, as triangulation uses them) as a
    PointCloud2 of the 25 KEYPOINTS in frame `camera`: x, y = pixel of the full-resolution image,
    z = 0, score = heatmap peak (0, with NaN x y, where the camera does not see the keypoint)."""
    uv = np.where(np.asarray(w)[:, None] > 0, uv, np.nan)
    return keypoint_cloud(ns, np.concatenate([uv, np.zeros((len(uv), 1))], axis=1), w, frame_id=camera)


def image_keypoints(msg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `image_keypoints_msg`: (25, 2) pixels and (25,) scores."""
    P, S, _ = cloud_keypoints(msg)
    if P is None:
        return np.full((len(KEYPOINTS), 2), np.nan), S
    return P[:, :2], S


def cloud_marker_extras(msg: dict) -> tuple[np.ndarray, np.ndarray]:
    """(residual px (25,), camera bit masks (25,)) of a markers cloud (NaN / 0 where absent)."""
    residual, cameras = np.full(len(KEYPOINTS), np.nan), np.zeros(len(KEYPOINTS), np.uint32)
    if msg["width"] * msg["height"]:
        pts = _cloud_points(msg)
        if pts.dtype in (MARKERS_DTYPE, MARKERS_PERSON_DTYPE, *_CHECKED_ANY):
            ids = pts["id"].astype(np.intp)
            residual[ids], cameras[ids] = pts["residual_px"], pts["cameras"]
    return residual, cameras


def cloud_marker_check(msg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """(confidence (25,), disagree and agree camera bit masks (25,)) of checked markers, else
    None; agree is None in recordings made before it was carried."""
    if msg["width"] * msg["height"] == 0:
        return None
    pts = _cloud_points(msg)
    if pts.dtype not in _CHECKED_ANY:
        return None
    confidence, disagree = np.full(len(KEYPOINTS), np.nan), np.zeros(len(KEYPOINTS), np.uint32)
    ids = pts["id"].astype(np.intp)
    confidence[ids], disagree[ids] = pts["confidence"], pts["disagree"]
    agree = None
    if pts.dtype != CHECKED_V1_DTYPE:
        agree = np.zeros(len(KEYPOINTS), np.uint32)
        agree[ids] = pts["agree"]
    return confidence, disagree, agree


def cloud_marker_others(msg: dict) -> int:
    """The others in view checked markers carry; -1 (not known) for other clouds and for
    recordings made before the field."""
    if msg["width"] * msg["height"] == 0:
        return -1
    pts = _cloud_points(msg)
    return int(pts["others"][0]) - 1 if pts.dtype in (*_INSIDE, CHECKED_V3_DTYPE) else -1


def cloud_marker_person(msg: dict) -> int:
    """The number of the person whose markers these are; -1 for the one subject's and other clouds."""
    if msg["width"] * msg["height"] == 0:
        return -1
    pts = _cloud_points(msg)
    return int(pts["person"][0]) - 1 if "person" in (pts.dtype.names or ()) else -1


def cloud_marker_inside(msg: dict) -> np.ndarray | None:
    """The per-keypoint camera bit masks (25,) checked markers carry as `inside`; None for other
    clouds, recordings made before the field, and markers written without it (all 0)."""
    if msg["width"] * msg["height"] == 0:
        return None
    pts = _cloud_points(msg)
    if pts.dtype not in _INSIDE or not pts["inside"].any():
        return None
    inside = np.zeros(len(KEYPOINTS), np.uint32)
    inside[pts["id"].astype(np.intp)] = pts["inside"]
    return inside



# ------------------------------------------------------------------------------- outputs
def joint_state_msg(ns: int, names: Sequence[str], q: np.ndarray) -> dict:
    return {"header": header(ns, ""), "name": list(names), "position": np.asarray(q, dtype=np.float64)}


# Bones drawn in the MarkerArray skeleton (pairs of KEYPOINTS names).
BONES: tuple[tuple[str, str], ...] = (
    ("pelvis", "neck"), ("neck", "nose"), ("nose", "left_eye"), ("nose", "right_eye"),
    ("left_eye", "left_ear"), ("right_eye", "right_ear"),
    ("neck", "left_shoulder"), ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
    ("left_wrist", "left_hand"), ("neck", "right_shoulder"), ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"), ("right_wrist", "right_hand"),
    ("pelvis", "left_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
    ("left_ankle", "left_heel"), ("left_ankle", "left_toe"),
    ("pelvis", "right_hip"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
    ("right_ankle", "right_heel"), ("right_ankle", "right_toe"),
)
_BONE_IDX = np.array([[INDEX[a], INDEX[b]] for a, b in BONES])


def skeleton_markers(ns: int, keypoints: np.ndarray | None) -> dict:
    """MarkerArray: bones as a LINE_LIST, keypoints as a SPHERE_LIST (DELETEALL when lost)."""
    if keypoints is None or not np.isfinite(keypoints).any():
        return {"markers": [{"header": header(ns, WORLD_FRAME), "ns": "vmocap", "action": 3}]}
    K = np.asarray(keypoints, dtype=np.float64)
    ok = np.isfinite(K).all(axis=1)
    bones = _BONE_IDX[ok[_BONE_IDX].all(axis=1)].ravel()  # type: ignore[index]  # numpy stub: all(axis=1) is an array

    def pts(idx: np.ndarray) -> np.ndarray:
        return K[idx]  # (N, 3): geometry_msgs/Point[] encoded as one block (see cdr)

    common = {"header": header(ns, WORLD_FRAME), "ns": "vmocap", "pose": {"orientation": {"w": 1.0}}}
    return {
        "markers": [
            dict(common, id=0, type=5, scale={"x": 0.02}, color={"r": 0.1, "g": 0.8, "b": 0.2, "a": 1.0}, points=pts(bones)),
            dict(common, id=1, type=7, scale={"x": 0.04, "y": 0.04, "z": 0.04},
                 color={"r": 0.9, "g": 0.3, "b": 0.1, "a": 1.0}, points=pts(np.flatnonzero(ok))),
        ]
    }


def diagnostics_msg(ns: int, statuses: Sequence[tuple[int, str, str, dict[str, Any]]]) -> dict:
    """DiagnosticArray from (level 0 OK/1 WARN/2 ERROR, name, message, key-values) tuples."""
    return {
        "header": header(ns, ""),
        "status": [
            {
                "level": int(level),
                "name": name,
                "message": message,
                "hardware_id": "vmocap",
                "values": [{"key": str(k), "value": str(v)} for k, v in values.items()],
            }
            for level, name, message, values in statuses
        ],
    }
