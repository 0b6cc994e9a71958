"""The heatmap (PCM) messages of a frame set <-> PcmViews, without ROS (messages.py holds the rest).

One pair per view and frame set, with the same header:
- `sensor_msgs/Image`, encoding `32FC<N>`, N = J + 1 or J + 2: row-major H x W cells,
  channels interleaved (OpenCV layout). Channels 0..J-1 are the keypoints in the order of the
  graph config's `pcm.keypoints`; a channel that is all NaN means "this view says nothing about
  that keypoint" (`PcmViews.valid` False). Channel J is constant: the view's `presence`.
  Channel J + 1, present when the maps were weighed by the CNN's landmark visibility
  (`PcmViews.visibility`, not all ones) or the census counted the others in view
  (`PcmViews.others` >= 0) or the maps are one of several people's (`PcmViews.person` >= 0):
  its first J cells (row-major) hold the J keypoints' visibility, cell J holds others + 1 (0:
  not known), cell J + 1 the person's number + 1 (0: the one subject), cell J + 2 how many
  others have a skeleton beside that person + 1 (`PcmViews.company`; 0: not known), the other
  cells 0.
- Several people (`padded`): a view with presence -1 (every keypoint channel NaN) stands for
  none. The PCM node sends one for each view a slot's person has none of (or every view, for a
  free slot), so that every slot answers every frame set in every view; it is read back as no
  view.
  `header.frame_id` is the camera name (as in the rig), `header.stamp` the capture time.
- `sensor_msgs/CameraInfo` of the heatmap as a camera: width W, height H, the camera's own D
  and distortion model, K = A K_cam with A the 3x3 form of `image_to_map`
  ([[a11 a12 a13] [a21 a22 a23] [0 0 1]]) and K_cam the camera's intrinsics from the rig,
  P = [K | 0], R = I. So projecting a camera-frame point with this CameraInfo (distort, then
  K) lands at heatmap map coordinates (cell (x, y) centred at (x, y)), and the receiver gets
  back image_to_map = (K K_cam^-1)[:2]. Rotated crops make K a general affine (non-zero
  K[1,0]), which is why the receiver inverts with the rig's K_cam rather than assuming
  upper-triangular form.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..cameras.projection import Rig
from ..errors import HeatmapError
from ..pcm.views import PcmViews
from .messages import camera_info_msg, header, image_array, image_msg, stamp_ns

# In-process only (never encoded): the (PcmViews, view index) an Image dict without `data`
# stands for, so a receiver in the same process reads the maps without their interleaving
PCM_VIEW = "_vmocap_pcm_view"
# the PcmViews counts the extra channel carries in its cells J, J + 1, ... as value + 1 (0: not known)
COUNTS = ("others", "person", "company")


def view_names(views: PcmViews, rig: Rig) -> list[str]:
    """Each view's name (its topics NS/pcm/VIEW/...): its camera's for the camera's first view,
    CAM_1, CAM_2 ... for more views of one camera (rotation lower_body)."""
    seen: dict[int, int] = {}
    names = []
    for c in views.camera:
        k = seen.get(int(c), 0)
        seen[int(c)] = k + 1
        names.append(_view_name(rig, int(c), k))
    return names


def _view_name(rig: Rig, camera: int, k: int) -> str:
    return rig[camera].name if k == 0 else f"{rig[camera].name}_{k}"


def rig_view_names(rig: Rig, per_camera: int = 1) -> list[str]:
    """Every view name a frame set can have with up to `per_camera` views per camera
    (blazepose.views_per_camera), in view_names' naming."""
    return [_view_name(rig, c, k) for k in range(per_camera) for c in range(len(rig))]


def view_camera(name: str, rig: Rig) -> int:
    """The rig camera a view name (view_names) belongs to."""
    if name in rig.names:
        return rig.names.index(name)
    base, _, k = name.rpartition("_")
    if base in rig.names and k.isdigit():
        return rig.names.index(base)
    raise HeatmapError(f"view {name!r} is no camera of the rig {rig.names} (nor CAM_k of one)")


