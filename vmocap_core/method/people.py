"""Several people in view (our extension for the Shelf benchmark; the paper tracks one person):
per-view joint candidates (OpenPose style: candidates with scores, plus part-affinity scores
between candidates of connected joints) -> 1. 2D people per view (greedy assembly on the
part-affinity scores), 2. 3D people (associating 2D people across views by epipolar
consistency, then triangulating), 3. PCMs rendered from one person's own detections.
multiperson.py is the look that gives people_tracker.py those PCMs. Nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..cameras.projection import Rig
from ..keypoints import KEYPOINTS
from ..pcm.views import PcmViews, stride_affine
from .triangulation import triangulate_robust, undistort_all

N_KP = len(KEYPOINTS)



# --------------------------------------------------------------------------------------------
# 1. 2D people per view


def assemble_people(
    candidates: Sequence[np.ndarray],
    limbs: Sequence[tuple[int, int]],
    paf: Sequence[np.ndarray],
    min_paf: float = 0.1,
    min_joints: int = 4,
) -> list[np.ndarray]:
    """Group joint candidates of one view into people.

    candidates: per source joint an (n, 3) array (x, y, score); paf: per limb (a, b) an
    (n_a, n_b) association score matrix. Connections are accepted greedily from the strongest
    down; two partial people merge only when they have no joint in common (a person has one
    candidate per joint, so this also uses each candidate at most once per limb).
    Returns people as (J_src, 3) arrays (x, y, score; score 0 where the joint is missing).
    """
    n_src = len(candidates)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in candidates])]).astype(int)
    n_nodes = int(offsets[-1])
    if n_nodes == 0:
        return []
    joint_of = np.repeat(np.arange(n_src), [len(c) for c in candidates])
    # All candidate pairs of all limbs with their PAF score, strongest first.
    edges = []
    for (a, b), m in zip(limbs, paf):
        if m.size == 0:
            continue
        ia, ib = np.nonzero(m > min_paf)
        if ia.size:
            edges.append(np.stack([m[ia, ib], offsets[a] + ia, offsets[b] + ib], axis=1))
    parent = np.arange(n_nodes)
    members = np.zeros((n_nodes, n_src), dtype=bool)  # joint occupancy of each root
    members[np.arange(n_nodes), joint_of] = True

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if edges:
        e = np.concatenate(edges)
        e = e[np.argsort(-e[:, 0], kind="stable")]
        for _, na, nb in e:  # a few dozen edges per view and frame
            ra, rb = root(int(na)), root(int(nb))
            if ra == rb or (members[ra] & members[rb]).any():
                continue
            parent[rb] = ra
            members[ra] |= members[rb]
    roots = np.array([root(i) for i in range(n_nodes)])
    people = []
    for r in np.unique(roots):
        nodes = np.nonzero(roots == r)[0]
        if len(nodes) < min_joints:
            continue
        p = np.zeros((n_src, 3))
        for node in nodes:
            j = joint_of[node]
            p[j] = candidates[j][node - offsets[j]]
        people.append(p)
    return people


def to_keypoints(people_src: Sequence[np.ndarray], src_to_kp: np.ndarray) -> np.ndarray:
    """Source-format people (P, J_src, 3) -> our vocabulary (P, 25, 3) (score 0 = absent)."""
    out = np.zeros((len(people_src), N_KP, 3))
    if len(people_src) == 0:
        return out
    src = np.asarray(people_src)
    ok = src_to_kp >= 0
    out[:, src_to_kp[ok]] = src[:, ok]
    return out


# --------------------------------------------------------------------------------------------
# 2. Cross-view association


def _essentials(rig: Rig) -> np.ndarray:
    """E[i, j] with x_j^T E[i, j] x_i = 0 for normalized coordinates of cameras i and j."""
    C = len(rig)
    R, t = rig._R, rig._t
    E = np.zeros((C, C, 3, 3))
    for i in range(C):
        for j in range(C):
            Rij = R[j] @ R[i].T
            tij = t[j] - Rij @ t[i]
            tx = np.array([[0, -tij[2], tij[1]], [tij[2], 0, -tij[0]], [-tij[1], tij[0], 0]])
            E[i, j] = tx @ Rij
    return E


def epipolar_costs(rig: Rig, people: Sequence[np.ndarray], min_common: int = 4) -> np.ndarray:
    """Mean symmetric epipolar distance (px) between every pair of 2D people of different views.

    people: per camera a (P_c, 25, 3) array. Returns (N, N) over all people in camera order
    (inf for people of the same view or with fewer than `min_common` joints seen by both).
    """
    cams = np.concatenate([np.full(len(p), c) for c, p in enumerate(people)]).astype(int)
    if cams.size == 0:
        return np.zeros((0, 0))
    allp = np.concatenate([p for p in people if len(p)], axis=0)  # (N, 25, 3)
    N = len(allp)
    # Normalized coordinates of every joint in its own camera.
    uv = np.zeros((len(rig), N, N_KP, 2))
    uv[cams, np.arange(N)] = allp[..., :2]
    xy = undistort_all(rig, uv.reshape(len(rig), N * N_KP, 2)).reshape(len(rig), N, N_KP, 2)
    xn = np.concatenate([xy[cams, np.arange(N)], np.ones((N, N_KP, 1))], axis=-1)  # (N, 25, 3)
    focal = np.array([c.focal for c in rig])
    E = _essentials(rig)[cams[:, None], cams[None, :]]  # (N, N, 3, 3): view of a -> view of b
    line_b = np.einsum("abij,akj->abki", E, xn)  # lines in b of a's joints (N, N, 25, 3)
    num = np.abs(np.einsum("abki,bki->abk", line_b, xn))
    d_ab = num / np.maximum(np.linalg.norm(line_b[..., :2], axis=-1), 1e-12) * focal[cams][None, :, None]
    d = 0.5 * (d_ab + d_ab.transpose(1, 0, 2))  # symmetric (N, N, 25)
    seen = allp[..., 2] > 0
    both = seen[:, None, :] & seen[None, :, :]
    n = both.sum(axis=-1)
    cost = np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1)
    cost = np.where((n >= min_common) & (cams[:, None] != cams[None, :]), cost, np.inf)
    return cost


def cluster_views(cost: np.ndarray, cams: np.ndarray, max_cost: float) -> list[np.ndarray]:
    """Average-linkage agglomeration of 2D people into 3D people, at most one per view."""
    clusters = [[i] for i in range(len(cams))]
    while True:
        best, pair = max_cost, None
        for a in range(len(clusters)):
            for b in range(a + 1, len(clusters)):
                ca, cb = clusters[a], clusters[b]
                if set(cams[ca]) & set(cams[cb]):
                    continue
                c = cost[np.ix_(ca, cb)]
                finite = np.isfinite(c)
                if not finite.any():
                    continue
                m = c[finite].mean()
                if m < best:
                    best, pair = m, (a, b)
        if pair is None:
            break
        a, b = pair
        clusters[a] = clusters[a] + clusters[b]
        del clusters[b]
    return [np.array(c) for c in clusters]


@dataclass
class Person3D:
    keypoints: np.ndarray  # (25, 3), NaN where not triangulated
    residual_px: np.ndarray  # (25,)
    members: dict[int, int]  # camera -> index of the 2D person in that view


def associate(
    rig: Rig,
    people: Sequence[np.ndarray],
    max_epipolar_px: float = 30.0,
    min_views: int = 2,
    max_reproj_px: float = 25.0,
) -> list[Person3D]:
    """3D people from per-view 2D people (P_c, 25, 3): epipolar clustering + robust DLT."""
    cams = np.concatenate([np.full(len(p), c) for c, p in enumerate(people)]).astype(int)
    local = np.concatenate([np.arange(len(p)) for p in people]).astype(int)
    if cams.size == 0:
        return []
    cost = epipolar_costs(rig, people)
    out = []
    for cl in cluster_views(cost, cams, max_epipolar_px):
        if len(cl) < min_views:
            continue
        members = {int(cams[i]): int(local[i]) for i in cl}
        uv, w = observations(len(rig), people, members)
        pts, res = triangulate_robust(rig, uv, w, max_error_px=max_reproj_px)
        out.append(Person3D(pts, res, members))
    return out


def observations(n_cams: int, people: Sequence[np.ndarray], members: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(C, 25, 2) pixels and (C, 25) scores of one person's 2D detections (0 where absent)."""
    uv = np.zeros((n_cams, N_KP, 2))
    w = np.zeros((n_cams, N_KP))
    for c, i in members.items():
        uv[c] = people[c][i, :, :2]
        w[c] = people[c][i, :, 2]
    return uv, w


