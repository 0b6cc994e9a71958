"""How much of the image benchmark's error is a landmark-definition offset in the body frame.

After `vmocap bench images` (its recordings in out/render_cache, its outputs in
out/image_bench), for each clip: the estimate's error per joint is expressed in the estimate's
own trunk frame (x forward, y left, z up: what a correction could use at run time), the mean
of those errors over the *other* clips is taken as the joint's offset, and removed from this
clip's estimate. Prints MPJPE before and after per clip and pooled (leave one clip out), and
the offsets learnt on all clips with their spread across clips.

    .venv/bin/python scripts/landmark_offsets.py [--config rot-int8] [--json]

An analysis, not part of the method: see docs/image_benchmark.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vmocap_core.apps.bench.images import read_estimates
from vmocap_core.apps.render.recording import read_truth
from vmocap_core.keypoints import INDEX, KEYPOINTS
from vmocap_core.paths import REPO


def trunk_frames(P: np.ndarray) -> np.ndarray:
    """(T, 3, 3): rows x forward, y left, z up of the trunk of keypoints P (T, 25, 3)."""
    z = P[:, INDEX["neck"]] - P[:, INDEX["pelvis"]]
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = P[:, INDEX["left_hip"]] - P[:, INDEX["right_hip"]] + P[:, INDEX["left_shoulder"]] - P[:, INDEX["right_shoulder"]]
    y -= (y * z).sum(1, keepdims=True) * z
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    return np.stack([np.cross(y, z), y, z], axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="rot-int8")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    clips = {}
    for rec in sorted((REPO / "out" / "render_cache").glob("*.mcap")):
        name = rec.stem.rsplit("_", 1)[0]
        out = REPO / "out" / "image_bench" / f"{name}_{a.config}.mcap"
        if out.exists():
            stamps, truth = read_truth(rec)
            clips[name] = (read_estimates(out, stamps), truth)
    if len(clips) < 2:
        raise SystemExit("run `vmocap bench images` first (out/render_cache, out/image_bench)")
    joints = np.flatnonzero(np.isfinite(next(iter(clips.values()))[1]).all(axis=(0, 2)))
    local = {}  # clip -> (F, 25, 3) errors in the estimate's trunk frame, tracked frames only
    for n, (e, g) in clips.items():
        ok = np.isfinite(e[:, joints]).all(axis=(1, 2))
        local[n] = np.einsum("tij,tkj->tki", trunk_frames(e[ok]), e[ok] - g[ok])
    rows = {}
    for held, (e, g) in clips.items():
        offset = np.concatenate([v for n, v in local.items() if n != held]).mean(axis=0)
        ok = np.isfinite(e[:, joints]).all(axis=(1, 2))
        e, g = e[ok][:, joints], g[ok][:, joints]
        corrected = e - np.einsum("tji,kj->tki", trunk_frames(clips[held][0][ok]), offset)[:, joints]
        rows[held] = {"frames": int(ok.sum()), "mpjpe_mm": float(np.linalg.norm(e - g, axis=-1).mean() * 1e3),
                      "corrected_mm": float(np.linalg.norm(corrected - g, axis=-1).mean() * 1e3)}
    everything = np.concatenate(list(local.values())).mean(axis=0)
    spread = np.std([v.mean(axis=0) for v in local.values()], axis=0)
    result = {"clips": rows, "offsets_mm": {KEYPOINTS[j]: (everything[j] * 1e3).round(1).tolist() for j in joints},
              "spread_mm": {KEYPOINTS[j]: (spread[j] * 1e3).round(1).tolist() for j in joints}}
    if a.json:
        print(json.dumps(result))
        return
    for n, r in rows.items():
        print(f"{n:14s} {r['mpjpe_mm']:6.1f} -> {r['corrected_mm']:6.1f} mm ({r['frames']} frame sets)")
    print("offsets learnt on all clips (mm; x forward, y left, z up of the trunk) and their spread across clips:")
    for k in result["offsets_mm"]:
        print(f"  {k:15s} {result['offsets_mm'][k]}  spread {result['spread_mm'][k]}")


if __name__ == "__main__":
    main()
