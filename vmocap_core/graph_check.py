"""Checks of a graph config against its rig and files, before any node starts (`vmocap config
check`, `vmocap launch`): values that each pass graph_config's type and range checks but cannot
work together, e.g. `min_cameras` above the rig's camera count, cameras or views the rig lacks,
a rig, bag, video or model file that does not exist, a recorder that would replace a file."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from .errors import OutputPathError
from .files import check_output
from .graph_config import GraphConfig, GraphConfigError, node_type

# files each recorded source kind reads (live cameras appear when plugged in: not checked)
_FILE_SOURCES = ("bag", "video")


def check_graph(cfg: GraphConfig, nodes: list[str] | None = None, overrides: dict[str, dict[str, Any]] | None = None) -> None:
    """Raise GraphConfigError naming the file, node and parameter of the first value that
    cannot work with the rig or the file system."""
    nodes = cfg.node_names() if nodes is None else nodes
    params = {n: cfg.node_params(n, (overrides or {}).get(n)) for n in nodes}
    _people(cfg, params)
    inputs: list[str] = []
    for node, p in params.items():
        cams = _cameras(cfg, node, p)
        kind = node_type(node)
        if kind in ("vmocap_pcm", "vmocap_markers") and cams is not None:
            views = p.get("views") or cams
            _views(cfg, node, views, cams)
            # a PCM worker for some of the cameras (`cameras` given) syncs what it has: the
            # tracker's frame sets are what need min_cameras views
            if p["min_cameras"] > len(views) and not (kind == "vmocap_pcm" and p["cameras"]):
                raise GraphConfigError(cfg.path, f"{node}.min_cameras", f"{p['min_cameras']} is more than the "
                                       f"{len(views)} {'views' if p.get('views') else 'cameras'} {views}")
        if kind == "vmocap_camera":
            inputs += _source_files(cfg, node, p, cams)
        if kind == "vmocap_pcm" and (p["source"] == "synthetic" or str(p["model"]).endswith(".mcap")):
            inputs.append(_existing(cfg, f"{node}.model", p["model"], "file"))
    for node, p in params.items():
        if node_type(node) == "vmocap_recorder" and p["output"]:
            try:
                check_output(p["output"], inputs + [str(cfg.path)], p["overwrite"])
            except OutputPathError as exc:
                raise GraphConfigError(cfg.path, f"{node}.output", str(exc)) from None


def _people(cfg: GraphConfig, params: dict[str, dict[str, Any]]) -> None:
    """Several people (max_people > 1): one vmocap_pcm finds everyone with BlazePose's person
    detector and crops each of them, so it needs that CNN and every camera's images."""
    stages = {n: p for n, p in params.items() if node_type(n) in ("vmocap_pcm", "vmocap_markers", "vmocap_skeleton")}
    for key in ("max_people", "end_after_s"):  # each side applies them: they must agree
        values = {p[key] for p in stages.values()}
        if len(values) > 1:
            raise GraphConfigError(cfg.path, key, f"the stage nodes disagree ({', '.join(f'{n}: {p[key]}' for n, p in stages.items())}): "
                                   "set it once, under /**")
    pcms = [n for n in params if node_type(n) == "vmocap_pcm"]
    for node in pcms:
        p = params[node]
        if p["max_people"] <= 1:
            continue
        if p["source"] != "model" or p["model"] not in ("blazepose", "blazepose-lite"):
            raise GraphConfigError(cfg.path, f"{node}.model", f"{p['model'] or p['source']!r}: max_people "
                                   f"{p['max_people']} needs 'blazepose' or 'blazepose-lite' (its person detector finds "
                                   "the people)")
        if len(pcms) > 1 or p["cameras"]:
            raise GraphConfigError(cfg.path, f"{node}.cameras", f"max_people {p['max_people']}: one vmocap_pcm for "
                                   "every camera (it finds the people across all of them), not a worker per camera")


def _existing(cfg: GraphConfig, key: str, path: str, what: str) -> str:
    if not path or not os.path.exists(path):
        raise GraphConfigError(cfg.path, key, f"{path or '(empty)'}: no such {what}")
    return path


def _cameras(cfg: GraphConfig, node: str, p: dict[str, Any]) -> list[str] | None:
    """The node's cameras (its rig restricted to `cameras`), None without a rig."""
    from .cameras.rig_file import load_rig

    if not p["rig"]:
        if p["cameras"]:
            raise GraphConfigError(cfg.path, f"{node}.cameras", f"{p['cameras']} given, but no rig names cameras")
        return None
    names = load_rig(_existing(cfg, f"{node}.rig", p["rig"], "rig file")).names
    unknown = [c for c in p["cameras"] if c not in names]
    if unknown:
        raise GraphConfigError(cfg.path, f"{node}.cameras", f"{unknown} not in the rig {p['rig']} (cameras: {names})")
    return list(p["cameras"]) or list(names)


def _views(cfg: GraphConfig, node: str, views: list[str], cams: list[str]) -> None:
    """A view is a camera or an extra rotated view of one (CAM_1, CAM_2 ...)."""
    unknown = [v for v in views if v not in cams and re.sub(r"_\d+$", "", v) not in cams]
    if unknown:
        raise GraphConfigError(cfg.path, f"{node}.views", f"{unknown} are not cameras of the rig (or CAM_N views "
                               f"of them); cameras: {cams}")


def _source_files(cfg: GraphConfig, node: str, p: dict[str, Any], cams: list[str] | None) -> list[str]:
    """The bag or video files a recorded source reads (each must exist); per-camera targets
    must name cameras of the rig."""
    from .cameras.factory import parse_uri

    if p["source"] not in _FILE_SOURCES:
        return []
    per, default, _ = parse_uri(p["uri"])
    if cams is not None:
        unknown = [c for c in per if c not in cams]
        if unknown:
            raise GraphConfigError(cfg.path, f"{node}.uri", f"names cameras {unknown} the rig lacks (cameras: {cams})")
    targets = list(per.values()) + ([default] if default else [])
    if not targets:
        raise GraphConfigError(cfg.path, f"{node}.uri", f"source {p['source']} needs a file (uri is empty)")
    files = []
    for t in targets:
        for cam in (cams or [""]) if "{camera}" in t else [""]:
            files.append(_existing(cfg, f"{node}.uri", t.replace("{camera}", cam), "file or folder"))
    return [f for f in files if Path(f).is_file()]
