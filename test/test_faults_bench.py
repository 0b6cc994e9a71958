"""`vmocap bench faults --json` on a subset of its faults (damaged bags through `vmocap process`
and `vmocap play`, the person leaving every view and returning through the node graph): the
JSON has the documented shape and every fault tried is survived and diagnosed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from graph_helpers import REPO, domain_env

FAULTS = ["truncated_bag", "corrupted_bag", "person_leaves"]


def test_bench_faults_subset_survived_and_diagnosed(tmp_path: Path) -> None:
    env = domain_env(41)
    run = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "bench", "faults", "--json", "--modes", "default",
                          "--only", *FAULTS, "--workdir", str(tmp_path)], env=env, cwd=REPO,
                         capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    names = set(out["faults"])
    assert names == {"truncated_bag:process", "truncated_bag:play", "corrupted_bag:process", "corrupted_bag:play",
                     "person_leaves:default"}, names
    assert out["tried"] == len(names)
    assert out["survived"] == sum(r["survived"] for r in out["faults"].values())
    for name, r in out["faults"].items():
        assert isinstance(r["survived"], bool) and isinstance(r["diagnosed"], bool) and isinstance(r["frames_lost"], int)
        assert r["survived"] and r["diagnosed"], (name, r)
    # damage at 60 % of the file: the frame sets before it are read, those after it lost
    for name in ("truncated_bag:process", "corrupted_bag:play"):
        assert 0 < out["faults"][name]["frames_lost"] < 150, out["faults"][name]
    person = out["faults"]["person_leaves:default"]
    assert person["tracked_after_return"] > 0 and person["output_while_absent"] < 10, person
