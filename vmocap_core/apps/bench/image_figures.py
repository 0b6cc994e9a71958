"""The pictures of `vmocap bench images`: one frame per camera with the truth and the estimate
projected, and each run's MPJPE over the clip."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...bag import BagReader
from ...bag import messages as M
from ...graph_config import Topics
from .accuracy import RATE_HZ


def overlay(rec: Path, rig, truth: np.ndarray, est: np.ndarray, frame: int, out: Path) -> None:
    """One frame per camera with the projected truth (green) and estimate (red)."""
    import cv2

    topics = Topics()
    want = {topics.image(c.name): i for i, c in enumerate(rig)}
    imgs: dict[int, np.ndarray] = {}
    with BagReader(rec) as r:
        for k, m in enumerate(r.messages(list(want))):
            if k // len(rig) == frame:
                imgs[want[m.topic]] = M.image_array(m.decode()).copy()
            elif k // len(rig) > frame:
                break
    for P, col in ((truth[frame], (0, 200, 0)), (est[frame], (0, 0, 255))):
        ok = np.isfinite(P).all(axis=1)
        if ok.any():
            uv, _ = rig.project(P[ok])
            for i, img in imgs.items():
                for u, v in uv[i]:
                    cv2.circle(img, (int(round(u)), int(round(v))), max(2, img.shape[1] // 200), col, -1)
    tiles = [imgs[i] for i in sorted(imgs)]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.vstack([np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles), 2)])
    cv2.imwrite(str(out), grid)


def plot_curves(name: str, row: dict[str, Any], curves: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.2))
    for k, v in curves.items():
        ax.plot(np.arange(len(v)) / RATE_HZ, v, label=f"{k} ({row[k]['mpjpe_mm'] or float('nan'):.1f} mm)", lw=1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("MPJPE (mm)")
    ax.set_title(f"{name} ({row['group']}): rendered images, {row['shape']} body")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
