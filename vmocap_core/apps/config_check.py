"""`vmocap config check FILE`: validate a graph config and print every node's resolved
parameters (defaults < '/**' < the node type's section < an instance's own section) and the
processes `vmocap launch` would start."""

from __future__ import annotations

import argparse
import json

from .. import graph_config
from ..graph_check import check_graph


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="graph config YAML (e.g. config/live.yaml)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    cfg = graph_config.load(args.config)  # GraphConfigError names the file, section and key
    check_graph(cfg)  # values that cannot work with the rig or the files
    nodes = {n: cfg.node_params(n) for n in cfg.node_names()}
    single = cfg.launch["mode"] == "single_process"
    processes = [cfg.node_names()] if single else cfg.process_groups()
    if args.json:
        print(json.dumps({"nodes": nodes, "processes": processes, "mode": cfg.launch["mode"]}, indent=1))
        return 0
    print(f"{cfg.path}: valid; mode {cfg.launch['mode']}, processes: " + "; ".join(" + ".join(g) for g in processes))
    for name, params in nodes.items():
        print(f"\n{name} ({graph_config.node_type(name)})")
        for key, value in sorted(params.items()):
            print(f"  {key}: {value}")
    return 0
