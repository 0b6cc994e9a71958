"""`vmocap launch CONFIG`: start the node graph of a config (no launch_ros wheel exists).

Default (`vmocap_launch: {mode: processes}`): one process per group of `vmocap_launch.groups`
(nodes of a group pass messages in-process, e.g. a camera's images to the PCM inference) and
one per remaining node (`python -m vmocap_ros.run_node CONFIG NODE [NODE ...]`);
`--single-process` (or `mode: single_process`): all nodes in this process with one executor.
Ctrl-C/SIGTERM: every node is asked to stop (SIGINT), closes its outputs (the recorder
finalizes its MCAP) and exits; stragglers get SIGTERM after --grace seconds, then SIGKILL.
A process that exits on its own is reported (`<group> exited with <code>`); when one of its
nodes is in `vmocap_launch.restart` (or that list is [all]) and it failed (code != 0), it is
started again, at most `restart_limit` times; otherwise the rest of the graph is stopped.
Discovery is localhost-only unless ROS_AUTOMATIC_DISCOVERY_RANGE is set (docs/graph.md).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

from .run_node import parse_sets


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="graph config YAML (see config/graph.yaml)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--single-process", action="store_true", help="all nodes in one process, one executor")
    mode.add_argument("--processes", action="store_true", help="each node its own process (default)")
    parser.add_argument("--nodes", nargs="+", default=None, help="override the config's node list")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="override a parameter")
    parser.add_argument("--grace", type=float, default=5.0, help="seconds a node gets to close on shutdown")


def child_env(profile: str | None = None) -> dict[str, str]:
    from .common import prepare_env

    env = dict(os.environ)
    prepare_env(env, profile)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def run(args: argparse.Namespace) -> int:
    # bad input (VmocapError) is reported by vmocap_core.cli.main
    from vmocap_core import graph_config

    cfg = graph_config.load(args.config)
    nodes = args.nodes or cfg.node_names()
    sets = parse_sets(args.set)
    from vmocap_core.graph_check import check_graph

    check_graph(cfg, nodes, sets)  # overrides included; before anything starts
    single = args.single_process or (cfg.launch["mode"] == "single_process" and not args.processes)
    env = child_env(cfg.launch.get("fastdds_profile"))
    for k, v in (cfg.launch.get("env") or {}).items():
        env[str(k)] = str(v)
    if single:
        if cfg.launch.get("restart"):
            print("vmocap launch: vmocap_launch.restart has no effect in single_process mode (one process: "
                  "nothing is left to restart it)", file=sys.stderr, flush=True)
        os.environ.update(env)
        from .run_node import spin_nodes

        return spin_nodes(args.config, nodes, sets)
    restart = set(cfg.launch.get("restart") or [])
    return run_processes(args.config, cfg.process_groups(nodes), args.set, env, args.grace,
                         restart=restart, restart_limit=int(cfg.launch.get("restart_limit", 3)))


def run_processes(config: str, groups: list[list[str]], sets: list[str], env: dict[str, str], grace: float,
                  restart: set[str] | None = None, restart_limit: int = 3) -> int:
    procs: list[tuple[str, subprocess.Popen]] = []
    stopping = {"flag": False}

    def stop(signum: int, frame: object) -> None:
        stopping["flag"] = True

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    cmds: dict[str, list[str]] = {}
    restartable: set[str] = set()
    for group in groups:
        n = "+".join(group)
        cmd = [sys.executable, "-m", "vmocap_ros.run_node", config, *group]
        for s in sets:
            if any(s.startswith(g + ".") for g in group):
                cmd += ["--set", s]
        cmds[n] = cmd
        if restart and ("all" in restart or restart & set(group)):
            restartable.add(n)
        # own process group: a terminal Ctrl-C reaches us, we forward it in order
        procs.append((n, subprocess.Popen(cmd, env=env, start_new_session=True)))
    print(f"vmocap launch: {len(procs)} processes: " + ", ".join(f"{n}[{p.pid}]" for n, p in procs), flush=True)
    code = 0
    restarts = {n: 0 for n in cmds}
    while not stopping["flag"]:
        time.sleep(0.1)
        dead = [(i, n, p) for i, (n, p) in enumerate(procs) if p.poll() is not None]
        fatal = False
        for i, n, p in dead:
            if n in restartable and p.returncode != 0 and restarts[n] < restart_limit and not stopping["flag"]:
                restarts[n] += 1
                procs[i] = (n, subprocess.Popen(cmds[n], env=env, start_new_session=True))
                print(f"vmocap launch: {n} exited with {p.returncode}; restarted as {n}[{procs[i][1].pid}] "
                      f"(restart {restarts[n]} of {restart_limit})", file=sys.stderr, flush=True)
                continue
            why = (f"restarted {restart_limit} times already" if n in restartable and p.returncode != 0
                   else "not in vmocap_launch.restart" if p.returncode != 0 else "it ended")
            print(f"vmocap launch: {n} exited with {p.returncode}; stopping the graph ({why})", file=sys.stderr, flush=True)
            code = code or p.returncode or 0
            fatal = True
        if fatal:
            break
    for _, p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace
    for n, p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            print(f"vmocap launch: {n} did not stop in {grace} s: SIGTERM", file=sys.stderr)
            p.terminate()
            try:
                p.wait(2.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    return code
