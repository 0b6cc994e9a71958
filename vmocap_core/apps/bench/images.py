"""`vmocap bench images`: the image-level benchmark with exact 3D truth.

Each motion clip is rendered as a textured MakeHuman body in the benchmark rig's cameras
(vmocap_core.apps.render), written to an MCAP recording (images, camera_info, truth), and run
through the offline pipeline (`vmocap process`: the real CNN on the images, crops from the
fed-back skeleton, lattice search, IK, filter) with image rotation on/off and the CNN in
float and int8, each clip with `--shapes` body shapes. Reported per clip and group (regular /
inverted / floor, motion_groups.py): MPJPE and PCK@50 against the clip, the constant per-joint
offset (mean error vector) and the MPJPE left after removing it, the link-length error, the
share of tracked frames that are wrong (false tracking), and the synthetic benchmark's MPJPE
for the same clip.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ... import paths
from ...errors import VmocapError
from ...graph_config import Topics
from ...keypoints import INDEX, KEYPOINTS
from ...method.results import seed_of, skeleton_of
from ...method.skeleton import BONES
from ...motion import TRANSFORMS, transformed
from ..metrics import acceleration_error, table_one
from . import add_tracker_arguments, tracker_settings
from .accuracy import BUNDLED, RATE_HZ, default_motions
from .blackout import blacked_out, covered, reacquisition_s, window_figures
from .clouds import read_clouds
from .image_figures import overlay, plot_curves
from .motion_groups import GROUPS, motion_group

REPO = paths.REPO
DEFAULT_CACHE = REPO / "out" / "render_cache"
CONFIGS = {"rot-int8": ("all", "int8"), "rot-float": ("all", "float"),
           "norot-int8": ("none", "int8"), "norot-float": ("none", "float")}
DEVELOPMENT = BUNDLED / "development"  # the other DeepMimic clips: lying, rolling, airborne
FALSE_TRACKING_MM = 100.0  # a frame reported tracking with a larger MPJPE is tracking something wrong


class _Provider:
    """The CNN (BlazePosePcm) with an explicit rotation mode and precision, fed like
    process.ModelPcmProvider (detector until a skeleton is fed back)."""

    def __init__(self, rig, rotation: str, precision: str, threads: int = 2, crop_prediction: str = "rigid") -> None:
        from ...method.landmarks import CNN_LANDMARKS
        from ...pcm.pipeline import BlazePosePcm

        self.rig = rig
        self.landmarks = CNN_LANDMARKS
        self.crop_prediction = crop_prediction  # read by Pipeline (method/prediction.py)
        self.pcm = BlazePosePcm(rig, rotation=rotation, threads=threads, precision=precision)
        self.name = f"blazepose-full {precision} (rotation {rotation})"

    def infer(self, images, cameras, stamp_ns, feedback):
        full: list = [None] * len(self.rig)
        for c, img in zip(cameras, images):
            full[int(c)] = img
        # no skeleton fed back: the detector looks for the subject (at the seed, when one came)
        return self.pcm.infer(full, keypoints=skeleton_of(feedback), stamp_ns=stamp_ns,
                             seed=seed_of(feedback))


def read_estimates(path: Path, stamps: np.ndarray) -> np.ndarray:
    """(T, 25, 3) graph keypoints at the truth stamps (NaN where nothing or 'not tracking')."""
    return read_clouds(path, stamps, Topics().keypoints)


def false_tracking(tracked: np.ndarray, error_mm: np.ndarray, limit_mm: float = FALSE_TRACKING_MM) -> dict[str, Any]:
    """Frames reported tracking (`tracked`, (T,) bool) whose MPJPE (`error_mm`, (T,)) is over
    `limit_mm`: their count and their share of the tracked frames (None when none was tracked)."""
    n = int(np.count_nonzero(tracked))
    bad = int(np.count_nonzero(tracked & (error_mm > limit_mm)))
    return {"tracked_frames": n, "false_tracked_frames": bad, "false_tracking_pct": 100.0 * bad / n if n else None}


def score(est: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """Figures from the first tracked frame on (the synthetic benchmark's rule), but
    `output_pct`: the share of all frames, the first ones included, with a body out. A frame
    counts as reported tracked when its keypoint cloud has points: the outputs carry them only
    for the status `tracking` (not while identifying, uncertain or lost)."""
    present = np.isfinite(truth).all(axis=(0, 2))
    reported = np.isfinite(est[:, present]).all(axis=(1, 2))
    false = false_tracking(reported, frame_mpjpe(est, truth))
    tracked = np.flatnonzero(reported)
    if tracked.size == 0:
        return {"mpjpe_mm": None, "pck50": None, "tracked_pct": 0.0, "output_pct": 0.0, "n": 0, **false}
    f = np.arange(tracked[0], len(est))
    e, g = est[f], truth[f]
    res = table_one(e, g, present)
    offset = np.zeros((len(KEYPOINTS), 3))  # constant per-joint offset (definition mismatch)
    offset[present] = np.nanmean(e[:, present] - g[:, present], axis=0)
    res_off = table_one(e - offset[None], g, present)
    bones = [(INDEX[a], INDEX[b]) for a, b in BONES.values() if present[INDEX[a]] and present[INDEX[b]]]
    ia, ib = np.array(bones).T
    L_est = np.nanmedian(np.linalg.norm(e[:, ia] - e[:, ib], axis=-1), axis=0)
    L_true = np.nanmedian(np.linalg.norm(g[:, ia] - g[:, ib], axis=-1), axis=0)
    return {
        "mpjpe_mm": res["mpjpe_mm"], "pck50": res["pck50"], "pck100": res["pck100"], "n": res["n"],
        "groups": res["groups"],
        "tracked_pct": float(100 * np.isfinite(e[:, present]).all(axis=(1, 2)).mean()),
        "output_pct": float(100 * reported.mean()),
        "init_frames": int(tracked[0]),
        "offset_mm": {KEYPOINTS[j]: float(np.linalg.norm(offset[j]) * 1000) for j in np.flatnonzero(present)},
        "mpjpe_without_offset_mm": res_off["mpjpe_mm"],
        "link_length_error_mm": float(np.nanmean(np.abs(L_est - L_true)) * 1000),
        "accel_error_m_s2": acceleration_error(e, g, RATE_HZ, present),
        **false,
    }


def synthetic_figure(path: Path, seed: int) -> float | None:
    """The synthetic benchmark's method MPJPE (mm) for the same clip (its own 4 s extension)."""
    from .accuracy import prepare, run_motion, score_run

    r: Any = score_run(run_motion(prepare(path), seed))
    return float(r["method"]["mpjpe_mm"])


SCENES = ("cross", "beside", "facing", "hug")  # --people: where person 1 walks (people.walker_paths)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--clips", nargs="+", type=Path,
                        help="motion .npz files, or `all`: the shared clips and the development set "
                             "(default: the shared clips)")
    parser.add_argument("--transform", nargs="+", choices=TRANSFORMS, default=[],
                        help="also the motions made from each clip: played backwards (reversed), reflected with left "
                             "and right swapped (mirrored); motions the tracker was not tuned on (motion.transformed)")
    parser.add_argument("--shapes", type=int,
                        help="body shapes per clip: the clip's own (the rendering of before) and the next ones, each "
                             "with its own seeded look (default: 2 with --clips all, else 1: the default run's rows, "
                             "time and figures stay as they were)")
    parser.add_argument("--rig", type=Path, default=REPO / "config" / "benchmark_rig.yaml")
    parser.add_argument("--frames", type=int, default=0,
                        help="frames rendered per clip at 60 Hz (default 0: the whole clip, at least 90)")
    parser.add_argument("--scale", type=float, default=1.0, help="image size factor (0.5: 512x384)")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS),
                        help="rotation (rot: all, norot: none) x CNN precision")
    parser.add_argument("--crop-prediction", default="rigid", choices=("rigid", "previous"),
                        help="the CNN's crops follow the skeleton extrapolated to the frame set (rigid) or the previous "
                             "one (vmocap_pcm's crop_prediction)")
    parser.add_argument("--blackout", type=float, nargs=2, metavar=("FROM_S", "TO_S"),
                        help="every camera black from FROM_S to TO_S seconds into the clip: the JSON's reacquire_s "
                             "is the time from TO_S to the first frame set output as tracked again")
    parser.add_argument("--cover", nargs=3, metavar=("CAMERA", "FROM_S", "TO_S"),
                        help="a grey panel hides the body from one camera from FROM_S to TO_S seconds into the clip (a "
                             "person covered in one view): the JSON's `covered` gives tracked %%, MPJPE and frames over 100 mm then")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="rendered recordings (by content hash)")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "image_bench", help="report, overlays, graph outputs")
    parser.add_argument("--graph", default="first", choices=("first", "all", "none"),
                        help="replay through the ROS 2 node graph too: for the first config (default), all, or none")
    parser.add_argument("--graph-rate", type=float, default=0.0,
                        help="playback speed of the recording in the graph; 0 (default): lockstep, each frame set "
                             "once the previous one's feedback came back (every frame set processed on any CPU)")
    parser.add_argument("--no-synthetic", action="store_true", help="skip the synthetic benchmark's figure")
    parser.add_argument("--leave-one-out", action="store_true",
                        help="score each clip with a landmark model learnt on the other clips (the shipped one was "
                             "learnt on the shared clips: their default figures are in-sample)")
    parser.add_argument("--people", type=int, default=1,
                        help="people in the scene (2 or 3, people.py): the subject (first of --clips) among others "
                             "walking around it (the next clips), scored alone and among them: swaps, ghosts, missed")
    parser.add_argument("--scene", choices=SCENES, default="cross",
                        help="with --people: person 1 crosses the room in front of the subject (cross), or walks in "
                             "and stands beside the subject's path, 0.4 m away (beside), or stands on that path facing "
                             "the subject, who walks up to 0.55 m of it, hip to hip (facing), or to 0.25 m (hug)")
    parser.add_argument("--max-people", type=int, default=1,
                        help="with --people: track up to this many (vmocap process --max-people) and score every "
                             "person: MPJPE, identity switches, missed frames, ghost bodies")
    parser.add_argument("--json", action="store_true")
    add_tracker_arguments(parser)  # --offline: the node graph (live by nature) is not run


