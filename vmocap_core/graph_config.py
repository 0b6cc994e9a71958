"""The node graph's configuration: one ROS 2 parameter file (config/*.yaml) for all nodes.

Layout (standard ROS 2 params-file syntax, so `ros2 run ... --params-file` and the launch
file in launch/ read it too)::

    /**:                      # shared by every node
      ros__parameters: {rig: ..., cameras: [...], namespace: /vmocap, ...}
    vmocap_markers:           # one section per node, named as the node
      ros__parameters: {...}
    vmocap_launch:            # read by `vmocap launch` only (not a node)
      mode: processes         # or single_process
      nodes: [vmocap_markers, vmocap_skeleton]
      restart: [vmocap_recorder]   # processes mode: restart these nodes' process when it dies ([all]: any)
      restart_limit: 3        # at most this many restarts per process, then the graph stops

Every parameter is declared here with a type (from its default), a description and a range;
a key that is not declared is rejected with GraphConfigError naming the file and the key.
Relative paths in values are resolved against the config file's directory.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .errors import VmocapError
from .topics import Topics  # noqa: F401 (re-exported: the graph's topic names)


class GraphConfigError(VmocapError):
    """A graph config file with a missing, unknown or out-of-range parameter."""

    def __init__(self, path: object, key: str, problem: str) -> None:
        self.path, self.key, self.problem = str(path), key, problem
        super().__init__(f"{self.path}: parameter '{key}': {problem}")


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] | None = None
    path: bool | str = False  # resolve relative to the config file ("auto": when it looks like a file)


COMMON = [
    Param("rig", "", "rig YAML (vmocap_core.cameras.rig_file format)", path=True),
    Param("cameras", [""], "camera names (rig order subset); empty: all cameras of the rig"),
    Param("namespace", "/vmocap", "topic prefix of the graph"),
    Param("pcm_keypoints", [""], "KEYPOINTS names of the PCM channels, in channel order; empty: all 25"),
    Param("use_sim_time", False, "take time from /clock (set when playing a bag)"),
    Param("fps", 30.0, "the cameras' frame rate (Hz): the filter's and the motion prior's time step", 1.0, 1000.0),
    Param("binning", 1, "camera images reduced this many times, 1, 2, 4 or 8 (REP 104): vmocap_camera publishes them so "
          "(JPEGs decoded directly at that size; CameraInfo binning_x/y) and vmocap_pcm cuts its crops from them; the rig "
          "stays at full resolution. For subjects spanning more than binning x 256 px: less decoding and copying", 1, 8),
    Param("lockstep", False, "recorded sources: vmocap_camera sends a frame set once the skeleton's feedback for the one "
          "before came back (the paper's causal loop), so every frame set is processed in order at the speed of this "
          "machine and the outputs equal `vmocap process`'s; `rate` is then ignored. Live cameras ignore it"),
    Param("shm_images", True, "vmocap_camera hands its frames to vmocap_pcm nodes in other processes of this machine "
          "through shared memory (NS/CAM/image_raw/shm carries references, cameras/shm.py) instead of sending the "
          "pixels over DDS, while flow control applies; a PCM node that cannot reach the memory (another machine) "
          "stops taking the references and gets the images over DDS"),
    Param("max_people", 1, "people tracked at once. 1: the subject; more: everyone in view up to this many, each a "
          "REP-155 body: vmocap_pcm finds them (BlazePose's detector) and crops each one, vmocap_markers and "
          "vmocap_skeleton run one stage per person on the topics of their slot, NS/people/slotK/... "
          "(method/people_look.py, people_stages.py)", 1, 32),
    Param("end_after_s", 1.0, "several people: a person without a skeleton this long (s) is ended (vmocap_pcm stops "
          "cropping them, vmocap_skeleton takes their body id off /humans/bodies/tracked)", 0.05, 600.0),
    Param("lockstep_timeout_ms", 10000.0, "lockstep: a frame set nobody answers (no person in any view, a node down) "
          "releases the next one after this long; the PCM and markers nodes wait for feedback at least this long", 1.0, 1e6),
]

NODE_PARAMS: dict[str, list[Param]] = {
    "vmocap_camera": [
        Param("source", "bag", "frame source kind", choices=("bag", "video", "aravis", "v4l2")),
        Param("uri", "", "source URI (vmocap_core.cameras.factory): bag file, video file/folder/template, "
              "/dev/videoN or Aravis ids, per camera as cam0=...,cam1=...; options after '?'", path="auto"),
        Param("rate", 1.0, "playback speed of recorded sources (0: as fast as possible)", 0.0, 100.0),
        Param("loop", False, "restart recorded sources at their end"),
        Param("start_offset", 0.0, "skip this many seconds of a recording", 0.0, 1e6),
        Param("wait_subscribers", 5.0, "recorded sources: before the first frame, wait up to this long (s) until "
              "every image topic has a subscriber (frames sent before the PCM node matched are lost)", 0.0, 600.0),
        Param("wait_topics", [""], "recorded sources: also wait (up to wait_subscribers) until each of these topics "
              "has a subscriber, e.g. the outputs a recorder in another process records (frames played before it "
              "matched give outputs it never gets)"),
        Param("recover", False, "recorded sources: read the intact parts of a damaged recording (chunks that fail "
              "their CRC, a truncated file) instead of refusing it"),
        Param("restamp", False, "recorded sources: stamp each frame with the wall-clock time it is published at "
              "(as a live camera stamps its capture time; loops keep counting forward)"),
        Param("reconnect_s", 1.0, "live cameras (aravis, v4l2): after a disconnection, try to reopen the camera "
              "every this many seconds", 0.05, 60.0),
        Param("max_in_flight", 2, "frame sets sent but not yet finished by the CNN (NS/pcm/done) beyond which "
              "newer frame sets are not sent (cameras/flow.py): an overloaded graph spends its cores on the frame "
              "sets it processes. Only while the images go to vmocap_pcm nodes in other processes and to nobody "
              "else (a recorder of the images gets every frame); 0: off; lockstep replaces it", 0, 1000),
        Param("reconnect_attempts", 60, "live cameras: give a disconnected camera up after this many failed "
              "reopen attempts (its thread ends, the node and the other cameras go on)", 1, 1000000),
    ],
    "vmocap_pcm": [
        Param("source", "model", "where heatmaps come from", choices=("model", "synthetic")),
        Param("model", "", "source=model: 'blazepose' / 'blazepose-lite' (the CNN) or a bag of heatmaps (*.mcap); "
              "source=synthetic: the motion clip (.npz)", path="auto"),
        Param("rotation", "all", "CNN input rotation (paper III-B): all = each crop rotated upright; lower_body = "
              "an extra rotated view per camera for the lower body (views CAM and CAM_1); none", choices=("all", "lower_body", "none")),
        Param("crop_prediction", "rigid", "the crops follow the skeleton extrapolated to the frame set by the body's "
              "rigid motion between the last two feedbacks (method/prediction.py), or the previous skeleton as it was",
              choices=("rigid", "previous")),
        Param("threads", 2, "onnxruntime threads of the CNN", 1, 64),
        Param("sync_tolerance_ms", 8.0, "max stamp difference of frames in one frame set", 0.0, 1000.0),
        Param("min_cameras", 2, "fewest cameras a frame set needs", 1, 64),
        Param("silent_after_ms", 500.0, "a camera without frames this long is reported silent", 1.0, 1e6),
        Param("use_feedback", True, "crop/rotate with the skeleton of the previous frame"),
        Param("feedback_wait_ms", 0.0, "0: crop with the latest skeleton (pipelined, fastest; several people: the "
              "detector's searches run beside the frame sets); > 0: frame t waits (at most this long) for the "
              "skeleton of frame t-1, exactly as offline (deterministic)", 0.0, 1e5),
        Param("queue_depth", 2, "frame sets waiting for the CNN (at least 2 images per camera topic are kept); when "
              "the node falls behind, older frame sets are dropped (2: a frame set that took longer than a period "
              "costs no frame set; 1 keeps only the newest: lower latency under overload, drops at the edge)", 1, 1000),
        Param("inference_thread", True, "run the CNN in a thread of its own, beside the spin loop (the process's "
              "other nodes work while it runs); false: inside the subscription callback"),
        Param("census_every", 15, "while tracking, the CNN's detector looks for other people (diagnostics "
              "others_in_view; with nobody else counted, vmocap_skeleton's path gate lets a track far off the "
              "subject's path go on) on one camera every this many frame sets, in a thread at the lowest CPU priority "
              "(frame sets never wait for it; skipped while the last look runs); 0: only at initialization", 0, 1000000),
        Param("detect_every_s", 0.5, "several people: while fewer than max_people are tracked, the detector looks for "
              "newcomers this often (s, capture time); it runs on every frame set while someone is being found or was "
              "lost", 0.0, 60.0),
        Param("glance_every_s", 0.2, "several people: between those searches, the detector glances at the whole "
              "images (no closer look) this often (s, capture time), so that someone walking in waits this long for "
              "it, not detect_every_s", 0.0, 60.0),
        Param("count_every_s", 2.0, "several people: while max_people are tracked, the detector counts the people left "
              "out this often (s, capture time; /diagnostics says how many; 0: never)", 0.0, 600.0),
    ],
    "vmocap_markers": [
        Param("sync_tolerance_ms", 1.0, "max stamp difference of PCM views of one frame set", 0.0, 1000.0),
        Param("min_cameras", 2, "fewest views a frame set needs", 1, 64),
        Param("silent_after_ms", 500.0, "a view without heatmaps this long is reported silent", 1.0, 1e6),
        Param("feedback_timeout_ms", 200.0, "wait this long for the previous frame's skeleton (0: never wait)", 0.0, 1e5),
        Param("views", [""], "PCM view names (topics NS/pcm/VIEW/...); empty: one per camera, named as it"),
        Param("queue_depth", 3, "subscription depth per PCM topic and frame sets queued while the "
              "lattice search waits for feedback (beyond it the oldest are dropped and counted)", 1, 1000),
        Param("init_warn_s", 2.0, "diagnostics turn WARN, naming the views that disagree and the cameras without "
              "a person, when no subject is initialized for this long (capture time)", 0.0, 1e6),
    ],
    "vmocap_skeleton": [
        Param("queue_depth", 3, "subscription depth of the markers topic (live: freshness over completeness; "
              "raise it to process every frame of a bag played faster than the pipeline)", 1, 1000),
        Param("init_warn_s", 2.0, "diagnostics turn WARN, saying why, when no subject is initialized for this long "
              "(capture time)", 0.0, 1e6),
        Param("hri", True, "publish the subject (several people: every person) the ROS4HRI way (REP-155): "
              "/humans/bodies/tracked, /humans/bodies/<id>/{joint_states,urdf}, TF body_<id>; several people also "
              "NS/bodies/<id>/keypoints (needs hri_msgs: bash scripts/build_ros_msgs.sh)"),
        Param("remember_s", 60.0, "several people: an ended person's identified skeleton is kept this long (s): a "
              "newcomer with its link lengths is tracked at once, without a new identification phase (0: forget at "
              "once)", 0.0, 86400.0),
        Param("confirm_frames", 3, "several people: a person's track (new, or found again) is published once this "
              "many frame sets agreed with its skeleton (check_confirm_frames if larger)", 0, 600),
        Param("contested_m", 0.1, "several people: a lattice marker this close (m) to another person's is one body "
              "part both searches found, and neither person's IK uses it in that frame set (0: off)", 0.0, 1.0),
    ],
    "vmocap_recorder": [
        Param("output", "", "MCAP file to write (renamed from .partial when closed)", path=True),
        Param("topics", [""], "topics to record; empty: the graph outputs"),
        Param("overwrite", False, "replace an existing output file (without it the recorder refuses to start)"),
        Param("compression", "none", "MCAP chunk compression", choices=("none", "zstd", "lz4")),
        Param("chunk_kb", 256, "MCAP chunk size (KiB): a killed recorder loses at most the chunk being filled "
              "(the graph's outputs fill 256 KiB in about a second; images much faster)", 16, 65536),
    ],
}
# groups: nodes that share a process in `processes` mode (their messages stay in-process, e.g. a
# camera's images and the PCM inference); nodes in no group get a process each
LAUNCH_KEYS: dict[str, Any] = {"mode": "processes", "nodes": None, "groups": None, "env": {}, "fastdds_profile": "fastdds_shm.xml",
                               "restart": [], "restart_limit": 3}


def stage_params(node_type_name: str) -> list[Param]:
    """The method's tunables of a node (vmocap_core.method.config): the dataclass fields of its
    stage, flat in the node's section; `fps` is shared ('/**')."""
    from .method.config import MarkersConfig, SkeletonConfig

    cls = {"vmocap_markers": MarkersConfig, "vmocap_skeleton": SkeletonConfig}.get(node_type_name)
    if cls is None:
        return []
    out = []
    for f in dataclasses.fields(cls):
        if f.name == "fps":
            continue
        out.append(Param(f.name, f.default, f"{cls.__name__}.{f.name} (vmocap_core/method/config.py)"))
    return out


def stage_sections(flat: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Flat method tunables (as PipelineConfig.from_dict takes them) split into the config
    sections that declare them: `fps` to '/**', the rest to vmocap_markers / vmocap_skeleton.
    For code that writes a graph config."""
    from .method.config import MarkersConfig, PipelineConfig

    PipelineConfig.from_dict(flat)  # unknown keys fail here, named
    out: dict[str, dict[str, Any]] = {"/**": {}, "vmocap_markers": {}, "vmocap_skeleton": {}}
    for k, v in flat.items():
        section = "/**" if k == "fps" else "vmocap_markers" if k in MarkersConfig.names() else "vmocap_skeleton"
        out[section][k] = v
    return out


def node_type(name: str) -> str:
    """The node type of a node name: the type itself, or an instance of it named TYPE_SUFFIX
    (e.g. `vmocap_pcm_cam0`, a PCM worker for one camera, configured by a section of its own
    on top of the type's section)."""
    if name in NODE_PARAMS:
        return name
    for t in sorted(NODE_PARAMS, key=len, reverse=True):
        if name.startswith(t + "_") and name[len(t) + 1:].replace("_", "").isalnum():
            return t
    hint = (" (several people now run in vmocap_pcm, vmocap_markers and vmocap_skeleton, with max_people under /**: "
            "config/people.yaml)") if name == "vmocap_people" else ""
    raise KeyError(f"unknown node {name!r}; nodes: {sorted(NODE_PARAMS)} or their instances TYPE_NAME{hint}")


def params_of(node: str) -> list[Param]:
    t = node_type(node)
    return COMMON + NODE_PARAMS[t] + stage_params(t)


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _check(path: Path, p: Param, value: Any) -> Any:
    d = p.default
    if isinstance(d, bool):
        if not isinstance(value, bool):
            raise GraphConfigError(path, p.name, f"expected true/false, got {value!r}")
    elif isinstance(d, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise GraphConfigError(path, p.name, f"expected an integer, got {value!r}")
    elif isinstance(d, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise GraphConfigError(path, p.name, f"expected a number, got {value!r}")
        value = float(value)
    elif isinstance(d, str):
        if not isinstance(value, str):
            raise GraphConfigError(path, p.name, f"expected a string, got {value!r}")
    elif isinstance(d, list):
        if not isinstance(value, list):
            raise GraphConfigError(path, p.name, f"expected a list, got {value!r}")
    if p.lo is not None and not (p.lo <= value <= p.hi):  # type: ignore[operator]
        raise GraphConfigError(path, p.name, f"{value} is outside [{p.lo}, {p.hi}]")
    if p.choices is not None and value not in p.choices:
        raise GraphConfigError(path, p.name, f"{value!r} is not one of {list(p.choices)}")
    # "auto": a relative value is a path only when it names something next to the config
    looks_like_file = p.path != "auto" or (isinstance(value, str) and bool(value) and (path.parent / value).exists())
    if p.path and looks_like_file and isinstance(value, str) and value and not Path(value).is_absolute():
        value = str((path.parent / value).resolve())
    return value


@dataclass
class GraphConfig:
    path: Path
    raw: dict[str, Any]
    launch: dict[str, Any] = field(default_factory=dict)

    def node_names(self) -> list[str]:
        nodes = self.launch.get("nodes")
        if nodes is None:
            return [n for n in NODE_PARAMS if n in self.raw]
        return list(nodes)

    def process_groups(self, nodes: list[str] | None = None) -> list[list[str]]:
        """The processes of `processes` mode: the configured groups (restricted to `nodes`),
        then one process per remaining node."""
        nodes = self.node_names() if nodes is None else nodes
        out = [[n for n in g if n in nodes] for g in (self.launch.get("groups") or [])]
        out = [g for g in out if g]
        grouped = {n for g in out for n in g}
        return out + [[n] for n in nodes if n not in grouped]

    def node_params(self, node: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        """Validated parameters of `node`: defaults < '/**' < the node's section < overrides."""
        spec = {p.name: p for p in params_of(node)}
        values = {n: p.default for n, p in spec.items()}
        given: dict[str, Any] = {}
        for section in dict.fromkeys(("/**", node_type(node), node)):
            given.update(_flatten(((self.raw.get(section) or {}).get("ros__parameters")) or {}))
        given.update(overrides or {})
        for key, value in given.items():
            if key not in spec:
                raise GraphConfigError(self.path, f"{node}.{key}", f"unknown parameter (known: {sorted(spec)})")
            try:
                values[key] = _check(self.path, spec[key], value)
            except GraphConfigError as exc:  # name the section too
                raise GraphConfigError(self.path, f"{node}.{key}", exc.problem) from None
        # ROS has no empty string arrays: [""] stands for "empty"
        for n, v in values.items():
            if isinstance(v, list) and v == [""]:
                values[n] = []
        if values["lockstep"] and values.get("restamp"):
            raise GraphConfigError(self.path, f"{node}.lockstep", "lockstep replays the recorded stamps: not with restamp")
        if values["lockstep"]:  # every frame set waits for its predecessor's feedback (cameras/lockstep.py)
            for key in ("feedback_wait_ms", "feedback_timeout_ms"):
                if key in values:
                    values[key] = max(values[key], values["lockstep_timeout_ms"])
        return values

    def stage_config(self, node: str, params: dict[str, Any] | None = None) -> Any:
        """The method's config of a marker or skeleton node (MarkersConfig / SkeletonConfig),
        from its resolved `params` (default: node_params(node))."""
        from .method.config import MarkersConfig, SkeletonConfig

        p = self.node_params(node) if params is None else params
        cls = MarkersConfig if node_type(node) == "vmocap_markers" else SkeletonConfig
        try:
            return cls.from_dict({k: p[k] for k in cls.names()})
        except ValueError as exc:
            raise GraphConfigError(self.path, node, str(exc)) from None

    def skeleton_config(self, node: str = "vmocap_skeleton", params: dict[str, Any] | None = None) -> Any:
        """stage_config of a skeleton node, its `landmarks: auto` resolved by this graph's PCM
        source (vmocap_pcm: the CNN's landmarks, or joint centres for synthetic heatmaps and
        PCM bags)."""
        from .method.landmarks import CNN_LANDMARKS, resolve

        cfg = self.stage_config(node, params)
        pcm = self.node_params("vmocap_pcm")
        cnn = pcm["source"] == "model" and not str(pcm["model"]).endswith(".mcap")
        return cfg.replace(landmarks=resolve(cfg.landmarks, CNN_LANDMARKS if cnn else "none"))

    def pipeline_config(self) -> Any:
        """Both stages' configs (method.config.PipelineConfig): what `vmocap process`, the
        demo and the nodes build their stages from."""
        from .method.config import PipelineConfig

        return PipelineConfig(self.stage_config("vmocap_markers"), self.stage_config("vmocap_skeleton"))

    def load_rig(self) -> Any:
        """The rig the config names (restricted to its `cameras`)."""
        from .cameras.rig_file import load_rig

        p = self.node_params("vmocap_markers")
        if not p["rig"]:
            raise GraphConfigError(self.path, "rig", "no rig given")
        rig = load_rig(p["rig"])
        return rig.subset(p["cameras"]) if p["cameras"] else rig


def load(path: str | Path) -> GraphConfig:
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise GraphConfigError(path, "-", f"cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        raise GraphConfigError(path, "-", f"invalid YAML ({exc})") from None
    if not isinstance(raw, dict):
        raise GraphConfigError(path, "-", "top level must be a mapping")
    launch = dict(LAUNCH_KEYS)
    for key, value in (raw.get("vmocap_launch") or {}).items():
        if key not in LAUNCH_KEYS:
            raise GraphConfigError(path, f"vmocap_launch.{key}", f"unknown (known: {sorted(LAUNCH_KEYS)})")
        launch[key] = value
    if launch["mode"] not in ("processes", "single_process"):
        raise GraphConfigError(path, "vmocap_launch.mode", "must be processes or single_process")
    for section in raw:
        if section in ("/**", "vmocap_launch"):
            continue
        try:
            node_type(section)
        except KeyError as exc:
            raise GraphConfigError(path, section, f"unknown section: {exc.args[0]}") from None
    cfg = GraphConfig(path=path, raw=raw, launch=launch)
    for node in cfg.node_names():
        try:
            node_type(node)
        except KeyError as exc:
            raise GraphConfigError(path, "vmocap_launch.nodes", str(exc.args[0])) from None
    groups = launch.get("groups") or []
    if not isinstance(groups, list) or not all(isinstance(g, list) and g for g in groups):
        raise GraphConfigError(path, "vmocap_launch.groups", "must be a list of node lists (one per process)")
    for node in (n for g in groups for n in g):
        try:
            node_type(node)
        except KeyError as exc:
            raise GraphConfigError(path, "vmocap_launch.groups", str(exc.args[0])) from None
    restart = launch.get("restart") or []
    if not isinstance(restart, list) or not all(isinstance(n, str) for n in restart):
        raise GraphConfigError(path, "vmocap_launch.restart", "must be a list of node names (or [all])")
    for node in restart:
        if node != "all":
            try:
                node_type(node)
            except KeyError as exc:
                raise GraphConfigError(path, "vmocap_launch.restart", str(exc.args[0])) from None
    limit = launch.get("restart_limit")
    if not isinstance(limit, int) or isinstance(limit, bool) or limit < 0:
        raise GraphConfigError(path, "vmocap_launch.restart_limit", "must be an integer >= 0")
    for node in set(cfg.node_names()) | {s for s in raw if s not in ("/**", "vmocap_launch")}:
        cfg.node_params(node)  # validate early: a bad file fails before anything starts
        if node_type(node) in ("vmocap_markers", "vmocap_skeleton"):
            cfg.stage_config(node)
    return cfg
