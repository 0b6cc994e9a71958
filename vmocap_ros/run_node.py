"""Run vmocap nodes in this process with one executor: `python -m vmocap_ros.run_node CONFIG NODE [NODE...]
[--set node.key=value ...]`. SIGINT/SIGTERM: stop spinning, close every node (outputs flushed,
bags finalized), then shut rclpy down. Prints READY when all nodes exist."""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Iterator

import yaml

DRAIN_S = 0.5  # after SIGINT/SIGTERM, keep handling messages in flight this long
LOCAL_S = 0.05  # in-process hand-overs in a row before the executor gets its turn


def parse_sets(items: list[str]) -> dict[str, dict[str, Any]]:
    """['vmocap_recorder.output=x.mcap', ...] -> {'vmocap_recorder': {'output': 'x.mcap'}}"""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, _, value = item.partition("=")
        node, _, param = key.partition(".")
        if not param:
            raise SystemExit(f"--set wants NODE.PARAM=VALUE, got {item!r}")
        out.setdefault(node, {})[param] = yaml.safe_load(value)
    return out


def _nothing() -> None:
    pass


def make_executor(context=None):
    """rclpy's EventsExecutor (C++ event queue; per message it costs a fraction of the
    SingleThreadedExecutor, which rebuilds a wait set over every entity on each spin) unless
    VMOCAP_EXECUTOR=single_threaded or this rclpy lacks it; on `context` (default: rclpy's)."""
    if os.environ.get("VMOCAP_EXECUTOR", "events") == "events":
        try:
            from rclpy.experimental import EventsExecutor

            return EventsExecutor(context=context)
        except ImportError:
            pass
    from rclpy.executors import SingleThreadedExecutor

    return SingleThreadedExecutor(context=context)


def spin_round(executor: Any, transport: Any, poll_s: float) -> None:
    """One turn of the spin loop: what is due goes out (recorded camera frames), then our nodes
    in this process hand their messages on, then the executor (DDS, timers) gets its turn,
    sleeping until something is due or arrives when nothing is left to do."""
    wait = transport.due.run_due(poll_s)
    busy = transport.bus.drain(max_s=LOCAL_S)
    transport.due.run_idle(idle=not busy)
    executor.spin_once(timeout_sec=0.0 if busy else wait)


def spin_nodes(config_path: str, names: list[str], overrides: dict[str, dict[str, Any]] | None = None,
               ready: Any = None, local_bus: bool = True) -> int:
    from vmocap_core import graph_config

    from .common import StopFlag, init_rclpy

    cfg = graph_config.load(config_path)
    stop = StopFlag().install()
    rclpy = init_rclpy()
    executor = make_executor()
    nodes = []
    from .nodes import create
    from .transport import Transport

    transport = Transport(local=len(names) > 1 and local_bus)
    transport.bus.spin_thread = threading.get_ident()
    # a task posted from another thread wakes a waiting spin_once at once (both executors)
    transport.bus.wake = transport.due.wake = lambda: executor.create_task(_nothing)
    try:
        for name in names:
            node = create(name, cfg, (overrides or {}).get(name), transport)
            nodes.append(node)
            executor.add_node(node)
        for node in nodes:
            node.finalize()
        print("READY " + " ".join(names), flush=True)
        if ready is not None:
            ready()
        while not stop:
            spin_round(executor, transport, transport.bus.poll_s)
        # drain: deliver what is already in flight (e.g. the last outputs to the recorder)
        drain_end = time.monotonic() + DRAIN_S
        while time.monotonic() < drain_end:
            spin_round(executor, transport, 0.05)
    finally:
        for node in reversed(nodes):
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001 - keep closing the others
                print(f"{node.get_name()}: close failed: {exc}", file=sys.stderr)
        transport.bus.wake = transport.due.wake = None
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vmocap_ros.run_node")
    ap.add_argument("config")
    ap.add_argument("nodes", nargs="+")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE")
    a = ap.parse_args(argv)
    from vmocap_core.errors import VmocapError

    try:
        return spin_nodes(a.config, a.nodes, parse_sets(a.set))
    except VmocapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


@contextmanager
def probe_node(name: str, env: dict[str, str]) -> Iterator[tuple[Any, Any]]:
    """(node, executor) of a node in this process on the domain of `env` (a graph this process
    started), with an rclpy context of its own and `env`'s DDS settings only while it lives: a
    caller's own rclpy (a test's listener on another domain) finds the process as it was."""
    keys = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION", "FASTRTPS_DEFAULT_PROFILES_FILE")
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: env[k] for k in keys if k in env})
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(env["ROS_DOMAIN_ID"]), signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, context=context)
    ex = make_executor(context)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.remove_node(node)
        ex.shutdown()
        node.destroy_node()
        context.try_shutdown()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v



if __name__ == "__main__":
    sys.exit(main())
