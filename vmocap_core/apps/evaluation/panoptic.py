"""`vmocap eval panoptic`: several people on real images through the multi-person tracker.

CMU Panoptic Studio frames (../shared/data/panoptic_demo: five HD views at five instants, three
people walking in the dome; no ground truth). Each instant is one still frame set: it is given
to a fresh method/people_tracker.py `frame_sets` times at the rig rate (the detector, the
initialization and the identification need several frame sets; a still body is the easy case
of motion), with the real CNN and the initialization's agreement bound in proportion to the
1920-px images (the default is for 1024 px). Reported per instant: the people tracked at the end, and per
person the median distance (px) between their skeleton's keypoints projected into each of
their views and that view's PCM peak (only peaks the CNN is confident of).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import VmocapError
from ...paths import SHARED_DATA

DEFAULT_DATA = SHARED_DATA / "panoptic_demo"
VIEWS = ("00_03", "00_06", "00_12", "00_13", "00_23")
PEOPLE = 3  # in every instant of the demo frames
REFERENCE_WIDTH = 1024  # the image width the default init_max_reprojection_px is meant for
FPS = 30.0
MIN_PEAK = 0.5  # a peak the CNN is confident of: the reprojection compares with it


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="panoptic_demo folder (VIEW/VIEW_FRAME.jpg, "
                        "camera_parameters.json)")
    parser.add_argument("--max-people", type=int, default=PEOPLE, help="people the tracker follows at once")
    parser.add_argument("--frame-sets", type=int, default=120, help="times each instant is given to the tracker")
    parser.add_argument("--instants", nargs="+", default=None, help="only these instants (frame numbers, e.g. 00009348)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")


def instants(data: Path) -> list[str]:
    names = sorted({p.stem.rsplit("_", 1)[-1] for p in (data / VIEWS[0]).glob("*.jpg")})
    if not names:
        raise VmocapError(f"{data}: no frames in {data / VIEWS[0]} (see ../shared/data/README.md)")
    return names


def reprojection_px(rig: Any, person: Any) -> float | None:
    """Median px between the person's keypoints (the first IK's, at the CNN's landmarks)
    projected into their views and those views' confident PCM peaks."""
    from ...method.results import skeleton_of
    from ...pcm.peaks import camera_keypoints

    fb, pcm = skeleton_of(person.feedback), None if person.last is None else person.last.pcm
    if fb is None or pcm is None or pcm.n_views == 0:
        return None
    uv, w = camera_keypoints(pcm, len(rig))
    proj, front = rig.project(fb)
    ok = (w > MIN_PEAK) & front & np.isfinite(fb).all(axis=1)[None]
    return float(np.median(np.linalg.norm(proj - uv, axis=-1)[ok])) if ok.any() else None


def why(tracker: Any, person: Any) -> str:
    """A person's status and, before their first skeleton, why (the graph's words, init_report.py)."""
    from ..process import why_not_tracked

    if person.status != "initializing" or person.last is None:
        return person.status
    return why_not_tracked(person.last, tracker.rig, tracker.config.markers.init_max_reprojection_px,
                           tracker.skeletons.stages[person.number].init_problem)


def evaluate(data: Path, max_people: int, frame_sets: int, only: list[str] | None = None) -> dict[str, Any]:
    import cv2
    from tqdm import tqdm

    from ...cameras.rig_file import load_panoptic_cameras
    from ...method.config import MarkersConfig, PipelineConfig
    from ...method.people_config import PeopleConfig
    from ...method.people_tracker import PeopleTracker
    from ...pcm.pipeline import BlazePosePcm

    rig = load_panoptic_cameras(data / "camera_parameters.json", VIEWS)
    pcm = BlazePosePcm(rig, threads=2)
    # the views' agreement at initialization, in pixels: for 1920-px images in proportion
    bound = MarkersConfig().init_max_reprojection_px * max(c.width for c in rig) / REFERENCE_WIDTH
    config = PipelineConfig.from_dict({"fps": FPS, "init_max_reprojection_px": bound})
    rows = []
    names = instants(data)
    unknown = sorted(set(only or []) - set(names))
    if unknown:
        raise VmocapError(f"{data}: no instant {unknown} (there are {names})")
    for name in tqdm([n for n in names if only is None or n in only], desc="instants", unit="instant", file=sys.stderr):
        images = [cv2.imread(str(data / v / f"{v}_{name}.jpg")) for v in VIEWS]
        missing = [v for v, im in zip(VIEWS, images) if im is None]
        if missing:
            raise VmocapError(f"{data}: cannot read frame {name} of {missing}")
        tracker = PeopleTracker(rig, pcm, config, PeopleConfig(max_people=max_people))
        for i in range(frame_sets):
            frame = tracker.step(images, int(1e12 + i * 1e9 / FPS))
        tracked = [p for p in frame.people if p.status == "tracking"]
        rows.append({"instant": name, "tracked": len(tracked),
                     "reprojection_px": [reprojection_px(rig, p) for p in tracked],
                     "not_tracked": {str(p.number): why(tracker, p) for p in frame.people if p.status != "tracking"}})
    return {"people_in_view": PEOPLE, "max_people": max_people, "frame_sets": frame_sets, "instants": rows,
            "init_max_reprojection_px": bound,
            "all_found": sum(r["tracked"] >= min(PEOPLE, max_people) for r in rows)}


def run(args: argparse.Namespace) -> int:
    res = evaluate(args.data, args.max_people, args.frame_sets, args.instants)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        for r in res["instants"]:
            px = ", ".join("-" if e is None else f"{e:.1f}" for e in r["reprojection_px"])
            print(f"{r['instant']}: {r['tracked']} of {PEOPLE} tracked; reprojection median per person (px): {px or '-'}")
        print(f"all {min(PEOPLE, args.max_people)} tracked at {res['all_found']} of {len(res['instants'])} instants")
    for r in res["instants"]:
        if r["tracked"] < min(PEOPLE, args.max_people):
            print(f"vmocap eval panoptic: WARNING: instant {r['instant']}: {r['tracked']} of {PEOPLE} people tracked "
                  f"(the others: {r['not_tracked'] or 'never found'})", file=sys.stderr)
    return 0 if any(r["tracked"] for r in res["instants"]) else 1