def padded(views: PcmViews, rig: Rig, names: Sequence[str]) -> PcmViews:
    """Several people: `views` and, for every name of `names` none of them has (view_names), a
    view that stands for none (presence -1, module doc), of the same size."""
    have = set(view_names(views, rig))
    missing = [n for n in names if n not in have]
    if not missing:
        return views
    n, (_, J, H, W) = len(missing), views.maps.shape
    return dataclasses.replace(
        views, maps=np.concatenate([views.maps, np.zeros((n, J, H, W), np.float32)]),
        image_to_map=np.concatenate([views.image_to_map, np.tile(np.eye(2, 3), (n, 1, 1))]),
        camera=np.concatenate([views.camera, [view_camera(m, rig) for m in missing]]),
        valid=np.concatenate([views.valid, np.zeros((n, J), bool)]), presence=np.concatenate([views.presence, np.full(n, -1.0)]),
        visibility=np.concatenate([views.visibility, np.ones((n, J))]))


def pcm_msgs(views: PcmViews, rig: Rig, data: bool = True) -> list[tuple[dict, dict]]:
    """One (Image, CameraInfo) pair per view (see the module docstring). data=False: the
    Images carry no `data` but refer to `views` (PCM_VIEW), for receivers in this process
    only (`pcm_views` reads them; CDR would encode them empty)."""
    V, J, H, W = views.maps.shape
    counts = [getattr(views, name) for name in COUNTS]
    extra = bool(np.any(views.visibility != 1.0)) or max(counts) >= 0
    N = J + 2 if extra else J + 1
    if extra and H * W < J + len(COUNTS):
        raise HeatmapError(f"{W}x{H} maps cannot carry {J} keypoints' visibility, the others in view, the person and "
                           "their company")
    if data:
        # all views at once: (V, H, W, N) interleaved, invalid channels NaN, presence (and visibility) last
        stack = np.empty((V, H, W, N), dtype=np.float32)
        np.copyto(stack[..., :J], views.maps.transpose(0, 2, 3, 1))
        invalid = ~np.asarray(views.valid, dtype=bool)
        if invalid.any():
            stack[..., :J] = np.where(invalid[:, None, None, :], np.float32(np.nan), stack[..., :J])
        stack[..., J] = np.asarray(views.presence, dtype=np.float32)[:, None, None]
        if extra:
            plane = np.zeros((V, H * W), dtype=np.float32)
            plane[:, :J] = views.visibility
            plane[:, J:J + len(COUNTS)] = np.maximum(counts, -1) + 1
            stack[..., J + 1] = plane.reshape(V, H, W)
    out = []
    for v in range(V):
        cam = rig[int(views.camera[v])]
        if data:
            img = image_msg(stack[v], views.stamp_ns, cam.name, encoding=f"32FC{N}", copy=False)  # stack is ours
        else:
            img = {"header": header(views.stamp_ns, cam.name), "height": H, "width": W, "encoding": f"32FC{N}",
                   "is_bigendian": 0, "step": 4 * W * N, PCM_VIEW: (views, v)}
        A = np.vstack([views.image_to_map[v], [0.0, 0.0, 1.0]])
        info = camera_info_msg(cam, views.stamp_ns, K=A @ cam.K, size=(W, H))
        out.append((img, info))
    return out