def all_clips(clips: list[Path] | None) -> bool:
    """--clips all"""
    return [str(c) for c in clips or []] == ["all"]


def clip_files(clips: list[Path] | None) -> list[Path]:
    """--clips: the given files; `all`: the shared clips and the development set; none: the
    shared clips."""
    if not clips:
        return default_motions()
    if all_clips(clips):
        files = {p.stem: p for p in default_motions()}
        for p in sorted(DEVELOPMENT.glob("*.npz")):
            files.setdefault(p.stem, p)
        return list(files.values())
    return list(clips)


def render(path: Path, rig, args: argparse.Namespace, variant: int = 0) -> tuple[Any, Path, np.ndarray, np.ndarray]:
    """The clip's rendered recording (cached) with body `variant` (0: the clip's own shape):
    (ClipSpec, MCAP path, truth stamps, truth)."""
    from ...motion import load_motion
    from ..render.recording import ClipSpec, read_truth, render_recording

    frames = args.frames
    if frames <= 0:  # the whole clip at the rig rate, at least 1.5 s (0.5 s go to identification)
        m = load_motion(path)
        frames = max(int(round((m.n_frames - 1) / m.fps * RATE_HZ)) + 1, int(1.5 * RATE_HZ))
    spec = ClipSpec(path, frames, RATE_HZ, args.seed, variant)
    rec = render_recording(spec, rig, args.cache, progress=not args.json)
    stamps, truth = read_truth(rec)
    return spec, rec, stamps, truth


