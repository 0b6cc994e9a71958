"""Part Confidence Maps of one synchronized frame set, with their exact mapping to pixels.

A *view* is one heatmap stack computed from one camera's image (possibly a rotated crop of
it). A camera can give several views, e.g. the paper's variant of input rotation (III-B) uses
the upright image for the upper body and the rotated one for the lower body: two views of the
same camera with complementary `valid` masks.

Map coordinate convention: the centre of heatmap cell (column x, row y) is at map coordinates
(x, y). An image pixel (u, v) (OpenCV convention, pixel centres at integers) maps to map
coordinates by the affine `image_to_map`: (x, y) = A @ (u, v, 1). For a whole image at stride s
with no crop, A = [[1/s, 0, 0.5/s - 0.5], [0, 1/s, 0.5/s - 0.5]], because cell x covers image
pixels [x*s - 0.5, (x+1)*s - 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import HeatmapError


def stride_affine(stride: float) -> np.ndarray:
    """image->map affine of a whole image downsampled by `stride` (no crop)."""
    s = float(stride)
    off = 0.5 / s - 0.5
    return np.array([[1.0 / s, 0.0, off], [0.0, 1.0 / s, off]])


def invert_affine(A: np.ndarray) -> np.ndarray:
    """Inverse of a (..., 2, 3) affine."""
    M = A[..., :2, :2]
    Minv = np.linalg.inv(M)
    b = -np.einsum("...ij,...j->...i", Minv, A[..., :2, 2])
    return np.concatenate([Minv, b[..., None]], axis=-1)


def apply_affine(A: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a (2, 3) affine to points (..., 2)."""
    return pts @ A[:, :2].T + A[:, 2]


