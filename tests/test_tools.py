"""The scripts in ``tools/`` run: each GPU-check step that can run on a CPU does, on a tiny scene.

The GPU check is run where a GPU is lent, rarely and on a short lease; a call into the package that
changed since (a renamed function, a new keyword) must fail here, not there.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from adnerf.model.train import TrainConfig, train
from adnerf.synth import SynthConfig, synthesize

ROOT = Path(__file__).resolve().parents[1]


def test_gpu_check_steps_run_on_the_cpu(tmp_path: Path) -> None:
    work = tmp_path / "work"
    data = synthesize(work / "demo" / "data", SynthConfig(seconds=1.2, size=16, voice="formant", seed=4))
    train(data, work / "demo" / "run", config=TrainConfig(head_iters=4, torso_iters=2, rays=32), progress=False)
    out = tmp_path / "gpu.json"
    cmd = [sys.executable, str(ROOT / "tools" / "gpu_check.py"), "--device", "cpu", "--work", str(work), "--out", str(out),
           "--skip", "tests,demo,bench_render,fields", "--render-size", "16", "--steps-counts", "1,1", "--steps-rays", "32,64", "--real", str(data), "--real-iters", "2,1"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    doc = json.loads(out.read_text())
    assert doc["device"] == "cpu" and {"render", "stream", "steps", "real"} <= doc.keys()
    for step in ("render", "stream", "steps", "real"):
        assert "error" not in doc[step], (step, doc[step])
    stream = {row["mode"]: row for row in doc["stream"]["rows"]}
    assert set(stream) == {"offline look-ahead", "causal"} and stream["causal"]["causal"] and not stream["offline look-ahead"]["causal"]
    assert stream["causal"]["lookahead_s"] < stream["offline look-ahead"]["lookahead_s"] and all(r["frames"] == 30 and r["frames_per_s"] > 0 for r in stream.values())
    assert doc["render"]["head_torso_chunk262144_fps"] > 0 and doc["render"]["head_chunk262144_fps"] > 0
    assert [(row["rays"], row["frames"], row["adam"]) for row in doc["steps"]["rows"]] == [(32, 1, "trainer"), (64, 1, "trainer"), (64, 2, "trainer"), (32, 1, "foreach")]
    real = doc["real"]["run"]
    assert real["schedule"] == {"rays": 1024, "frames": 1, "head_iters": 2, "torso_iters": 1} and real["frames"] > 0 and real["psnr"] > 0
