"""`vmocap eval shelf`: our pipeline on the Shelf benchmark's real OpenPose detections.

Per frame and view the BODY_25 candidates are grouped into 2D people with their part-affinity
scores; the multi-person tracker of the live graph (method/people_tracker.py: a marker and a
skeleton stage per person, people ended by the same rule) runs on them with the detections'
look (method/multiperson.py) instead of the CNN's: 2D people go to the person whose projected
skeleton they fit, the rest are associated across views (epipolar consistency +
triangulation) into new people, and each person's PCMs are rendered (a Gaussian per candidate
at OpenPose's stride 8, amplitude = candidate score) from their own candidates only. While a
person initializes (the paper's II-C needs a few agreeing frames) they are reported by
triangulation of their own detections.

The ground truth is read only to score: per frame, Hungarian matching of reconstructed people
to ground-truth ids, then PCP per part and id and MPJPE per id (pcp.py states the head-joint
mapping). The baseline is per-frame triangulation of the same associated detections (no
tracking, no skeleton, no filtering).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import VmocapError
from ...keypoints import KEYPOINTS
from ...method.multiperson import DetectionsLook, MultiPersonConfig
from ...method.people import PcmRenderer, assemble_people, associate, to_keypoints
from ...method.people_config import PeopleConfig
from ...paths import SHARED_DATA
from .pcp import PART_GROUPS, ShelfScore, to_shelf15
from .shelf_data import BODY25_LIMBS, BODY25_TO_KEYPOINT, ShelfData, load_shelf

DEFAULT_DATA = SHARED_DATA / "shelf"
N_KP = len(KEYPOINTS)
FPS = 25.0  # Shelf's frame rate (approximately)
STRIDE = 8  # OpenPose's output stride
SIGMA_CELLS = 2.0  # Gaussian of a rendered candidate, in map cells (a wide basin for the lattice)

# Tracker settings for Shelf (25 fps, people 3-6 m from the cameras); the measurements behind
# each choice are in docs/benchmarks.md.
TRACKER_SETTINGS = {
    "fps": FPS,
    "lattice_k": 5,  # +-10 cm around the constant-velocity prediction
    "lattice_spacing": 0.02,
    "coarse_to_fine": False,  # the full lattice scores slightly better on Shelf
    "prediction": "constant_velocity",  # 25 fps: limbs move up to ~10 cm per frame
    "init_frames": 3,
    # Several people's peaks share the maps: a view's refinement window catches a neighbour's
    # peak more often than on one person, so the lattice argmax is kept.
    "refine_markers": False,
    # People walk in and out: output from the first agreeing frames counts more than exact
    # link lengths.
    "identify_seconds": 0.0,
    "init_max_reprojection_px": 15.0,
    "lost_frames": 8,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="Shelf folder (calibration.json, detection/, gt.txt)")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def people_per_view(data: ShelfData, frame: int) -> list[np.ndarray]:
    """2D people of every view in one frame, in our keypoint vocabulary ((P_c, 25, 3))."""
    out = []
    for view in data.views:
        vf = view[frame]
        out.append(to_keypoints(assemble_people(vf.candidates, BODY25_LIMBS, vf.paf), BODY25_TO_KEYPOINT))
    return out


# The people's settings of the live graph (people_config.py), with room for everyone on the shelf
PEOPLE = {"max_people": 10}


def make_tracker(data: ShelfData, tracker_settings: dict | None = None, mp_config: MultiPersonConfig | None = None,
                 sigma_cells: float | None = None) -> Any:
    """The multi-person tracker (people_tracker.py) with the detections' look over Shelf."""
    from ...method.config import PipelineConfig
    from ...method.people_tracker import PeopleTracker

    people = PeopleConfig(**PEOPLE)
    look = DetectionsLook(data.rig, make_renderer(data, sigma_cells or SIGMA_CELLS), mp_config, people)
    return PeopleTracker(data.rig, None, PipelineConfig.from_dict(tracker_settings or TRACKER_SETTINGS), people,
                         landmarks="none", look=look)


def make_renderer(data: ShelfData, sigma_cells: float = SIGMA_CELLS) -> PcmRenderer:
    keypoints = np.unique(BODY25_TO_KEYPOINT[BODY25_TO_KEYPOINT >= 0])
    return PcmRenderer([(c.width, c.height) for c in data.rig], keypoints, stride=STRIDE,
                       sigma_cells=sigma_cells, radius=int(np.ceil(3 * sigma_cells)))


