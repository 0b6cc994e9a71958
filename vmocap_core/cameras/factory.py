"""Build a camera source from a kind and a URI string (the camera node's `source`/`uri`).

URI: ``TARGETS[?key=value&key=value]`` where TARGETS is either one target for every camera
or ``camera=target,camera=target``; a target may contain ``{camera}``. Options become
keyword arguments of the source class (numbers and true/false are converted).

- video:  a file, a folder holding ``<camera>.<ext>``, or a template ``videos/{camera}.mp4``;
          options: fps, offset_frames, loop, realtime, mono, flip, trigger_mode
          (``offset_frames`` may also be given per camera: ``offset.cam1=3``)
- v4l2:   ``/dev/videoN`` per camera; options: width, height, fps, fourcc, mono, buffers, strict
- aravis: an Aravis device id per camera (``Fake_1``, a serial, an IP); options:
          pixel_format, mono, exposure_us, gain_db, fps, trigger, trigger_activation, buffers,
          interfaces (``Fake+GigEVision``)
- bag:    an MCAP file; options: topic, start_offset_s, loop
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl

from ..errors import SourceError
from .base import FrameSource

VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v")


def _value(v: str) -> Any:
    low = v.lower()
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def parse_uri(uri: str) -> tuple[dict[str, str], str | None, dict[str, Any]]:
    """-> (per-camera targets, default target, options)."""
    target, _, query = uri.partition("?")
    per: dict[str, str] = {}
    default = None
    for part in filter(None, (p.strip() for p in target.split(","))):
        if "=" in part and not part.startswith("/"):
            cam, t = part.split("=", 1)
            per[cam.strip()] = t.strip()
        elif default is None:
            default = part
        else:
            raise SourceError(f"source uri '{uri}': several targets without camera names")
    opts = {k: _value(v) for k, v in parse_qsl(query, keep_blank_values=False)}
    return per, default, opts


def _target(uri: str, camera: str, per: dict[str, str], default: str | None) -> str:
    t = per.get(camera, default)
    if t is None:
        raise SourceError(f"camera {camera}: source uri '{uri}' names no target for it (cameras: {sorted(per)})")
    return t.replace("{camera}", camera)


def _video_path(target: str, camera: str) -> Path:
    p = Path(target)
    if p.is_dir():
        hits = [p / f"{camera}{ext}" for ext in VIDEO_EXTS if (p / f"{camera}{ext}").is_file()]
        if not hits:
            raise SourceError(f"camera {camera}: no video named {camera}.* in {p}")
        return hits[0]
    return p


def make_source(kind: str, uri: str, camera: str, **extra: Any) -> FrameSource:
    """A FrameSource of `kind` for `camera` (not opened)."""
    per, default, opts = parse_uri(uri)
    opts.update(extra)
    target = _target(uri, camera, per, default)
    per_cam = {k.split(".", 1)[1]: v for k, v in opts.items() if k.startswith("offset.")}
    opts = {k: v for k, v in opts.items() if not k.startswith("offset.")}
    try:
        if kind == "video":
            from .video import VideoFrameSource

            if camera in per_cam:
                opts["offset_frames"] = int(per_cam[camera])
            return VideoFrameSource(_video_path(target, camera), camera, **opts)
        if kind == "v4l2":
            from .v4l2 import V4L2FrameSource

            return V4L2FrameSource(target, camera, **opts)
        if kind == "aravis":
            from .aravis import AravisFrameSource

            if "interfaces" in opts:
                opts["interfaces"] = tuple(str(opts["interfaces"]).split("+"))
            return AravisFrameSource(target, camera, **opts)
        if kind == "bag":
            from .bag import BagFrameSource

            return BagFrameSource(target, camera, **opts)
    except TypeError as exc:  # an option the source does not take
        raise SourceError(f"camera {camera}: bad {kind} source option ({exc})") from None
    raise SourceError(f"camera {camera}: unknown source kind '{kind}' (video, v4l2, aravis, bag)")
