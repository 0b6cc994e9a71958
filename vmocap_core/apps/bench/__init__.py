"""Benchmark commands: they print figures (and JSON with --json); tests do not time things."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    """The tracker options both accuracy benchmarks take (PipelineConfig keys)."""
    parser.add_argument("--config", type=Path, help="tracker parameters (YAML mapping)")
    parser.add_argument("--offline", action="store_true",
                        help="offline mode: whole-clip identification, RTS smoother, second IK (offline.py)")
    parser.add_argument("--lag", type=int, metavar="N", help="live fixed-lag smoothing over N frames (smoothing_lag_frames)")


def tracker_settings(args: argparse.Namespace, fps: float) -> dict[str, Any]:
    """The flat tracker settings (`PipelineConfig.from_dict`) that add_tracker_arguments' options ask for."""
    cfg: dict[str, Any] = {"fps": fps}
    if args.config:
        import yaml

        cfg.update(yaml.safe_load(args.config.read_text()) or {})
    if args.offline:
        cfg["offline"] = True
    if args.lag is not None:
        cfg["smoothing_lag_frames"] = args.lag
    return cfg