@dataclass
class PcmViews:
    """Heatmaps of one frame set: V views, each J keypoint channels of H x W cells."""

    maps: np.ndarray  # (V, J, H, W) float32, values in [0, 1]
    image_to_map: np.ndarray  # (V, 2, 3) float64, image pixel -> map coordinates
    camera: np.ndarray  # (V,) int, index of the view's camera in the rig
    keypoints: np.ndarray  # (J,) int, index of each channel in keypoints.KEYPOINTS
    valid: np.ndarray  # (V, J) bool, False where the view says nothing about a keypoint
    presence: np.ndarray  # (V,) float in [0, 1], the model's confidence a person is there
    stamp_ns: int = 0
    # (V, J) float in [0, 1]: the factor each map was weighed by, the CNN's probability that the
    # keypoint is in view and not occluded (pcm/model.py); empty (default): ones, the model does not say
    visibility: np.ndarray = field(default_factory=lambda: np.empty(0))
    # people besides the subject the detector's census last saw in any camera (census.py); -1: not known
    others: int = -1
    # several people (method/people_look.py): the number of the person these are the crops of; -1: the one subject
    person: int = -1
    # several people: how many others have a skeleton beside this person (0: tracked alone); -1: not known
    company: int = -1
    # peaks() of every channel, kept: the consistency check reads them twice per frame set
    _all_peaks: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.maps = np.asarray(self.maps, dtype=np.float32)
        if self.maps.ndim != 4:
            raise HeatmapError(f"maps must be (V, J, H, W), got shape {self.maps.shape}")
        V, J = self.maps.shape[:2]
        self.image_to_map = np.asarray(self.image_to_map, dtype=np.float64).reshape(V, 2, 3)
        self.camera = np.asarray(self.camera, dtype=np.intp).reshape(V)
        self.keypoints = np.asarray(self.keypoints, dtype=np.intp).reshape(J)
        self.valid = np.asarray(self.valid, dtype=bool).reshape(V, J)
        self.presence = np.asarray(self.presence, dtype=np.float64).reshape(V)
        # float32 values, as the PCM message carries them: the graph and the offline run then
        # read the same peaks before the visibility (centroids), bit for bit
        visibility = np.asarray(self.visibility, dtype=np.float32).astype(np.float64)
        self.visibility = np.ones((V, J)) if visibility.size == 0 else visibility.reshape(V, J)

    @classmethod
    def empty(cls, channels: int, map_size: int, stamp_ns: int = 0) -> "PcmViews":
        """A frame set without views (nobody to crop), `channels` keypoints of map_size maps."""
        J = channels
        return cls(np.zeros((0, J, map_size, map_size)), np.zeros((0, 2, 3)), np.zeros(0), np.arange(J),
                   np.zeros((0, J), bool), np.zeros(0), stamp_ns)

    def select(self, keep: np.ndarray, stamp_ns: int | None = None) -> "PcmViews":
        """The views where `keep` (V,) is True (stamped `stamp_ns` when given)."""
        keep = np.asarray(keep, dtype=bool).reshape(self.n_views)
        return replace(self, maps=self.maps[keep], image_to_map=self.image_to_map[keep], camera=self.camera[keep],
                       valid=self.valid[keep], presence=self.presence[keep], visibility=self.visibility[keep],
                       stamp_ns=self.stamp_ns if stamp_ns is None else stamp_ns)

    @property
    def n_views(self) -> int:
        return self.maps.shape[0]

    @property
    def map_size(self) -> tuple[int, int]:
        """(W, H) of the maps."""
        return self.maps.shape[3], self.maps.shape[2]

    def sanitized(self) -> "PcmViews":
        """Replace NaN/inf by 0 and clip to [0, 1]; views that had non-finite values are
        marked invalid for the affected keypoints (a broken CNN output must not steer)."""
        # min/max propagate NaN, so two reductions tell whether anything needs fixing.
        if self.maps.size == 0 or (self.maps.min() >= 0.0 and self.maps.max() <= 1.0):
            return self
        finite = np.isfinite(self.maps)
        bad = ~finite.all(axis=(2, 3))  # (V, J)
        maps = np.clip(np.where(finite, self.maps, 0.0), 0.0, 1.0).astype(np.float32)
        return replace(self, maps=maps, valid=self.valid & ~bad)

    def corrupted(self) -> dict[int, int]:
        """Per camera index, how many values of its valid channels are not finite or outside
        [0, 1] (what `sanitized` cleans up silently); {} for clean maps. An entirely-NaN channel
        is the documented "no information" and does not count."""
        valid = np.asarray(self.valid, dtype=bool)
        if self.maps.size == 0 or not valid.any():
            return {}
        m = self.maps[valid]  # (n, h, w)
        if np.isfinite(m).all() and m.min() >= 0.0 and m.max() <= 1.0:
            return {}
        bad = (~np.isfinite(m) | (np.nan_to_num(m, nan=0.0) < 0.0) | (np.nan_to_num(m, nan=0.0) > 1.0)).sum(axis=(1, 2))
        views = np.nonzero(valid)[0]
        out: dict[int, int] = {}
        for v, n in zip(views, bad):
            if n:
                c = int(self.camera[v])
                out[c] = out.get(c, 0) + int(n)
        return out

    def peaks(self, channels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per view and channel (all, or the given channel indices), the image pixel of the
        heatmap maximum (V, J', 2) and its value (V, J'); NaN cells are ignored. The maps are
        not to change after the first call (every channel's peaks are kept)."""
        if channels is None and self._all_peaks is not None:
            return self._all_peaks
        chans = np.arange(self.maps.shape[1]) if channels is None else np.asarray(channels)
        valid = self.valid[:, chans]
        V, _, H, W = self.maps.shape
        flat: Any  # (V, C, H*W) array, or a list of (V, H*W) views
        if channels is None:
            flat = self.maps.reshape(V, chans.size, H * W)
        else:  # a few channels: (V, H*W) views of each, no copy of the stack
            flat = [self.maps[:, c].reshape(V, H * W) for c in chans]
        arg = np.stack([f.argmax(axis=1) for f in flat], axis=1) if channels is not None else flat.argmax(axis=2)
        val = np.stack([flat[i][np.arange(V), arg[:, i]] for i in range(chans.size)], axis=1) \
            if channels is not None else np.take_along_axis(flat, arg[..., None], axis=2)[..., 0]
        broken = np.isnan(val)  # argmax stops at a NaN: redo only those channels without them
        for v, i in zip(*np.nonzero(broken)):
            fixed = np.nan_to_num(self.maps[v, chans[i]].reshape(-1), nan=0.0)
            arg[v, i] = fixed.argmax()
            val[v, i] = fixed[arg[v, i]]
        xy = np.stack([arg % W, arg // W], axis=-1).astype(np.float64)
        inv = invert_affine(self.image_to_map)  # (V, 2, 3)
        uv = np.einsum("vij,vkj->vki", inv[:, :, :2], xy) + inv[:, None, :, 2]
        out = uv, np.clip(np.where(valid, val, 0.0), 0.0, 1.0)
        if channels is None:
            self._all_peaks = out
        return out

    def unweighed(self, values: np.ndarray) -> np.ndarray:
        """(V, J) values read on the maps, as on the maps before the visibility weighed them
        (0 where the visibility is 0: that map carries nothing)."""
        return np.divide(values, self.visibility, out=np.zeros(np.shape(values)), where=self.visibility > 0)

    def centroids(self, threshold: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """Per view and channel, the image pixel of the PCM centroid around the peak (V, J, 2)
        and the peak value (V, J) (II-C uses centroids of the maps for initialization), taken
        before the visibility weighed the map (the CNN's guess of a hidden keypoint counts, as
        the triangulation's residuals check it); 0 where it is below `threshold`.

        The centroid is taken over cells within 3 cells of the peak whose value is at least
        half the peak, so a second person or a false peak elsewhere does not drag it.
        """
        V, J, H, W = self.maps.shape
        flat = self.maps.reshape(V, J, H * W)
        arg = flat.argmax(axis=2)
        val = np.take_along_axis(flat, arg[..., None], axis=2)[..., 0]
        px, py = arg % W, arg // W
        r = 3
        off = np.arange(-r, r + 1)
        xs = np.clip(px[..., None, None] + off[None, None, None, :], 0, W - 1)  # (V,J,1,K)
        ys = np.clip(py[..., None, None] + off[None, None, :, None], 0, H - 1)  # (V,J,K,1)
        vi = np.arange(V)[:, None, None, None]
        ji = np.arange(J)[None, :, None, None]
        win = self.maps[vi, ji, ys, xs].astype(np.float64)  # (V, J, K, K)
        w = np.where(win >= 0.5 * val[..., None, None], win, 0.0)
        wsum = w.sum(axis=(2, 3))
        wsum = np.where(wsum > 0, wsum, 1.0)
        cx = (w * xs).sum(axis=(2, 3)) / wsum
        cy = (w * ys).sum(axis=(2, 3)) / wsum
        xy = np.stack([cx, cy], axis=-1)
        inv = invert_affine(self.image_to_map)
        uv = np.einsum("vij,vkj->vki", inv[:, :, :2], xy) + inv[:, None, :, 2]
        guess = self.unweighed(val)
        ok = self.valid & (guess >= threshold)
        return uv, np.where(ok, np.minimum(guess, 1.0), 0.0)


def blank_views(pcm: PcmViews, cameras: list[int]) -> PcmViews:
    """`pcm` plus views of `cameras` that say nothing (every channel invalid, presence 0), as
    many per camera as the others have (rotation lower_body: 2): a camera whose image was not
    used still has its views in the frame set, so vmocap_markers does not wait for them."""
    V, J, H, W = pcm.maps.shape
    per = int(np.bincount(np.asarray(pcm.camera, dtype=np.intp)).max())
    cams = np.repeat(np.asarray(cameras, dtype=np.intp), per)
    n = len(cams)
    return PcmViews(np.concatenate([pcm.maps, np.zeros((n, J, H, W), np.float32)]),
                    np.concatenate([pcm.image_to_map, np.tile(np.eye(2, 3), (n, 1, 1))]),
                    np.concatenate([pcm.camera, cams]), pcm.keypoints,
                    np.concatenate([pcm.valid, np.zeros((n, J), bool)]), np.concatenate([pcm.presence, np.zeros(n)]),
                    pcm.stamp_ns, np.concatenate([pcm.visibility, np.ones((n, J))]), pcm.others, pcm.person)
