"""`vmocap bench images --people N`: the subject among others, exact truth for everyone.

The subject (person 0, the first of --clips) is rendered as the one-person benchmark renders
its clip alone; the others (the next clips, or the subject's clip again with other bodies)
walk around it (render/group.py): person 1 crosses the room in front of the subject from
cam0/cam1's side; person 2 stands beside it, walks out of the capture volume (behind cam2,
seen by one camera) and comes back. The default tracker follows one person: the subject is
scored against its truth, alone and among the others (the same recording without them), and
each output frame is matched to the nearest person's truth: frames nearer another person
(swaps), identity switches, frames near nobody (ghosts), frames where the present subject
has no body.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import VmocapError
from ...keypoints import INDEX
from .accuracy import RATE_HZ
from .clouds import read_clouds
from .images import CONFIGS, FALSE_TRACKING_MM, SCENES, _Provider, default_motions, frame_mpjpe, read_estimates, score

MAX_PEOPLE = 3
DEFAULT_SECONDS = {2: 4.0, 3: 8.0}  # the walks at 2.1 (2) and 2.4 m/s (3)
SIZES = (1.0, 0.93, 1.06)  # body (and truth) scale per person
RATIO_TARGET = 1.10  # issue 32: the subject's MPJPE among others within 10 % of the clip alone
REENTRY_TARGET_S = 0.5  # issue 32: a person who comes back has a body (an id) within this
ABSENT_S = 0.25  # seen by fewer than 2 cameras this long: their next presence is an entry


BESIDE_M = 0.4  # "beside": person 1 stops this far from the line the subject walks along (shoulders all but touch)
FACING_X = 1.05  # "facing": person 1 stands here on the subject's line, 0.55 m from the subject's turning point
HUG_X = 0.75  # "hug": ... 0.25 m from it: the two bodies all but touch and the detector sees them as one


def walker_paths(people: int, seconds: float, scene: str = "cross") -> list[tuple[tuple[float, float, float], ...]]:
    """Waypoints (t_s, x, y) of persons 1.. (the benchmark rig's cameras stand at (+-2.47, +-2.47)).
    1: from beyond the left edge of the room to beyond the right one at y = 0.9, between the
    subject and cam0/cam1 (it enters, crosses in front of the subject, leaves); with scene
    "beside", it walks in at y = BESIDE_M and stops at x = 0 beside the subject (who walks
    along y = 0, x -0.6 ... 0.6), who then passes it again and again shoulder to shoulder; with
    scene "facing", it walks in along that line from beyond the room's +x edge and stops at
    x = FACING_X facing the subject, who walks up to 0.55 m of it (hip to hip: handshake distance,
    each in front of the other for the cameras on the +x side) and back, again and again; with
    scene "hug", the same but it stops at x = HUG_X, 0.25 m from the subject's turning point
    (the distance of a hug: the clips do not embrace, their arms pass through each other).
    2: from behind cam2 (at (-3.9, -3.9) one camera sees it: not present) to stand beside the
    subject at (-1.2, -1.2), out again and back (the subject is alone at the start: the benchmark
    scores the person the tracker starts on)."""
    d = seconds
    out, beside = (-3.9, -3.9), (-1.2, -1.2)
    if scene not in SCENES:
        raise VmocapError(f"scene {scene!r}: one of {', '.join(SCENES)}")
    first = {"beside": ((0.0, -3.0, BESIDE_M), (0.3 * d, 0.0, BESIDE_M), (d, 0.0, BESIDE_M)),
             "facing": ((0.0, 4.2, 0.0), (0.3 * d, FACING_X, 0.0), (d, FACING_X, 0.0)),
             "hug": ((0.0, 4.2, 0.0), (0.3 * d, HUG_X, 0.0), (d, HUG_X, 0.0)),
             "cross": ((0.0, -4.2, 0.9), (d, 4.2, 0.9))}[scene]
    paths: list[tuple[tuple[float, float, float], ...]] = [first]
    paths.append(tuple((f * d, *xy) for f, xy in ((0.0, out), (0.05, out), (0.25, beside), (0.4, beside),
                                                  (0.6, out), (0.7, out), (0.9, beside), (1.0, beside))))
    return paths[: people - 1]


def person_clips(clips: list[Path] | None, people: int) -> list[Path]:
    """--clips A B ...: person k gets the k-th (the last one for the rest); none: the walk clip."""
    files = list(clips or [])
    if not files:
        walk = [p for p in default_motions() if p.stem == "walk"]
        files = walk or default_motions()[:1]
    return [files[min(k, len(files) - 1)] for k in range(people)]


def seen_by(rig, truth: np.ndarray) -> np.ndarray:
    """(P, T) how many cameras have the person's pelvis and neck in front and inside the image
    (no occlusion test: a person hidden behind another still counts)."""
    pts = truth[:, :, [INDEX["pelvis"], INDEX["neck"]]]  # (P, T, 2, 3)
    uv, front = rig.project(pts)  # (C, P, T, 2, 2), (C, P, T, 2)
    size = np.array([[c.width, c.height] for c in rig], float)[:, None, None, None]
    inside = front & np.isfinite(uv).all(axis=-1) & (uv >= 0).all(axis=-1) & (uv < size).all(axis=-1)
    return inside.all(axis=-1).sum(axis=0)


def identity_figures(est: np.ndarray, truths: np.ndarray, present: np.ndarray) -> dict[str, Any]:
    """The output (T, 25, 3) against every person's truth (P, T, 25, 3), the subject first;
    present (T,): the subject is seen by >= 2 cameras. From the first frame with a body on:
    swaps (the body nearer another person than the subject), identity switches (the nearest
    person changes between bodies near someone), ghosts (nobody within FALSE_TRACKING_MM), and
    the share of the frames with the subject present that have no body."""
    d = np.stack([frame_mpjpe(est, g) for g in truths])  # (P, T), NaN where no body
    body = np.isfinite(d).all(axis=0)
    out: dict[str, Any] = {"swap_frames": 0, "identity_switches": 0, "ghost_frames": 0, "missed_pct": None,
                           "first_swap_s": None}
    if not body.any():
        return out
    f = np.arange(np.flatnonzero(body)[0], len(est))
    nearest = np.where(body, np.argmin(np.where(np.isfinite(d), d, np.inf), axis=0), -1)
    ghost = body & (np.nanmin(np.where(np.isfinite(d), d, np.inf), axis=0) > FALSE_TRACKING_MM)
    swap = body & ~ghost & (nearest != 0)
    someone = nearest[body & ~ghost]
    out["swap_frames"] = int(swap[f].sum())
    out["identity_switches"] = int(np.count_nonzero(np.diff(someone)))
    out["ghost_frames"] = int(ghost[f].sum())
    seen = present[f]
    out["missed_pct"] = float(100.0 * (seen & ~body[f]).sum() / seen.sum()) if seen.any() else None
    if swap.any():
        out["first_swap_s"] = float(np.flatnonzero(swap)[0] / RATE_HZ)
    return out


def body_tracks(path: Path, stamps: np.ndarray, namespace: str = "/vmocap") -> dict[str, np.ndarray]:
    """Per REP-155 body id, its keypoints (T, 25, 3) at the truth stamps (NaN where not tracked)."""
    from ...bag import BagReader

    with BagReader(path) as r:
        topics = [t for t in r.topics if t.startswith(f"{namespace}/bodies/") and t.endswith("/keypoints")]
    return {t.split("/")[-2]: read_clouds(path, stamps, t) for t in sorted(topics)}


def entries(present: np.ndarray, absent_frames: int) -> np.ndarray:
    """The frames one person (present (T,): seen by >= 2 cameras) enters view: their first
    presence, and each one after an absence of at least absent_frames."""
    seen = np.flatnonzero(present)
    return seen[np.r_[True, np.diff(seen) > absent_frames]] if seen.size else seen


def identity_switches(ids: np.ndarray, frames: np.ndarray, starts: np.ndarray) -> tuple[int, int]:
    """(switches, new ids at a re-entry) of one person's matched body ids (ids (M,) at frames
    (M,), increasing): a change of id is a switch unless the person entered view again in
    between (starts, `entries`): someone who left is ended and comes back under a new id
    (people_tracker.py, REP-155)."""
    stay = np.searchsorted(starts, frames, side="right")  # which stay in view each frame is in
    changed = np.flatnonzero(np.diff(ids) != 0)
    after_entry = stay[changed] < stay[changed + 1]
    return int((~after_entry).sum()), int(after_entry.sum())


def entry_delays(present: np.ndarray, matched: np.ndarray, absent_frames: int) -> list[float | None]:
    """Per entry of one person (`entries`), the seconds from it to their first body (matched
    (T,)) before they leave again; None: no body in that stretch."""
    starts = entries(present, absent_frames)
    out: list[float | None] = []
    for i, s in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else len(present)
        hit = np.flatnonzero(matched[s:end] & present[s:end])
        out.append(float(hit[0] / RATE_HZ) if hit.size else None)
    return out


def people_figures(bodies: dict[str, np.ndarray], truths: np.ndarray, present: np.ndarray) -> dict[str, Any]:
    """Every person's truth (P, T, 25, 3) against the bodies (id -> (T, 25, 3)); present (P, T):
    the person is seen by >= 2 cameras. Per frame the bodies are matched to the people one to
    one (least summed MPJPE, pairs over FALSE_TRACKING_MM apart are no match). Per person, from
    their first match on: MPJPE and PCK@50 over their matched frames, the share of the frames
    they are present without a body (missed), identity switches (their matched body's id
    changes while they stay in view; a new id after they left and came back is counted apart,
    `reentry_new_ids`), and per entry into view the time to their first body (entry_delays; the first
    entry too). Over the whole recording: the share of the frames they are present without a
    body (`without_body_pct`: the wait for their first body counts too). Frames with a body
    matched to nobody are ghosts."""
    from scipy.optimize import linear_sum_assignment

    ids = list(bodies)
    P, T = truths.shape[:2]
    d = np.full((len(ids), P, T), np.inf)
    for b, est in enumerate(bodies.values()):
        for k in range(P):
            d[b, k] = np.nan_to_num(frame_mpjpe(est, truths[k]), nan=np.inf)
    match = np.full((P, T), -1)
    ghosts = 0
    for t in range(T):
        shown = np.flatnonzero(np.isfinite(d[:, :, t]).any(axis=1))
        if shown.size == 0:
            continue
        cost = np.minimum(d[shown, :, t], 1e6)
        rows, cols = linear_sum_assignment(cost)
        ok = cost[rows, cols] <= FALSE_TRACKING_MM
        match[cols[ok], t] = shown[rows[ok]]
        ghosts += int(shown.size - ok.sum())
    persons: list[dict[str, Any]] = []
    absent = int(round(ABSENT_S * RATE_HZ))
    for k in range(P):
        m = np.flatnonzero(match[k] >= 0)
        delays = entry_delays(present[k], match[k] >= 0, absent)
        timing = {"entry_to_body_s": delays, "reentry_s": max(delays[1:], key=lambda v: np.inf if v is None else v)
                  if len(delays) > 1 else None,
                  "without_body_pct": float(100 * (present[k] & (match[k] < 0)).sum() / max(present[k].sum(), 1))}
        if m.size == 0:
            persons.append({"mpjpe_mm": None, "pck50": None, "missed_pct": None, "identity_switches": 0,
                            "reentry_new_ids": 0, "first_s": None, **timing})
            continue
        f = np.arange(m[0], T)
        kp = np.linalg.norm(np.stack([bodies[ids[match[k, t]]][t] for t in m]) - truths[k, m], axis=-1) * 1000
        kp = kp[:, np.isfinite(truths[k]).all(axis=(0, 2))]
        seen = present[k, f]
        switches, reentry_ids = identity_switches(match[k, m], m, entries(present[k], absent))
        persons.append({"mpjpe_mm": float(kp.mean()), "pck50": float(100 * (kp < 50).mean()),
                        "missed_pct": float(100 * (seen & (match[k, f] < 0)).sum() / max(seen.sum(), 1)),
                        "identity_switches": switches, "reentry_new_ids": reentry_ids,
                        "first_s": float(m[0] / RATE_HZ), "ids": sorted({ids[b] for b in match[k, m]}), **timing})
    return {"persons": persons, "ghost_frames": ghosts, "bodies": len(ids)}


def subject_figures(est: np.ndarray, truths: np.ndarray, present: np.ndarray) -> dict[str, Any]:
    return {**score(est, truths[0]), **identity_figures(est, truths, present)}


def run(args: argparse.Namespace, rig) -> int:
    """The scene of args.people people per config (and the graph for the first), the subject's
    clip alone for the ratio; writes OUT/people.json; exit 1 when the subject was never tracked."""
    from ..process import process_bag
    from ..render.group import GroupSpec, Walker, render_group, truth_topic
    from ..render.recording import ClipSpec, read_truth, render_recording

    if not 2 <= args.people <= MAX_PEOPLE:
        raise VmocapError(f"--people {args.people}: between 2 and {MAX_PEOPLE} (1: the benchmark without --people)")
    if getattr(args, "leave_one_out", False):
        raise VmocapError("--people scores the shipped landmark model: without --leave-one-out")
    max_people = getattr(args, "max_people", 1)
    scene = getattr(args, "scene", "cross")
    if max_people < 1:
        raise VmocapError(f"--max-people {max_people}: at least 1")
    files = person_clips(args.clips, args.people)
    seconds = args.frames / RATE_HZ if args.frames > 0 else DEFAULT_SECONDS[args.people]
    frames = int(round(seconds * RATE_HZ))
    subject = ClipSpec(files[0], frames, RATE_HZ, args.seed)
    walkers = tuple(Walker(ClipSpec(p, frames, RATE_HZ, args.seed, variant=k), path, SIZES[k])
                    for k, (p, path) in enumerate(zip(files[1:], walker_paths(args.people, seconds, scene)), start=1))
    spec = GroupSpec(subject, walkers)
    group = render_group(spec, rig, args.cache, progress=not args.json)
    alone = render_recording(subject, rig, args.cache, progress=not args.json)
    stamps, _ = read_truth(group)
    truths = np.stack([read_truth(group, truth_topic(k))[1] for k in range(args.people)])
    seen = seen_by(rig, truths)
    present = seen[0] >= 2
    persons = [{"clip": s.label(), "shape": s.shape(), "size": SIZES[k], "present_pct": float(100 * (seen[k] >= 2).mean())}
               for k, s in enumerate([subject] + [w.clip for w in walkers])]
    result: dict[str, Any] = {"people": args.people, "scene": scene, "max_people": max_people, "frames": frames, "persons": persons, "recording": str(group),
                              "ratio_target": RATIO_TARGET, "tracker": args.tracker, "runs": {}}
    for name in args.configs:
        rotation, precision = CONFIGS[name]
        runs = {}
        for what, rec in (("group", group), ("alone", alone)):
            out = args.out / f"{rec.stem}_{name}.mcap"
            process_bag(rec, out, rig, config=args.tracker, progress=not args.json,
                        provider=_Provider(rig, rotation, precision), overwrite=True,
                        max_people=max_people if what == "group" else 1)
            runs[what] = read_estimates(out, stamps)
            if what == "group" and max_people > 1:
                everyone = people_figures(body_tracks(out, stamps), truths, seen >= 2)
        row: dict[str, Any] = {"group": subject_figures(runs["group"], truths, present),
                               "alone": subject_figures(runs["alone"], truths[:1], present)}
        if max_people > 1:
            row["everyone"] = everyone
        graph = "none" if args.tracker.get("offline") else args.graph
        if graph == "all" or (graph == "first" and name == args.configs[0]):
            g = importlib.import_module("vmocap_ros.bench.images_graph")  # by name: vmocap_core never imports rclpy
            est_g, counts = g.run_graph(group, args.rig_file, stamps, rotation, precision, args.tracker,
                                        args.graph_rate, args.out, max_people=max_people)
            bodies = counts.pop("bodies", None)
            row["graph"] = {**subject_figures(est_g, truths, present), **counts}
            if bodies is not None:
                row["graph_everyone"] = people_figures(bodies, truths, seen >= 2)
        a, b = row["alone"]["mpjpe_mm"], row["group"]["mpjpe_mm"]
        row["mpjpe_ratio"] = b / a if a and b is not None else None
        result["runs"][name] = row
    (args.out / "people.json").write_text(json.dumps(result, indent=1))
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print_people(result)
    return verdict(result)


def verdict(result: dict[str, Any]) -> int:
    """Loud on stderr where a run misses the target; exit 1 when the subject was never tracked."""
    status = 0
    for name, row in result["runs"].items():
        for run in ("group", "graph"):
            r = row.get(run)
            if r is None:
                continue
            if r["mpjpe_mm"] is None:
                print(f"vmocap bench images --people: {name} {run}: the subject was never tracked", file=sys.stderr)
                status = 1
            elif r["swap_frames"]:
                print(f"vmocap bench images --people: WARNING {name} {run}: the output followed another person in "
                      f"{r['swap_frames']} frames (first at {r['first_swap_s']:.2f} s)", file=sys.stderr)
        for key in ("everyone", "graph_everyone"):
            for k, r in enumerate(row.get(key, {}).get("persons", [])):
                if r["mpjpe_mm"] is None and result["persons"][k]["present_pct"] > 0:
                    print(f"vmocap bench images --people: {name} {key}: person {k} was present and never tracked",
                          file=sys.stderr)
                    status = 1
                late = r.get("reentry_s", None) is None and len(r.get("entry_to_body_s", [])) > 1
                if late or (r.get("reentry_s") or 0.0) > REENTRY_TARGET_S:
                    took = "no body" if late else f"a body after {r['reentry_s']:.2f} s"
                    print(f"vmocap bench images --people: WARNING {name} {key}: person {k} came back into view and had "
                          f"{took} (target {REENTRY_TARGET_S:g} s)", file=sys.stderr)
        ratio = row["mpjpe_ratio"]
        if ratio is not None and ratio > result["ratio_target"]:
            print(f"vmocap bench images --people: WARNING {name}: the subject's MPJPE among others is {ratio:.2f}x "
                  f"the clip alone's (target {result['ratio_target']:.2f}x)", file=sys.stderr)
    return status


def print_people(result: dict[str, Any]) -> None:
    def f(v: Any, fmt: str = ".1f") -> str:
        return "-" if v is None else format(v, fmt)

    print(f"{result['people']} people, {result['frames']} frame sets: " + ", ".join(
        f"{k}: {p['clip']} ({p['shape']}, x{p['size']:g}, present {p['present_pct']:.0f} %)"
        for k, p in enumerate(result["persons"])))
    print(f"{'run':<22}{'MPJPE':>8}{'PCK50':>7}{'swaps':>7}{'switch':>7}{'ghosts':>7}{'missed%':>8}{'init':>6}")
    for name, row in result["runs"].items():
        for run in ("alone", "group", "graph"):
            if run in row:
                r = row[run]
                print(f"{name + ' ' + run:<22}{f(r['mpjpe_mm']):>8}{f(r['pck50']):>7}{r['swap_frames']:>7}"
                      f"{r['identity_switches']:>7}{r['ghost_frames']:>7}{f(r['missed_pct']):>8}"
                      f"{r.get('init_frames', '-'):>6}")
        print(f"{name}: subject MPJPE among others / alone = {f(row['mpjpe_ratio'], '.3f')} "
              f"(target <= {result['ratio_target']:.2f}, 0 swaps)")
        for key, run in (("everyone", "offline"), ("graph_everyone", "node graph")):
            every = row.get(key)
            if not every:
                continue
            print(f"{name} {run}, max_people {result['max_people']}: {every['bodies']} body ids, "
                  f"{every['ghost_frames']} ghost frames")
            for k, r in enumerate(every["persons"]):
                entries = ", ".join("never" if v is None else f"{v:.2f} s" for v in r["entry_to_body_s"])
                print(f"  person {k}: MPJPE {f(r['mpjpe_mm'])} mm, PCK50 {f(r['pck50'])}, missed {f(r['missed_pct'])} % "
                      f"({f(r['without_body_pct'])} % of their time in view, first wait included), "
                      f"switches {r['identity_switches']} (new ids on re-entry {r['reentry_new_ids']}), "
                      f"first body at {f(r['first_s'], '.2f')} s, entry -> body {entries or '-'}")
