"""The graph config: declared parameters only, types and ranges checked, paths resolved."""

from pathlib import Path

import pytest
import yaml

from vmocap_core import graph_config
from vmocap_core.graph_config import GraphConfigError

REPO = Path(__file__).resolve().parent.parent


def _cfg(tmp_path: Path, patch: dict) -> Path:
    cfg = yaml.safe_load((REPO / "config" / "graph.yaml").read_text())
    for section, params in patch.items():
        cfg.setdefault(section, {"ros__parameters": {}})["ros__parameters"].update(params)
    p = tmp_path / "g.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_shipped_config_is_valid_and_complete():
    cfg = graph_config.load(REPO / "config" / "graph.yaml")
    p = cfg.node_params("vmocap_markers")
    assert Path(p["rig"]).is_file() and p["cameras"] == [] and len(p["pcm_keypoints"]) == 14
    assert p["fps"] == 30.0 and p["lattice_k"] == 5 and "filter_kind" not in p
    for node in graph_config.NODE_PARAMS:
        cfg.node_params(node)
        for prm in graph_config.params_of(node):
            assert prm.description


def test_unknown_parameter_is_rejected(tmp_path):
    with pytest.raises(GraphConfigError, match=r"vmocap_markers\.lattice_kk.*unknown"):
        graph_config.load(_cfg(tmp_path, {"vmocap_markers": {"lattice_kk": 3}}))
    with pytest.raises(GraphConfigError, match="unknown section"):
        graph_config.load(_cfg(tmp_path, {"vmocap_nonsense": {"x": 1}}))
    with pytest.raises(GraphConfigError, match=r"vmocap_skeleton\.nope.*unknown"):
        graph_config.load(_cfg(tmp_path, {"vmocap_skeleton": {"nope": 1}}))
    # one stage per section: a marker-stage key in the skeleton's section is an error, named
    with pytest.raises(GraphConfigError, match=r"vmocap_skeleton\.lattice_k.*unknown"):
        graph_config.load(_cfg(tmp_path, {"vmocap_skeleton": {"lattice_k": 3}}))
    # the old nested `tracker:` block is not silently ignored
    with pytest.raises(GraphConfigError, match=r"tracker\.fps.*unknown"):
        graph_config.load(_cfg(tmp_path, {"vmocap_markers": {"tracker": {"fps": 30.0}}}))


def test_each_stage_reads_its_own_section(tmp_path):
    from vmocap_core.method.config import PipelineConfig

    cfg = graph_config.load(_cfg(tmp_path, {"/**": {"fps": 50.0}, "vmocap_markers": {"lattice_k": 3},
                                            "vmocap_skeleton": {"filter_kind": "butterworth", "ik_iterations": 5}}))
    pc = cfg.pipeline_config()
    assert isinstance(pc, PipelineConfig)
    assert (pc.markers.lattice_k, pc.skeleton.fps, pc.skeleton.filter_kind, pc.skeleton.ik_iterations) == (3, 50.0, "butterworth", 5)
    # a value the stage's own checks reject names the file and the section
    bad = _cfg(tmp_path, {"vmocap_skeleton": {"filter_cutoff_hz": 40.0}})
    with pytest.raises(GraphConfigError, match="vmocap_skeleton.*half the frame rate") as exc:
        graph_config.load(bad)
    assert str(bad) in str(exc.value)
    # what a config writer uses: flat tunables to their sections
    sections = graph_config.stage_sections({"fps": 60.0, "lattice_k": 4, "identify_seconds": 0.0})
    assert sections == {"/**": {"fps": 60.0}, "vmocap_markers": {"lattice_k": 4}, "vmocap_skeleton": {"identify_seconds": 0.0}}