def evaluate(data: ShelfData, progress: bool = True, tracker_settings: dict | None = None,
             mp_config: MultiPersonConfig | None = None, sigma_cells: float | None = None) -> dict:
    """Run ours and the baseline over all frames; returns the results dictionary."""
    from tqdm import tqdm

    rig = data.rig
    tracker = make_tracker(data, tracker_settings, mp_config, sigma_cells)
    max_epipolar_px = tracker.look.cfg.max_epipolar_px
    ours, base = ShelfScore(), ShelfScore()
    sources = {"tracker": 0, "triangulated": 0}
    started: set[int] = set()
    ended = 0
    t_front = t_track = 0.0
    for f in tqdm(range(data.n_frames), desc="shelf", unit="frame", disable=not progress, file=sys.stderr):
        gt = data.gt[f]
        t0 = time.perf_counter()
        people = people_per_view(data, f)
        t1 = time.perf_counter()
        # Baseline: per-frame association and triangulation of the same 2D people.
        bpeople = [p.keypoints for p in associate(rig, people, max_epipolar_px)]
        base.add_frame(to_shelf15(np.array(bpeople).reshape(-1, N_KP, 3)), gt.ids, gt.joints, gt.valid)
        # Ours.
        t2 = time.perf_counter()
        frame = tracker.step(people, int(f * 1e9 / FPS))
        seats = {s.number: s for s in tracker.look.seats}
        preds = []
        for p in frame.people:
            started.add(p.number)
            r = p.result
            if r is not None and r.status == "tracking" and np.isfinite(r.keypoints).all():
                preds.append(r.keypoints)
                sources["tracker"] += 1
            elif p.number in seats and seats[p.number].triangulated is not None:
                preds.append(seats[p.number].triangulated)
                sources["triangulated"] += 1
        ended += len(frame.ended)
        ours.add_frame(to_shelf15(np.array(preds).reshape(-1, N_KP, 3)), gt.ids, gt.joints, gt.valid)
        t3 = time.perf_counter()
        t_front += t1 - t0
        t_track += t3 - t2
    result = ours.summary()
    result["baseline"] = base.summary()
    result["frames_total"] = data.n_frames
    result["person_frames"] = sources
    result["tracks_started"] = len(started)
    result["tracks_ended"] = ended
    result["time_ms_per_frame"] = {
        "grouping": 1000 * t_front / max(data.n_frames, 1),
        "trackers": 1000 * t_track / max(data.n_frames, 1),
    }
    result["tracker_settings"] = tracker.config.to_dict()
    result["people_settings"] = dict(PEOPLE)
    result["head_mapping"] = (
        "bottom = S + (E-S)/2 + 0.15 F, top = bottom + 0.8 (E-S) + 0.25 F; S shoulder centre, "
        "E ear centre, F = nose - E; pelvis = hip centre"
    )
    return result



def format_table(res: dict) -> str:
    ids = [k for k in res["pcp"] if k != "mean"]
    lines = ["Shelf PCP (%) per ground-truth id and part; MPJPE (mm) over the 15 Shelf joints", ""]
    head = f"{'':24s}" + "".join(f"{'id ' + i:>9s}" for i in ids) + f"{'mean':>9s}"
    for name, r in (("ours (lattice trackers)", res), ("baseline (triangulation)", res["baseline"])):
        lines.append(name)
        lines.append(head)
        for g in PART_GROUPS:
            vals = [r["pcp_parts"][i][g] for i in ids]
            lines.append(f"  {g:22s}" + "".join(f"{v:9.1f}" for v in vals) + f"{np.mean(vals):9.1f}")
        lines.append(f"  {'PCP':22s}" + "".join(f"{r['pcp'][i]:9.1f}" for i in ids) + f"{r['pcp']['mean']:9.1f}")
        lines.append(f"  {'MPJPE mm':22s}" + "".join(f"{r['mpjpe_mm'][i]:9.1f}" for i in ids) + f"{r['mpjpe_mm']['mean']:9.1f}")
        lines.append(f"  {'joints reconstr. %':22s}" + "".join(f"{r['joints_reconstructed_pct'][i]:9.1f}" for i in ids))
        lines.append(f"  {'frames (missed)':22s}" + "".join(f"{str(r['frames'][i]) + '(' + str(r['missed_frames'][i]) + ')':>9s}" for i in ids))
        lines.append("")
    lines.append(f"tracks started {res['tracks_started']}, ended {res['tracks_ended']}; person-frames from "
                 f"trackers {res['person_frames']['tracker']}, triangulated while initializing "
                 f"{res['person_frames']['triangulated']}")
    t = res["time_ms_per_frame"]
    lines.append(f"time per frame: 2D grouping {t['grouping']:.1f} ms, trackers {t['trackers']:.1f} ms")
    lines.append(f"head mapping: {res['head_mapping']}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    try:
        data = load_shelf(args.data, args.frames)
    except VmocapError as exc:
        print(f"vmocap eval shelf: {exc}", file=sys.stderr)
        return 2
    res = evaluate(data, progress=not args.no_progress)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        print(format_table(res))
    return 0
