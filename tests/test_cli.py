"""The adnerf command line."""

from __future__ import annotations

import json
import subprocess
import sys

from adnerf.cli import main


def test_bench_render_json(capsys) -> None:
    assert main(["bench", "render", "--json", "--samples", "4,8", "--size", "8", "--repeats", "1"]) == 0
    captured = capsys.readouterr()
    rows = [json.loads(line) for line in captured.out.splitlines()]
    assert [(r["samples_per_ray"], r["method"]) for r in rows] == [(4, "stratified"), (4, "importance"), (8, "stratified"), (8, "importance")]
    assert all(r["seconds_per_mrays"] > 0 and r["opacity_rel_err"] >= 0 for r in rows)
    assert "opacity rel err" in captured.err  # the readable table goes to stderr


def test_bench_render_table(capsys) -> None:
    assert main(["bench", "render", "--samples", "4", "--size", "8", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "stratified" in out and "importance" in out and "s / Mray" in out


def test_bad_arguments_give_clear_errors() -> None:
    r = subprocess.run([sys.executable, "-m", "adnerf.cli", "bench", "render", "--samples", "4,x"], capture_output=True, text=True)
    assert r.returncode == 2 and "comma-separated integers" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "adnerf.cli", "bench", "render", "--device", "tpu"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown device" in r.stderr and "Traceback" not in r.stderr


def test_bench_features_json(capsys) -> None:
    assert main(["bench", "features", "--seconds", "2", "--repeats", "1", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["kind"] for r in rows] == ["logmel", "phonemes"]
    assert all(r["realtime_factor"] > 0 and r["audio_seconds"] == 2.0 for r in rows)


def test_demo_scale_trains_the_scaled_schedule(monkeypatch, tmp_path, capsys) -> None:
    from adnerf.commands import demo

    seen = []

    def fake_run_demo(out_dir, *, device, train_config, **_):
        seen.append(train_config)
        return dict.fromkeys(("psnr_test", "ssim_test", "psnr_mouth_test", "mouth_open_corr", "train_seconds", "render_fps", "total_seconds"), 0.0)

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    assert main(["demo", "-o", str(tmp_path / "d"), "--scale", "4"]) == 0
    assert main(["demo", "-o", str(tmp_path / "e")]) == 0
    scaled, plain = seen
    assert plain == demo.DEMO_TRAIN
    assert (scaled.rays, scaled.frames, scaled.head_iters, scaled.torso_iters) == (4 * plain.rays, 4 * plain.frames, plain.head_iters // 4, plain.torso_iters // 4)