def test_types_and_ranges_are_checked(tmp_path):
    with pytest.raises(GraphConfigError, match="outside"):
        graph_config.load(_cfg(tmp_path, {"vmocap_markers": {"min_cameras": 0}}))
    with pytest.raises(GraphConfigError, match="expected a number"):
        graph_config.load(_cfg(tmp_path, {"vmocap_markers": {"sync_tolerance_ms": "fast"}}))
    with pytest.raises(GraphConfigError, match="not one of"):
        graph_config.load(_cfg(tmp_path, {"vmocap_pcm": {"source": "magic"}}))
    cfg = graph_config.load(_cfg(tmp_path, {"vmocap_markers": {"sync_tolerance_ms": 2}}))
    assert cfg.node_params("vmocap_markers")["sync_tolerance_ms"] == 2.0
    # overrides (vmocap launch --set) are validated the same way
    with pytest.raises(GraphConfigError):
        cfg.node_params("vmocap_recorder", {"compression": "rar"})


def test_live_config_and_config_check_command(tmp_path):
    import subprocess
    import sys

    cfg = graph_config.load(REPO / "config" / "live.yaml")
    assert cfg.process_groups() == [["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton"], ["vmocap_recorder"]]
    assert cfg.node_params("vmocap_pcm")["model"] == "blazepose"
    # the template names a rig the user writes (`vmocap calibrate --out`): checked, it is missing
    tpl = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "config", "check", str(REPO / "config" / "live.yaml")],
                         capture_output=True, text=True, timeout=60)
    assert tpl.returncode == 2 and "my_rig.yaml: no such rig file" in tpl.stderr, tpl.stderr
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm.synthetic import benchmark_rig

    save_rig(benchmark_rig(), tmp_path / "my_rig.yaml")
    live = tmp_path / "live.yaml"
    live.write_text((REPO / "config" / "live.yaml").read_text())
    ok = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "config", "check", str(live)],
                        capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "vmocap_camera + vmocap_pcm" in ok.stdout and "threads: 2" in ok.stdout, ok.stderr
    bad = _cfg(tmp_path, {"vmocap_pcm_cam0": {"cameras": ["cam0"], "threads": "two"}})
    out = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "config", "check", str(bad)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "vmocap_pcm_cam0" in out.stderr and "threads" in out.stderr and str(bad) in out.stderr


def test_skeleton_landmarks_follow_the_graphs_pcm_source(tmp_path):
    """`landmarks: auto` is the CNN's landmark model when vmocap_pcm runs the CNN, joint
    centres for synthetic heatmaps and PCM bags; a value given stays."""
    def landmarks(patch):
        return graph_config.load(_cfg(tmp_path, patch)).skeleton_config().landmarks

    assert landmarks({}) == "none"  # the shipped graph.yaml: synthetic heatmaps
    assert landmarks({"vmocap_pcm": {"source": "model", "model": "blazepose"}}) == "blazepose"
    assert landmarks({"vmocap_pcm": {"source": "model", "model": "pcm.mcap"}}) == "none"
    assert landmarks({"vmocap_pcm": {"source": "model", "model": "blazepose"},
                      "vmocap_skeleton": {"landmarks": "none"}}) == "none"
    assert graph_config.load(REPO / "config" / "live.yaml").skeleton_config().landmarks == "blazepose"


def test_people_config_checks(tmp_path):
    """config/people.yaml: the stage nodes in the camera's process, max_people and end_after_s
    shared, each node's people settings in its section."""
    import subprocess
    import sys

    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm.synthetic import benchmark_rig

    save_rig(benchmark_rig(), tmp_path / "my_rig.yaml")
    people = tmp_path / "people.yaml"
    people.write_text((REPO / "config" / "people.yaml").read_text())
    cfg = graph_config.load(people)
    assert cfg.process_groups() == [["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton"], ["vmocap_recorder"]]
    assert all(cfg.node_params(n)["max_people"] == 2 for n in ("vmocap_pcm", "vmocap_markers", "vmocap_skeleton"))
    assert cfg.node_params("vmocap_pcm")["detect_every_s"] == 0.5 and cfg.node_params("vmocap_skeleton")["remember_s"] == 60.0
    assert cfg.pipeline_config().markers.lattice_k == 5
    ok = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "config", "check", str(people)],
                        capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