def leave_one_out_models(files: list[Path], rig, args: argparse.Namespace) -> dict[str, Path]:
    """Per clip, a landmark model learnt on the other clips only (landmark_fit.py), from their
    lattice markers of a rot-int8 run without a landmark model: clip name -> model file."""
    import yaml
    from tqdm import tqdm

    from ..process import process_bag
    from .landmark_fit import clip_samples, model_yaml, read_markers

    folder = args.out / "landmarks"
    folder.mkdir(exist_ok=True)
    samples = {}
    for path in tqdm(files, desc="landmark samples", disable=args.json):
        _, rec, stamps, truth = render(path, rig, args)
        out = folder / f"{path.stem}_markers.mcap"
        process_bag(rec, out, rig, config={**args.tracker, "landmarks": "none"}, progress=False,
                    provider=_Provider(rig, "all", "int8"), overwrite=True)
        samples[path.stem] = clip_samples(truth, read_markers(out, stamps))
    models = {}
    for held in samples:
        others = [n for n in samples if n != held]
        models[held] = folder / f"without_{held}.yaml"
        note = f"learnt by vmocap bench images --leave-one-out on {', '.join(others)} (rot-int8 lattice markers)"
        models[held].write_text(yaml.safe_dump(model_yaml(f"without-{held}", {n: samples[n] for n in others}, note),
                                               sort_keys=False, default_flow_style=None))
    return models


