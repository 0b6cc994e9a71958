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
    """Several people run in vmocap_people, one person in vmocap_pcm/markers/skeleton: not both
    (they would publish the same subject topics), and max_people > 1 only with vmocap_people."""
    kinds = {node_type(n): n for n in params}
    single = [kinds[k] for k in ("vmocap_pcm", "vmocap_markers", "vmocap_skeleton") if k in kinds]
    if "vmocap_people" in kinds and single:
        raise GraphConfigError(cfg.path, "vmocap_launch.nodes", f"vmocap_people tracks everyone itself: not with "
                               f"{', '.join(single)} (they publish the same subject topics)")
    many = [n for n, p in params.items() if p.get("max_people", 1) > 1 and node_type(n) != "vmocap_people"]
    if many and "vmocap_people" not in kinds and single:
        raise GraphConfigError(cfg.path, "max_people", f"{params[many[0]]['max_people']}: several people are tracked by "
                               "vmocap_people (config/people.yaml), which this graph does not run; "
                               "vmocap_pcm/markers/skeleton follow one subject")


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
