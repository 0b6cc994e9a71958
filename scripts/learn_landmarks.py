"""Learn a CNN's landmark offsets (vmocap_core/method/landmarks.py) from the image benchmark.

After `vmocap bench images` (its renders in --cache, its offline outputs in --runs), for each
clip: our skeleton is identified on the true joint centres and fitted to every frame, and each
lattice marker's offset from its true joint centre is expressed in its segment's frame. The
median over clips of each clip's median is the model (--write, e.g.
vmocap_core/data/landmarks/blazepose.yaml); --leave-one-out DIR also writes, per clip, a
tracker config whose model was learnt on the other clips only, to score each clip with
offsets it was not learnt on:

    .venv/bin/python scripts/learn_landmarks.py --write vmocap_core/data/landmarks/blazepose.yaml \
        --leave-one-out out/landmarks
    vmocap bench images --clips <clip.npz> --config out/landmarks/<clip>.yaml ...
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from vmocap_core.apps.bench.images import DEFAULT_CACHE
from vmocap_core.apps.render.recording import read_truth
from vmocap_core.bag import BagReader
from vmocap_core.bag import messages as M
from vmocap_core.graph_config import Topics
from vmocap_core.keypoints import KEYPOINTS
from vmocap_core.method.init import fit_skeleton, frame_poses
from vmocap_core.method.landmarks import SEGMENT, learn_offsets
from vmocap_core.paths import REPO


def read_markers(path: Path, stamps: np.ndarray) -> np.ndarray:
    """(T, 25, 3) lattice markers at the truth stamps (NaN: none or weight 0)."""
    out = np.full((len(stamps), len(KEYPOINTS), 3), np.nan)
    row = {int(s): i for i, s in enumerate(stamps)}
    with BagReader(path) as r:
        for m in r.messages([Topics().markers]):
            d = m.decode()
            P, S, kind = M.cloud_keypoints(d)
            i = row.get(M.stamp_ns(d))
            if P is not None and i is not None and kind == "lattice":
                out[i] = np.where((S > 0)[:, None], P, np.nan)
    return out


def clip_samples(recording: Path, run: Path) -> dict[str, np.ndarray]:
    stamps, truth = read_truth(recording)
    markers = read_markers(run, stamps)
    fitted = fit_skeleton(truth, 1.0)
    assert fitted is not None  # a 1 m bound accepts any body
    sk, fit = fitted
    return learn_offsets(sk, np.array(frame_poses(sk, truth, fit.q)), markers, truth)


def model(name: str, samples: list[dict[str, np.ndarray]], note: str) -> dict[str, object]:
    """The median over clips of each clip's median: every clip one vote, however long."""
    offsets = {k: [round(float(x) * 1e3, 1) for x in np.median([np.median(s[k], axis=0) for s in samples], axis=0)]
               for k in SEGMENT if k.startswith("left_")}
    return {"name": name, "note": note, "offsets_mm": offsets}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--runs", type=Path, default=REPO / "out" / "image_bench")
    ap.add_argument("--config", default="rot-int8", help="which benchmark configuration's markers")
    ap.add_argument("--name", default="blazepose")
    ap.add_argument("--write", type=Path, help="the model learnt on every clip (YAML)")
    ap.add_argument("--leave-one-out", type=Path, metavar="DIR", help="per clip, a tracker config learnt on the others")
    a = ap.parse_args()
    clips = {}
    for rec in sorted(a.cache.glob("*.mcap")):
        name = rec.stem.rsplit("_", 1)[0]
        run = a.runs / f"{name}_{a.config}.mcap"
        if run.exists():
            clips[name] = (rec, run)
    if len(clips) < 2:
        raise SystemExit(f"run `vmocap bench images` first: no pairs of {a.cache}/*.mcap and {a.runs}/<clip>_{a.config}.mcap")
    samples = {n: clip_samples(rec, run) for n, (rec, run) in tqdm(clips.items(), desc="clips")}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO).stdout.strip()
    note = (f"learnt by scripts/learn_landmarks.py on {datetime.date.today()} at {commit} from the image benchmark's "
            f"{a.config} lattice markers of: {', '.join(clips)}; offsets of the left side in its segment's frame "
            "(x forward, y left, z up in the neutral pose)")
    if a.write:
        a.write.parent.mkdir(parents=True, exist_ok=True)
        a.write.write_text(yaml.safe_dump(model(a.name, list(samples.values()), note), sort_keys=False, width=120, default_flow_style=None))
        print(f"wrote {a.write}")
    if a.leave_one_out:
        a.leave_one_out.mkdir(parents=True, exist_ok=True)
        for held in clips:
            path = a.leave_one_out / f"{held}.yaml"
            m = model(f"{a.name}-without-{held}", [s for n, s in samples.items() if n != held], note + f", {held} left out")
            (a.leave_one_out / f"{held}_landmarks.yaml").write_text(yaml.safe_dump(m, sort_keys=False, width=120, default_flow_style=None))
            path.write_text(yaml.safe_dump({"landmarks": str((a.leave_one_out / f"{held}_landmarks.yaml").resolve())}))
        print(f"wrote {len(clips)} leave-one-out configs to {a.leave_one_out}")
    print("per clip, the median offset (mm, x y z of the segment):")
    for n, v in samples.items():
        print(f"  {n:14s} " + "  ".join(f"{k[5:]} {np.round(np.median(s, axis=0) * 1e3).astype(int)}" for k, s in v.items()))


if __name__ == "__main__":
    main()
