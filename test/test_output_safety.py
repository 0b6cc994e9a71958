"""No command loses a user's data: outputs never written onto an input (same path, symlink,
hard link), no existing file replaced without --overwrite, no half-written file after a crash,
damaged MCAP chunks refused with the chunk named (--recover reads the others), and config
values that cannot work with the rig refused before any node starts."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from graph_helpers import synthetic_bag, write_config

from vmocap_core.bag import BagReader
from vmocap_core.errors import ChunkCrcError, OutputPathError
from vmocap_core.files import staged, write_text

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.run([sys.executable, "-m", "vmocap_core.cli", *args], capture_output=True, text=True,
                          timeout=300, env=env)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("safety")
    rig, rig_path, kps = synthetic_bag(d / "in.mcap", frames=40)
    cfg = write_config(d / "g.yaml", rig_path, kps, ["vmocap_markers"])
    out = d / "out.mcap"
    p = _cli("process", str(d / "in.mcap"), "-o", str(out), "--config", str(cfg), "--no-progress")
    assert p.returncode == 0, p.stderr
    return {"d": d, "in": d / "in.mcap", "cfg": cfg, "out": out, "rig": rig_path}


def _refused(p: subprocess.CompletedProcess, *words: str) -> None:
    assert p.returncode == 2, p.stdout + p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and all(w in lines[0] for w in words), p.stderr


def test_process_refuses_its_input_by_path_symlink_and_hard_link(work) -> None:
    d, src = work["d"], work["in"]
    before = src.read_bytes()
    link, hard = d / "link.mcap", d / "hard.mcap"
    link.symlink_to(src)
    os.link(src, hard)
    for target in (src, link, hard):  # --overwrite does not make an input writable
        _refused(_cli("process", str(src), "-o", str(target), "--config", str(work["cfg"]), "--overwrite",
                      "--no-progress"), "refusing to write onto it")
    assert src.read_bytes() == before and link.is_symlink()


def test_existing_outputs_need_overwrite(work) -> None:
    d, out = work["d"], work["out"]
    before = out.read_bytes()
    _refused(_cli("process", str(work["in"]), "-o", str(out), "--config", str(work["cfg"]), "--no-progress"),
             str(out), "--overwrite")
    assert out.read_bytes() == before
    csv = d / "s.csv"
    csv.write_text("mine\n")
    _refused(_cli("export", str(out), "--format", "csv", "-o", str(csv)), "exists")
    assert csv.read_text() == "mine\n"
    _refused(_cli("export", str(out), "--format", "csv", "-o", str(out)), "refusing to write onto it")
    assert _cli("export", str(out), "--format", "csv", "-o", str(csv), "--overwrite").returncode == 0
    assert csv.read_text() != "mine\n"
    urdf = d / "s.urdf"
    urdf.write_text("mine")
    _refused(_cli("urdf", "-o", str(urdf)), "exists")
    assert urdf.read_text() == "mine"
    # nothing half-written or staged is left next to the outputs
    assert not [p for p in d.iterdir() if p.name.startswith(".vmocap-") or p.name.endswith(".partial")]


def test_crash_mid_write_leaves_the_old_file(tmp_path: Path) -> None:
    out = tmp_path / "r.txt"
    out.write_text("old")
    with pytest.raises(RuntimeError):
        with staged(out, overwrite=True) as tmp:
            tmp.write_text("half of the new")
            raise RuntimeError("crash")
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["r.txt"]
    with pytest.raises(OutputPathError, match="exists"):
        write_text(out, "new")
    # a symlinked output with overwrite: the link's target gets the new content, the link stays
    link = tmp_path / "l.txt"
    link.symlink_to(out)
    write_text(link, "new", overwrite=True)
    assert link.is_symlink() and out.read_text() == "new"


def _damage_chunk(src: Path, dst: Path) -> int:
    from vmocap_ros.bench.fault_harness import damage_chunk

    return damage_chunk(src, dst)[0]


def test_damaged_chunk_refused_by_process_export_and_play(work) -> None:
    d = work["d"]
    bad_in = d / "bad_in.mcap"
    k = _damage_chunk(work["in"], bad_in)
    with pytest.raises(ChunkCrcError, match=rf"chunk {k} of \d+ \(byte offset \d+"):
        list(BagReader(bad_in).open().messages())
    p = _cli("process", str(bad_in), "-o", str(d / "x.mcap"), "--config", str(work["cfg"]), "--no-progress")
    _refused(p, str(bad_in), f"chunk {k} of", "--recover")
    assert not (d / "x.mcap").exists() and not (d / "x.mcap.partial").exists()
    with BagReader(bad_in, recover=True) as r:  # the intact chunks, before and after the damaged one
        got = list(r.messages())
        assert len(r.damaged_chunks) == 1 and 0 < len(got) < sum(r.message_counts.values())
    bad_out = d / "bad_out.mcap"
    k = _damage_chunk(work["out"], bad_out)
    _refused(_cli("export", str(bad_out), "--format", "csv", "-o", str(d / "b.csv")), f"chunk {k} of", "--recover")
    assert not (d / "b.csv").exists()
    # (the processed bag's keypoints may all sit in the damaged chunk: then nothing is left to export)
    rec = _cli("export", str(bad_out), "--format", "csv", "-o", str(d / "b.csv"), "--recover")
    assert "skipped (recover)" in rec.stderr and "read the intact chunks" not in rec.stderr.splitlines()[-1], rec.stderr
    pytest.importorskip("rclpy")
    play = subprocess.run([str(REPO / ".venv" / "bin" / "vmocap"), "play", str(bad_in), "--rate", "0"],
                          capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert play.returncode != 0 and "is damaged" in play.stderr and "--recover" in play.stderr, play.stderr[-2000:]


def _config(tmp_path: Path, rig: Path, **sections: dict) -> Path:
    raw = {"/**": {"ros__parameters": {"rig": str(rig)}}}
    for name, params in sections.items():
        raw.setdefault(name, {"ros__parameters": {}})["ros__parameters"].update(params)
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("sections, words", [
    ({"vmocap_markers": {"min_cameras": 5}}, ["vmocap_markers.min_cameras", "more than the 4"]),
    ({"vmocap_pcm": {"min_cameras": 5}}, ["vmocap_pcm.min_cameras"]),  # a worker for some cameras (`cameras`) may have fewer
    ({"vmocap_markers": {"cameras": ["cam0", "cam9"]}}, ["cameras", "cam9", "not in the rig"]),
    ({"vmocap_markers": {"views": ["cam0", "cam1_1", "side"]}}, ["views", "side"]),
    ({"vmocap_camera": {"source": "bag", "uri": "missing.mcap"}}, ["vmocap_camera.uri", "missing.mcap: no such"]),
    ({"vmocap_camera": {"source": "video", "uri": "cam7=a.mp4"}}, ["vmocap_camera.uri", "cam7"]),
    ({"vmocap_markers": {"fps": 0.0}}, ["fps", "outside"]),
    ({"vmocap_recorder": {"output": "EXISTING"}}, ["vmocap_recorder.output", "exists", "--overwrite"]),
    ({"vmocap_pcm": {}, "vmocap_markers": {"max_people": 2}, "vmocap_skeleton": {}}, ["max_people", "disagree", "/**"]),
    ({"/**": {"max_people": 2}, "vmocap_pcm": {}}, ["vmocap_pcm.model", "blazepose"]),  # several people: found by BlazePose's detector
    ({"vmocap_people": {}}, ["vmocap_people", "max_people", "config/people.yaml"]),  # the node of earlier versions
])
def test_config_values_that_cannot_work_are_refused(work, tmp_path: Path, sections: dict, words: list[str]) -> None:
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"recording")
    sections = yaml.safe_load(yaml.safe_dump(sections).replace("EXISTING", str(existing)))
    cfg = _config(tmp_path, work["rig"], **sections)
    _refused(_cli("config", "check", str(cfg)), *words)
    _refused(_cli("launch", str(cfg), "--single-process"), *words)
    assert existing.read_bytes() == b"recording"


def test_config_rig_that_does_not_exist(tmp_path: Path) -> None:
    cfg = _config(tmp_path, tmp_path / "nope.yaml", vmocap_markers={})
    _refused(_cli("config", "check", str(cfg)), "nope.yaml: no such rig file")


def test_plots_replace_their_own_files_but_never_an_input(work, tmp_path: Path) -> None:
    """`vmocap process --plots DIR`: its plot files are replaced on a rerun; a plot file that is an
    input (here a link to the config) or a DIR that is a file is refused before the work."""
    plots = tmp_path / "plots"
    out = tmp_path / "o.mcap"
    base = ("process", str(work["in"]), "-o", str(out), "--config", str(work["cfg"]), "--no-progress", "--overwrite")
    for _ in range(2):
        assert _cli(*base, "--plots", str(plots)).returncode == 0
    assert sorted(p.name for p in plots.iterdir()) == ["joint_angles.png", "keypoint_speeds.png"]
    cfg_before = work["cfg"].read_bytes()
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "joint_angles.png").symlink_to(work["cfg"])
    out.unlink()
    _refused(_cli(*base, "--plots", str(linked)), "joint_angles.png", "refusing to write onto it")
    not_a_folder = tmp_path / "f.png"
    not_a_folder.write_bytes(b"mine")
    _refused(_cli(*base, "--plots", str(not_a_folder)), "not a folder")
    assert work["cfg"].read_bytes() == cfg_before and not_a_folder.read_bytes() == b"mine" and not out.exists()


def test_figure_writer_keeps_inputs(tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vmocap_core.files import output_folder, write_figure

    src = tmp_path / "in.png"
    src.write_bytes(b"input")
    fig = plt.figure()
    try:
        folder = output_folder(tmp_path / "figs", ["a.png"], [src])
        write_figure(fig, folder / "a.png", [src])
        first = (folder / "a.png").read_bytes()
        write_figure(fig, folder / "a.png", [src])  # its own figure: replaced
        assert first.startswith(b"\x89PNG") and (folder / "a.png").read_bytes().startswith(b"\x89PNG")
        with pytest.raises(OutputPathError, match="refusing to write onto it"):
            write_figure(fig, src, [src])
        with pytest.raises(OutputPathError, match="refusing to write onto it"):
            output_folder(tmp_path, ["in.png"], [src])
    finally:
        plt.close(fig)
    assert src.read_bytes() == b"input"


def test_demo_refuses_an_earlier_run_without_overwrite(tmp_path: Path) -> None:
    """`vmocap demo --out DIR` over an earlier run's files: refused without --overwrite (make demo
    passes it), and a --bag among its outputs refused even with it; both before any work."""
    out = tmp_path / "demo"
    out.mkdir()
    (out / "report.md").write_text("earlier run")
    _refused(_cli("demo", "--out", str(out), "--bag", str(tmp_path / "b.mcap")), "report.md", "exists", "--overwrite")
    (out / "outputs.mcap").write_bytes(b"a bag")
    _refused(_cli("demo", "--out", str(out), "--bag", str(out / "outputs.mcap"), "--mode", "in-process", "--overwrite"),
             "outputs.mcap", "refusing to write onto it")
    assert (out / "report.md").read_text() == "earlier run" and (out / "outputs.mcap").read_bytes() == b"a bag"
    assert sorted(p.name for p in out.iterdir()) == ["outputs.mcap", "report.md"] and not (tmp_path / "b.mcap").exists()
