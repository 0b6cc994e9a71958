"""`vmocap record -o OUT.mcap [TOPIC ...]`: record topics (default: the graph outputs) into a
rosbag2-compatible MCAP. Ctrl-C/SIGTERM close the file properly (footer + summary, then the
rename from OUT.mcap.partial to OUT.mcap)."""

from __future__ import annotations

import argparse
import sys

from .common import CONFIG_DIR


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topics", nargs="*", help="topics to record (default: the graph outputs)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write")
    parser.add_argument("--namespace", default="/vmocap", help="graph namespace (for the default topics)")
    parser.add_argument("--compression", default="none", choices=("none", "zstd", "lz4"))
    parser.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    parser.add_argument("--config", default=str(CONFIG_DIR / "graph.yaml"), help="graph config (for shared parameters)")


def run(args: argparse.Namespace) -> int:
    from vmocap_core.errors import VmocapError

    from .run_node import spin_nodes

    overrides = {"vmocap_recorder": {"output": args.output, "topics": list(args.topics) or [""],
                                     "compression": args.compression, "namespace": args.namespace,
                                     "overwrite": args.overwrite}}
    try:
        return spin_nodes(args.config, ["vmocap_recorder"], overrides)
    except VmocapError as exc:
        print(f"vmocap record: {exc}", file=sys.stderr)
        return 2  # bad input, as every vmocap command
