"""`vmocap export BAG.mcap --format bvh|c3d|trc|csv -o FILE`: a recorded or processed session in a
biomechanics format (units, axes and gap handling: export/markers.py, export/bvh.py)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..files import check_output, staged
from .bvh import write_bvh
from .markers import write_c3d, write_csv, write_trc
from .session import load_session

FORMATS = ("bvh", "c3d", "trc", "csv")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="MCAP recording of the graph's outputs or `vmocap process` bag (NS/keypoints, NS/joint_states)")
    parser.add_argument("--format", choices=FORMATS, required=True)
    parser.add_argument("-o", "--output", type=Path, required=True, help="file to write")
    parser.add_argument("--namespace", default="/vmocap")
    parser.add_argument("--recover", action="store_true", help="read a damaged bag: a truncated one up to the damage, "
                        "one with damaged chunks without them (each skipped chunk is reported)")
    parser.add_argument("--overwrite", action="store_true", help="replace the output file(s) if they exist")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON")


def export(session_path: Path, fmt: str, output: Path, namespace: str = "/vmocap", progress: bool = True,
           recover: bool = False, overwrite: bool = False) -> dict:
    """Export one bag; returns the files, frame counts and rate. The files are written complete
    or not at all, never onto the bag, and replace existing ones only with `overwrite`."""
    check_output(output, [session_path], overwrite)  # before reading: a refusal costs nothing
    session = load_session(session_path, namespace, recover=recover)
    if not session.tracked.any():
        from ..errors import VmocapError

        raise VmocapError(f"{session_path}: no tracked frame to export")
    with staged(output, [session_path], overwrite) as tmp:  # written under the final names, moved when complete
        if fmt == "bvh":
            files = [output.with_name(f.name) for f in write_bvh(session, tmp)]
        else:
            {"c3d": write_c3d, "trc": write_trc, "csv": write_csv}[fmt](session, tmp, progress=progress)
            files = [output]
    return {"files": [str(f) for f in files], "frames": session.n_frames, "tracked": int(session.tracked.sum()),
            "segments": len(session.segments()), "rate_hz": session.rate_hz}


def run(args: argparse.Namespace) -> int:
    info = export(args.input, args.format, args.output, args.namespace, progress=not args.json,
                  recover=args.recover, overwrite=args.overwrite)
    if args.json:
        print(json.dumps(info))
    else:
        print(f"{info['frames']} frames ({info['tracked']} tracked, {info['segments']} segments) at "
              f"{info['rate_hz']:.3f} Hz -> {', '.join(info['files'])}", file=sys.stdout)
    return 0