def run_clip(path: Path, rig, args: argparse.Namespace, variant: int = 0) -> dict[str, Any]:
    """One clip with body `variant`: figures per config (and graph run), its group and shape."""
    from ...motion import load_motion
    from ..process import process_bag

    spec, rec, stamps, truth = render(path, rig, args, variant)
    motion = load_motion(path)
    label = spec.label()
    blackout = getattr(args, "blackout", None)
    if blackout:  # the benchmark's own product in its --out folder
        rec = blacked_out(rec, args.out / f"{label}_blackout.mcap", stamps, tuple(blackout))
    cover = getattr(args, "cover", None)
    if cover:
        if cover[0] not in rig.names:
            raise VmocapError(f"--cover {cover[0]}: not a camera of the rig ({', '.join(rig.names)})")
        covered_s = (float(cover[1]), float(cover[2]))
        rec = covered(rec, args.out / f"{label}_covered.mcap", stamps, truth, rig, cover[0], covered_s)
    row: dict[str, Any] = {"clip": label, "motion": path.stem, "recording": str(rec), "shape": spec.shape(),
                           "frames": len(stamps), "group": motion_group(motion.positions),
                           "inverted": motion.is_inverted(), "landmarks": args.tracker.get("landmarks", "auto")}
    curves: dict[str, np.ndarray] = {}
    for name in args.configs:
        rotation, precision = CONFIGS[name]
        out = args.out / f"{label}_{name}.mcap"
        # the benchmark's own product in its --out folder: a rerun replaces it
        process_bag(rec, out, rig, config=args.tracker, progress=not args.json,
                    provider=_Provider(rig, rotation, precision, crop_prediction=args.crop_prediction), overwrite=True)
        est = read_estimates(out, stamps)
        row[name] = score(est, truth)
        if blackout:
            row[name]["reacquire_s"] = reacquisition_s(est[:, np.isfinite(truth).all(axis=(0, 2))], stamps, blackout[1])
        if cover:
            row[name]["covered"] = {"camera": cover[0], **window_figures(est, truth, stamps, covered_s, FALSE_TRACKING_MM)}
        curves[name] = frame_mpjpe(est, truth)
        if name == args.configs[0]:
            overlay(rec, rig, truth, est, len(stamps) // 2, args.out / f"{label}.png")
        graph = "none" if args.tracker.get("offline") else args.graph
        if graph == "all" or (graph == "first" and name == args.configs[0]):
            # vmocap_ros is imported by name (as cli.py does): vmocap_core itself never imports rclpy
            g = importlib.import_module("vmocap_ros.bench.images_graph")
            est_g, counts = g.run_graph(rec, args.rig_file, stamps, rotation, precision, args.tracker, args.graph_rate,
                                        args.out, crop_prediction=args.crop_prediction)
            row[f"graph:{name}"] = {**score(est_g, truth), **counts}
            if cover:
                row[f"graph:{name}"]["covered"] = {"camera": cover[0], **window_figures(est_g, truth, stamps, covered_s,
                                                                                        FALSE_TRACKING_MM)}
            curves[f"graph:{name}"] = frame_mpjpe(est_g, truth)
    if not args.no_synthetic and variant == 0:  # no body in the synthetic benchmark: once per clip
        row["synthetic_mpjpe_mm"] = synthetic_figure(path, args.seed)
    plot_curves(label, row, curves, args.out / f"{label}_mpjpe.png")
    return row


def frame_mpjpe(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T,) mean error (mm) over the clip's keypoints per frame (NaN while not tracking)."""
    present = np.isfinite(truth).all(axis=(0, 2))
    return np.linalg.norm(est[:, present] - truth[:, present], axis=-1).mean(axis=1) * 1000


def _pool(rows: list[dict[str, Any]], name: str, key: str) -> float | None:
    v = [(r[name][key], r[name]["n"]) for r in rows if r[name].get(key) is not None and np.isfinite(r[name][key])]
    return float(sum(a * n for a, n in v) / sum(n for _, n in v)) if v else None


def _pool_false_tracking(rows: list[dict[str, Any]], name: str) -> float | None:
    n = sum(r[name].get("tracked_frames", 0) for r in rows)
    return 100.0 * sum(r[name].get("false_tracked_frames", 0) for r in rows) / n if n else None


def summarize(clips: dict[str, dict[str, Any]], configs: list[str], key: str, labels: dict[str, Any]) -> dict[str, Any]:
    """Figures pooled per group: rows whose `key` equals labels[group] (joint-frame weighted;
    false tracking over the tracked frames), for the runs every row of the group has."""
    summary = {}
    for label, value in labels.items():
        rows = [r for r in clips.values() if r[key] == value]
        if rows:
            runs = [c for c in list(configs) + [f"graph:{c}" for c in configs] if all(c in r for r in rows)]
            summary[label] = {c: {**{k: _pool(rows, c, k) for k in ("mpjpe_mm", "pck50", "mpjpe_without_offset_mm",
                                                                    "link_length_error_mm", "accel_error_m_s2")},
                                  "false_tracking_pct": _pool_false_tracking(rows, c), "rows": len(rows)} for c in runs}
    return summary


def prepare(args: argparse.Namespace) -> tuple[list[Path], range, Any]:
    """The clips, body variants and (scaled, saved) rig of a run, its folders made and its
    tracker settings resolved into `args`: what `run` and people.py's run share."""
    from ...cameras.rig_file import load_rig, save_rig
    from ..render.body import SHAPES
    from ..render.recording import scale_rig

    files = clip_files(args.clips)
    files += [transformed(f, kind, args.cache / "transformed") for f in list(files) for kind in args.transform]
    if not files:
        raise VmocapError("no motion clips (give --clips)")
    if args.shapes is None:
        args.shapes = 2 if all_clips(args.clips) else 1
    if not 1 <= args.shapes <= len(SHAPES):
        raise VmocapError(f"--shapes {args.shapes}: between 1 and {len(SHAPES)} (the body shapes {sorted(SHAPES)})")
    variants = range(args.shapes)
    rig = scale_rig(load_rig(args.rig), args.scale)
    args.out, args.cache = args.out.resolve(), args.cache.resolve()  # the graph's config lives in --out
    args.out.mkdir(parents=True, exist_ok=True)
    args.rig_file = args.out / "rig.yaml"  # the (scaled) rig the graph loads
    args.tracker = tracker_settings(args, RATE_HZ)
    save_rig(rig, args.rig_file)
    return files, variants, rig


def run(args: argparse.Namespace) -> int:
    """`vmocap bench images` for one person per scene (images_cli.py dispatches --people)."""
    files, variants, rig = prepare(args)
    if args.leave_one_out:
        if len(files) < 2:
            raise VmocapError("--leave-one-out needs at least two clips")
        models = leave_one_out_models(files, rig, args)
        rows = [run_clip(p, rig, argparse.Namespace(**{**vars(args), "tracker": {
            **args.tracker, "landmarks": str(models[p.stem])}}), v) for p in files for v in variants]
    else:
        rows = [run_clip(p, rig, args, v) for p in files for v in variants]
    clips = {r["clip"]: r for r in rows}
    result = {"clips": clips, "summary": summarize(clips, args.configs, "group", {g: g for g in GROUPS}),
              # the split of before (neck below both ankles in some frame: inverted), for comparisons
              "summary_by_inversion": summarize(clips, args.configs, "inverted", {"regular": False, "inverted": True}),
              "false_tracking_mm": FALSE_TRACKING_MM, "shapes": args.shapes, "frames": args.frames,
              "scale": args.scale, "seed": args.seed, "tracker": args.tracker,
              "landmarks": landmarks_used(args, sorted({r["motion"] for r in rows}))}
    (args.out / "report.json").write_text(json.dumps(result, indent=1))
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print_table(result, args.configs)
    bad = [n for n, r in clips.items() if all(r[c]["mpjpe_mm"] is None for c in args.configs)]
    if bad:  # a figure of the benchmark (reported, pooled figures leave them out), loud
        print(f"vmocap bench images: WARNING never tracked (left out of the pooled figures): {bad}", file=sys.stderr)
    return 1 if len(bad) == len(clips) else 0


def landmarks_used(args: argparse.Namespace, clips: list[str]) -> str:
    """Which landmark model the CNN's runs used, and whether it saw the scored clips."""
    from ...method.landmarks import CNN_LANDMARKS, load_landmarks, resolve

    if args.leave_one_out:
        return "leave-one-out: each clip with a model learnt on the others (OUT/landmarks)"
    model = load_landmarks(resolve(args.tracker.get("landmarks", "auto"), CNN_LANDMARKS))
    if model is None:
        return "none (joint centres)"
    seen = [c for c in clips if c in model.learnt_on]
    return model.name + (f", learnt on {', '.join(seen)} among others: figures on those are in-sample "
                         "(--leave-one-out for held-out ones)" if seen else "")


def _f(v: float | None, fmt: str = "6.1f") -> str:
    return "    - " if v is None else format(v, fmt)


def print_table(result: dict[str, Any], configs: list[str]) -> None:
    first = next(iter(result["clips"].values()))
    runs = list(configs) + [f"graph:{c}" for c in configs if f"graph:{c}" in first]
    print(f"{'clip':<24}{'group':>9} {'shape':>8} | " + " | ".join(f"{c:>25}" for c in runs) + " | synthetic")
    print(f"{'':<42} | " + " | ".join(f"{'MPJPE  PCK50  -off  false%':>25}" for _ in runs) + " |")
    for name, r in result["clips"].items():
        cells = [f"{_f(r[c]['mpjpe_mm'])} {_f(r[c]['pck50'], '5.1f')} {_f(r[c].get('mpjpe_without_offset_mm'))} "
                 f"{_f(r[c].get('false_tracking_pct'), '5.1f')}" if c in r else f"{'':>25}" for c in runs]
        print(f"{name:<24}{r['group']:>9} {r['shape']:>8} | " + " | ".join(cells)
              + f" | {_f(r.get('synthetic_mpjpe_mm'))}")
    print(f"landmark model: {result['landmarks']}")
    print(f"false%: share of the frames reported tracking whose MPJPE is over {result['false_tracking_mm']:g} mm")
    for label, s in result["summary"].items():
        print(f"{label.upper()}: " + "; ".join(f"{c} {_f(v['mpjpe_mm'], '.1f')} mm (PCK50 {_f(v['pck50'], '.1f')} %, "
                                               f"false tracking {_f(v['false_tracking_pct'], '.1f')} %, "
                                               f"link {_f(v['link_length_error_mm'], '.1f')} mm, acceleration error "
                                               f"{_f(v['accel_error_m_s2'], '.1f')} m/s^2)" for c, v in s.items()))