# --------------------------------------------------------------------------------------------
# 3. PCMs of one person


@dataclass
class PcmRenderer:
    """Renders detections as PCMs: one Gaussian per detection at the CNN's output stride,
    amplitude = detection score (values combine by max, like OpenPose's training targets)."""

    sizes: Sequence[tuple[int, int]]  # per camera (width, height) in pixels
    keypoints: np.ndarray  # (J,) indices into KEYPOINTS of the channels
    stride: float = 8.0
    sigma_cells: float = 1.0
    radius: int = 3

    def __post_init__(self) -> None:
        self.keypoints = np.asarray(self.keypoints, dtype=np.intp)
        self.W = int(np.ceil(max(w for w, _ in self.sizes) / self.stride))
        self.H = int(np.ceil(max(h for _, h in self.sizes) / self.stride))
        self.A = stride_affine(self.stride)
        self._chan = np.full(N_KP, -1, dtype=np.intp)
        self._chan[self.keypoints] = np.arange(len(self.keypoints))

    def render(self, uv: np.ndarray, score: np.ndarray, view_ok: np.ndarray, stamp_ns: int = 0) -> PcmViews:
        """PcmViews (one view per camera) of one person: uv (C, 25, 2) pixels and score (C, 25)
        in KEYPOINTS order, one detection per keypoint and camera (score 0 = none). Cameras
        with view_ok False (the person is not seen there) are marked invalid."""
        C = uv.shape[0]
        J = len(self.keypoints)
        maps = np.zeros((C, J, self.H, self.W), dtype=np.float32)
        s = np.clip(score[:, self.keypoints], 0.0, 1.0)  # (C, J)
        xy = uv[:, self.keypoints] @ self.A[:, :2].T + self.A[:, 2]  # map coordinates (C, J, 2)
        c_idx, j_idx = np.nonzero((s > 0) & np.isfinite(xy).all(axis=-1))
        if c_idx.size:
            p = xy[c_idx, j_idx]  # (N, 2)
            off = np.arange(-self.radius, self.radius + 1)
            cx = np.round(p[:, 0]).astype(int)[:, None, None] + off[None, None, :]  # (N, 1, K)
            cy = np.round(p[:, 1]).astype(int)[:, None, None] + off[None, :, None]  # (N, K, 1)
            g = np.exp(-((cx - p[:, 0, None, None]) ** 2 + (cy - p[:, 1, None, None]) ** 2) / (2 * self.sigma_cells**2))
            val = (g * s[c_idx, j_idx][:, None, None]).astype(np.float32)
            cx, cy = np.broadcast_arrays(cx, cy)
            inside = (cx >= 0) & (cx < self.W) & (cy >= 0) & (cy < self.H)
            n_idx = np.broadcast_to(np.arange(len(p))[:, None, None], inside.shape)
            flat = ((c_idx[n_idx] * J + j_idx[n_idx]) * self.H + cy) * self.W + cx
            np.maximum.at(maps.reshape(-1), flat[inside], val[inside])
        valid = np.broadcast_to(np.asarray(view_ok, dtype=bool)[:, None], (C, J)).copy()
        return PcmViews(
            maps=maps,
            image_to_map=np.broadcast_to(self.A, (C, 2, 3)).copy(),
            camera=np.arange(C),
            keypoints=self.keypoints,
            valid=valid,
            presence=np.asarray(view_ok, dtype=np.float64),
            stamp_ns=stamp_ns,
        )
