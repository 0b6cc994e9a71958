"""`vmocap opensim SESSION.mcap -o DIR`: a processed or live recording through OpenSim (marker
TRC, scaled model, IK joint angles, IK marker errors, a plot of the main joint angles;
export/opensim.py). OpenSim is optional: `pip install 'vmocap[opensim]'`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..files import check_output, staged
from .session import load_session


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="MCAP recording of the graph's outputs or `vmocap process` bag")
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder for the files (created)")
    parser.add_argument("--name", help="file name stem (default: the input's)")
    parser.add_argument("--namespace", default="/vmocap")
    parser.add_argument("--recover", action="store_true", help="read a damaged bag up to / around the damage")
    parser.add_argument("--overwrite", action="store_true", help="replace earlier files of the same name in the folder")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def opensim_export(session_path: Path, folder: Path, stem: str | None = None, namespace: str = "/vmocap",
                   progress: bool = True, recover: bool = False, overwrite: bool = False) -> dict:
    """Run the round trip; the files appear in `folder` all together when it succeeded (never
    onto the input, replacing earlier ones only with `overwrite`)."""
    from .opensim import import_opensim, round_trip

    import_opensim()  # the one-line install hint before reading anything
    stem = stem or session_path.stem
    check_output(folder / f"{stem}.trc", [session_path], overwrite)
    session = load_session(session_path, namespace, recover=recover)
    with staged(folder / f"{stem}.trc", [session_path], overwrite) as tmp:
        info = round_trip(session, tmp.parent, stem, progress=progress)
    info["files"] = [str(folder / Path(f).name) for f in info["files"]]
    return info


def run(args: argparse.Namespace) -> int:
    info = opensim_export(args.input, args.output, args.name, args.namespace, progress=not args.json,
                          recover=args.recover, overwrite=args.overwrite)
    info.pop("ik")
    for w in info["warnings"]:
        print(f"WARNING: {w}", file=sys.stderr)
    if args.json:
        print(json.dumps(info))
    else:
        rms = info["marker_rms_mm"]
        print(f"{info['frames']} frames ({info['tracked']} tracked, {info['segments']} segments) at {info['rate_hz']:.3f} Hz; "
              f"IK marker RMS error median {rms['median']:.1f} mm (max {rms['max']:.1f}) -> {', '.join(info['files'])}")
    return 0
