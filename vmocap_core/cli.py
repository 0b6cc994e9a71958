"""The `vmocap` command. Each subcommand lives in its own module, imported only when used.

A module named here provides `add_arguments(parser)` and `run(args) -> int`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import VmocapError

# (command words, module, help)
COMMANDS: list[tuple[tuple[str, ...], str, str]] = [
    (("bench", "accuracy"), "vmocap_core.apps.bench.accuracy", "synthetic multi-camera accuracy benchmark"),
    (("bench", "speed"), "vmocap_core.apps.bench.speed", "back-end time per frame"),
    (("bench", "images"), "vmocap_core.apps.bench.images_cli", "image-level benchmark: rendered body, real CNN, 3D truth"),
    (("bench", "opensim"), "vmocap_core.apps.bench.opensim", "OpenSim joint angles against truth through the same scaled model"),
    (("bench", "pcm"), "vmocap_core.apps.bench.pcm", "PCM (CNN) inference time"),
    (("bench", "cnn"), "vmocap_core.apps.bench.cnn", "CNN budget: time of each model variant, interleaved"),
    (("bench", "graph"), "vmocap_ros.bench.graph", "latency and rate of the ROS 2 node graph"),
    (("bench", "faults"), "vmocap_ros.bench.faults", "inject faults into the node graph, bags and recorder"),
    (("bench", "soak"), "vmocap_ros.bench.soak", "the node graph for minutes: RSS, rate, drops, latency per minute"),
    (("models", "fetch"), "vmocap_core.pcm.fetch", "obtain and convert the PCM models (no hubs)"),
    (("models", "check"), "vmocap_core.pcm.selfcheck", "check the int8 CNN against the float one on this CPU"),
    (("process",), "vmocap_core.apps.process", "run the pipeline offline on an MCAP bag"),
    (("config", "check"), "vmocap_core.apps.config_check", "validate a graph config and print the resolved parameters"),
    (("export",), "vmocap_core.export.cli", "export a processed bag as BVH, C3D, TRC or CSV"),
    (("opensim",), "vmocap_core.export.opensim_cli", "a processed bag through OpenSim: scaled model, IK joint angles"),
    (("launch",), "vmocap_ros.launcher", "start the ROS 2 node graph from a config"),
    (("play",), "vmocap_ros.player", "play an MCAP bag onto ROS 2 topics"),
    (("record",), "vmocap_ros.recorder", "record ROS 2 topics into an MCAP bag"),
    (("calibrate",), "vmocap_core.calibration.cli", "calibrate a camera rig from board images/videos"),
    (("eval", "shelf"), "vmocap_core.apps.evaluation.shelf", "Shelf benchmark on real 2D detections"),
    (("eval", "panoptic"), "vmocap_core.apps.evaluation.panoptic", "several people on real Panoptic images, the CNN"),
    (("demo",), "vmocap_core.apps.demo.cli", "end-to-end demo on the Pose2Sim videos"),
    (("report",), "vmocap_core.apps.report", "paper-style results report"),
    (("urdf",), "vmocap_core.outputs.cli", "write the tracked subject's URDF (robot_description)"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vmocap", description=__doc__.splitlines()[0])
    groups: dict[tuple[str, ...], argparse._SubParsersAction] = {}
    top = parser.add_subparsers(dest="command", required=True)
    groups[()] = top
    for words, module, help_text in COMMANDS:
        for depth in range(1, len(words)):
            prefix = words[:depth]
            if prefix not in groups:
                sub = groups[words[: depth - 1]].add_parser(prefix[-1], help=f"{prefix[-1]} commands")
                groups[prefix] = sub.add_subparsers(dest="_".join(prefix), required=True)
        p = groups[words[:-1]].add_parser(words[-1], help=help_text)
        p.set_defaults(_module=module)
        p._vmocap_module = module  # type: ignore[attr-defined]
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    # Find the command without -h (so its help lists the module's own arguments), then let
    # the module add its arguments before the final parse.
    words = [a for a in argv if a not in ("-h", "--help")]
    if not words:
        parser.print_help()
        return 2
    known, _ = parser.parse_known_args(words)
    module = importlib.import_module(known._module)
    sub = _find_subparser(parser, known._module)
    module.add_arguments(sub)
    args = parser.parse_args(argv)
    try:
        return int(module.run(args) or 0)
    except VmocapError as exc:  # bad input: one clear line, no traceback
        print(f"vmocap: error: {exc}", file=sys.stderr)
        return 2


def _find_subparser(parser: argparse.ArgumentParser, module: str) -> argparse.ArgumentParser:
    stack = [parser]
    while stack:
        p = stack.pop()
        if getattr(p, "_vmocap_module", None) == module:
            return p
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())
    raise KeyError(module)


if __name__ == "__main__":
    sys.exit(main())