def pcm_views(pairs: Sequence[tuple[dict, dict]], rig: Rig, keypoints: np.ndarray) -> PcmViews:
    """Inverse of `pcm_msgs`: (Image, CameraInfo) pairs of one frame set -> PcmViews. An
    Image that refers to its PcmViews (PCM_VIEW) gives the same values as its data would, and
    that PcmViews' own image_to_map, which through the CameraInfo's K = A K_cam comes back
    with its last bits changed: the graph in one process then computes what the method does
    offline, bit for bit (several people's tracks diverge from a 1e-16 difference within seconds)."""
    if not pairs:
        raise HeatmapError("no PCM views in the frame set")
    J, V = len(keypoints), len(pairs)
    H, W = pairs[0][0]["height"], pairs[0][0]["width"]
    names = rig.names
    cams = []
    for img, info in pairs:
        name = img["header"]["frame_id"]
        if name not in names:
            raise HeatmapError(f"PCM view of unknown camera {name!r} (rig has {names})")
        if img["encoding"] not in (f"32FC{J + 1}", f"32FC{J + 2}"):
            raise HeatmapError(f"PCM of {name}: {img['encoding']} but {J} keypoints + presence (+ visibility) expected")
        if (info["width"], info["height"]) != (img["width"], img["height"]):
            raise HeatmapError(f"PCM of {name}: CameraInfo size differs from the heatmap's")
        if (img["height"], img["width"]) != (H, W):
            raise HeatmapError(f"PCM of {name}: {img['width']}x{img['height']} differs from the other views' {W}x{H}")
        cams.append(names.index(name))
    sources = [img.get(PCM_VIEW) for img, _ in pairs]
    whole = sources[0] is not None and sources[0][0].n_views == V and all(
        s is not None and s[0] is sources[0][0] and s[1] == i for i, s in enumerate(sources))
    if whole:  # every view of one PcmViews, in order (in-process): what its data would hold
        views = sources[0][0]  # type: ignore[index]  # `whole` checked sources[0] is not None
        maps = views.maps.astype(np.float32, copy=True)
        maps[~np.asarray(views.valid, dtype=bool)] = np.nan
        presence = np.asarray(views.presence, dtype=np.float32).astype(np.float64)
        visibility = np.asarray(views.visibility, dtype=np.float32).astype(np.float64)
        counts = {name: getattr(views, name) for name in COUNTS}
    else:
        maps = np.empty((V, J, H, W), dtype=np.float32)
        presence = np.zeros(V)
        visibility = np.ones((V, J))
        counts = dict.fromkeys(COUNTS, -1)  # the most any view says (every view of a frame set carries the same)
        for i, ((img, _), source) in enumerate(zip(pairs, sources)):
            if source is None:
                arr = image_array(img)  # (H, W, J + 1 or J + 2), channels interleaved
                maps[i] = arr[..., :J].transpose(2, 0, 1)
                if H * W:
                    presence[i] = arr[0, 0, J]
                if arr.shape[-1] == J + 2:
                    extra = arr[..., J + 1].reshape(-1)
                    visibility[i] = extra[:J]
                    for k, name in enumerate(COUNTS):
                        if extra.size > J + k:
                            counts[name] = max(counts[name], int(extra[J + k]) - 1)
            else:
                views, v = source
                maps[i] = views.maps[v]
                maps[i][~np.asarray(views.valid[v], dtype=bool)] = np.nan
                presence[i] = np.float32(views.presence[v])
                visibility[i] = views.visibility[v].astype(np.float32)
                for name in COUNTS:
                    counts[name] = max(counts[name], getattr(views, name))
    # (V, J): an all-NaN channel says nothing; only a channel whose first cell is NaN can be one
    flat = maps.reshape(V * J, H * W)
    valid: np.ndarray = np.full(V * J, H * W > 0)  # an empty map says nothing either
    if H * W:
        maybe = np.flatnonzero(np.isnan(flat[:, 0]))
        valid[maybe] = ~np.isnan(flat[maybe]).all(axis=1)
    valid = valid.reshape(V, J)
    maps[~valid] = 0.0
    Kmap = np.stack([np.asarray(info["k"], dtype=np.float64).reshape(3, 3) for _, info in pairs])
    Kcam = np.stack([rig[c].K for c in cams])
    affine = (Kmap @ np.linalg.inv(Kcam))[:, :2]
    for i, source in enumerate(sources):  # in-process: the sender's own affine, not its last bits through K
        if source is not None:
            affine[i] = source[0].image_to_map[source[1]]
    out = PcmViews(
        maps=maps,
        image_to_map=affine,
        camera=np.array(cams),
        keypoints=np.asarray(keypoints),
        valid=valid,
        presence=presence,
        stamp_ns=stamp_ns(pairs[0][0]),
        visibility=visibility,
        **counts,
    )
    if (presence < 0).any():  # a placeholder view stands for none
        out = out.select(presence >= 0)
    return out
