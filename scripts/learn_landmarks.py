"""Learn a CNN's landmark offsets (vmocap_core/method/landmarks.py) from the image benchmark.

After `vmocap bench images --configs rot-int8 --graph none --config NONE.yaml` (a tracker
config `landmarks: none`; its renders in --cache, its offline outputs in --runs), the offsets
of each clip's lattice markers from the true joint centres in their segments' frames
(vmocap_core/apps/bench/landmark_fit.py); the median over clips of each clip's median is the
model:

    .venv/bin/python scripts/learn_landmarks.py --write vmocap_core/data/landmarks/blazepose.yaml

Held-out figures: `vmocap bench images --leave-one-out` learns the same way per clip.
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from vmocap_core.apps.bench import landmark_fit
from vmocap_core.apps.bench.images import DEFAULT_CACHE
from vmocap_core.apps.bench.landmark_fit import Samples, model_yaml, read_markers
from vmocap_core.apps.render.recording import read_truth
from vmocap_core.paths import REPO


def clip_samples(recording: Path, run: Path) -> Samples:
    stamps, truth = read_truth(recording)
    return landmark_fit.clip_samples(truth, read_markers(run, stamps))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--runs", type=Path, default=REPO / "out" / "image_bench")
    ap.add_argument("--config", default="rot-int8", help="which benchmark configuration's markers")
    ap.add_argument("--name", default="blazepose")
    ap.add_argument("--write", type=Path, help="the model learnt on every clip (YAML)")
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
        a.write.write_text(yaml.safe_dump(model_yaml(a.name, samples, note), sort_keys=False, width=120, default_flow_style=None))
        print(f"wrote {a.write}")
    print("per clip, the median offset (mm, x y z of the segment):")
    for n, v in samples.items():
        print(f"  {n:14s} " + "  ".join(f"{k[5:]} {np.round(np.median(s, axis=0) * 1e3).astype(int)}" for k, s in v.items()))


if __name__ == "__main__":
    main()
