"""The fast path: empty-space skipping in the model, the tri-plane encoding, and ``adnerf bench fields``."""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path

import pytest
import torch

from adnerf.bench.fields import (
    CONFIGS,
    _reference_times,
    bench_fields,
    bench_model_config,
    format_fields_table,
    load_rows,
    plot_fields,
)
from adnerf.cli import main
from adnerf.encodings import TriPlaneEncoding
from adnerf.model.conditions import FrameCondition
from adnerf.formats.dataset import load_dataset
from adnerf.model.talking_head import (
    TalkingHead,
    migrate_state_dict,
    mixed_precision,
    model_config,
    render_frame,
)
from adnerf.model.train import RunError, TrainConfig, load_model_state, train
from adnerf.pose import HeadPose, euler_rotation
from adnerf.samplers import PosedAABBBounds
from adnerf.synth import SynthConfig, synthesize

TINY = SynthConfig(seconds=1.6, size=32, voice="formant", seed=5)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("speed") / "data", TINY)


def _model(tiny: Path) -> tuple[TalkingHead, object]:
    ds = load_dataset(tiny, truth=False)
    torch.manual_seed(0)
    return TalkingHead(model_config(ds.meta, "fast")), ds


def _bilinear_reference(enc: TriPlaneEncoding, x: torch.Tensor) -> torch.Tensor:
    """Tri-plane features by explicit corner gathers (align_corners=True, border clamp)."""
    p = enc.normalize(x)
    coords = torch.stack([p[:, [0, 1]], p[:, [0, 2]], p[:, [1, 2]]], dim=1)  # (N, 3 planes, 2)
    feats = []
    for planes in enc.planes:
        R = planes.shape[-1]
        u = ((coords + 1) * 0.5 * (R - 1)).clamp(0, R - 1)
        i0 = u.floor().clamp(max=R - 2)
        f = u - i0
        i0 = i0.long()
        for k in range(3):
            table = planes[k]  # (C, R, R), indexed [c, y, x]
            x0, y0, fx, fy = i0[:, k, 0], i0[:, k, 1], f[:, k, 0:1], f[:, k, 1:2]
            v = (
                table[:, y0, x0].T * (1 - fx) * (1 - fy)
                + table[:, y0, x0 + 1].T * fx * (1 - fy)
                + table[:, y0 + 1, x0].T * (1 - fx) * fy
                + table[:, y0 + 1, x0 + 1].T * fx * fy
            )
            feats.append(v)
    return torch.cat(feats, dim=-1)


def test_triplane_matches_explicit_bilinear_reference() -> None:
    torch.manual_seed(0)
    enc = TriPlaneEncoding((-1.0, -2.0, 0.5), (1.0, 2.0, 3.0), n_levels=3, channels=4, base_resolution=8, max_resolution=32).double()
    x = torch.rand(500, 3, dtype=torch.float64) * torch.tensor([2.4, 4.8, 3.0]) - torch.tensor([1.2, 2.4, -0.2])  # some outside the box
    fast = enc(x)
    assert fast.shape == (500, enc.out_dim)
    torch.testing.assert_close(fast, _bilinear_reference(enc, x), rtol=0, atol=1e-12)
    # Batch shapes pass through, and the gradient reaches the planes.
    assert enc(x.reshape(20, 25, 3)).shape == (20, 25, enc.out_dim)
    fast.square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.planes)


def _set_head_density_bias(model: TalkingHead, bias: float) -> None:
    for field in (model.layers["head"].coarse, model.layers["head"].fine):
        with torch.no_grad():
            field.density_head.weight.zero_()
            field.density_head.bias.fill_(bias)


def test_empty_grid_skips_everything_and_full_grid_changes_nothing(tiny: Path) -> None:
    model, ds = _model(tiny)
    model.eval()
    head = model.layers["head"]
    cam = ds.meta.camera()
    pose = ds.head_pose(0)
    cond = FrameCondition(torch.randn(model.config.audio_dim), pose)
    plate = torch.rand(cam.height, cam.width, 3)
    assert head.occupied() is None  # not estimated yet: nothing is skipped
    rays = cam.rays().flatten()
    near, far = head.crossing(rays, pose)
    rays = rays[far > near]  # rays that cross the head box (zero-length samples are skipped anyway)

    _set_head_density_bias(model, 30.0)  # dense everywhere: every cell occupied
    reference = head.render(rays, cond)
    assert head.update_occupancy(cond) == 1.0
    skipped = head.render(rays, cond)
    assert torch.equal(skipped.final.rgb, reference.final.rgb) and skipped.samples_evaluated == reference.samples_evaluated

    _set_head_density_bias(model, -30.0)  # softplus(-30) ~ 1e-13 < threshold: every cell empty
    assert head.update_occupancy(cond, decay=0.0) == 0.0
    empty = head.render(rays, cond)
    assert empty.samples_evaluated == 0 and torch.equal(empty.final.opacity, torch.zeros_like(empty.final.opacity))
    frame = render_frame(model, cam, pose, cond.audio, plate, layers=("head",))
    assert torch.equal(frame.head_opacity, torch.zeros_like(frame.head_opacity))
    torch.testing.assert_close(frame.rgb, plate.clamp(0, 1))


def test_head_layer_lives_in_canonical_space_and_torso_in_camera_space(tiny: Path) -> None:
    """Rays are moved into the head's frame once: they cross its box where the posed box of the
    reference bounds says, with the same ``t``, and pass canonical points where the camera rays
    pass their posed images. The torso layer leaves rays as they are."""
    model, ds = _model(tiny)
    head, torso = model.layers["head"], model.layers["torso"]
    R = euler_rotation(0.3, -0.2, 0.1, like=torch.zeros((), dtype=torch.float64))
    pose = HeadPose(R, torch.tensor([0.1, -0.3, 6.0], dtype=torch.float64))
    rays = ds.meta.camera().rays().flatten()
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in model.config.head_aabb)
    ref_near, ref_far = PosedAABBBounds(lo, hi, pose.R, pose.t)(rays)
    near, far = head.crossing(rays, pose)
    hit = ref_far > ref_near
    assert hit.any() and torch.equal(far > near, hit)
    torch.testing.assert_close(near[hit], ref_near[hit], rtol=0, atol=1e-12)
    torch.testing.assert_close(far[hit], ref_far[hit], rtol=0, atol=1e-12)
    moved = head.to_space(rays, pose)
    t = near[hit][:, None]
    torch.testing.assert_close(moved.origins[hit] + t * moved.directions[hit], pose.to_canonical(rays.origins[hit] + t * rays.directions[hit]), rtol=0, atol=1e-12)
    assert torso.to_space(rays, pose) is rays
    with pytest.raises(ValueError, match="head pose"):
        head.to_space(rays, None)
    # The grids are looked up in each layer's space.
    grid = head.occupancy
    grid.density = torch.rand(grid.density.shape)  # some estimate
    grid.occupied = grid.density > 0.5
    assert torch.equal(head.occupied()(grid.cell_centers().reshape(-1, 3)), grid.occupied.reshape(-1))


def test_occupancy_is_a_union_over_frames_with_decay(tiny: Path) -> None:
    model, ds = _model(tiny)
    head = model.layers["head"]
    cond = FrameCondition(torch.zeros(model.config.audio_dim), ds.head_pose(0))
    _set_head_density_bias(model, 6.0)  # raw density 6 - 1 (the fast field's bias): softplus(5) = 5.0067
    head.update_occupancy(cond, dilation=0)
    _set_head_density_bias(model, -30.0)
    # The old estimate decays by 0.7 per update: 5.0067 * 0.7^17 = 0.0116 > 0.01 > 5.0067 * 0.7^18.
    fractions = [head.update_occupancy(cond, dilation=0) for _ in range(19)]
    assert fractions[:17] == [1.0] * 17 and fractions[-1] == 0.0


def test_training_skips_empty_space_and_counts_samples(tiny: Path, tmp_path: Path) -> None:
    cfg = TrainConfig(head_iters=40, torso_iters=0, rays=128, log_every=10, occupancy_start=0.25, occupancy_every=5)
    run = train(tiny, tmp_path / "run", config=cfg, progress=False)
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert all(r["samples_per_s"] > 0 for r in rows)
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    density = ckpt["model"]["layers.head.occupancy.density"]
    assert torch.isfinite(density).all()  # estimated during training
    off = train(tiny, tmp_path / "off", config=TrainConfig(**{**cfg.__dict__, "occupancy_start": 1.0}), progress=False)
    assert torch.isinf(torch.load(off / "checkpoint.pt", weights_only=False)["model"]["layers.head.occupancy.density"]).all()


def test_checkpoints_without_grids_load_and_wrong_weights_fail(tiny: Path) -> None:
    model, _ = _model(tiny)
    state = {k: v for k, v in model.state_dict().items() if ".occupancy." not in k}
    fresh, _ = _model(tiny)
    load_model_state(fresh, state, Path("old.pt"), smoothing=False)  # a run from before the grids: they stay unestimated
    assert not fresh.layers["head"].occupancy.estimated
    with pytest.raises(RunError, match="do not match"):
        load_model_state(fresh, {**state, "stray.weight": torch.zeros(1)}, Path("bad.pt"), smoothing=False)
    with pytest.raises(RunError, match="do not match"):
        load_model_state(fresh, {k: v for k, v in state.items() if not k.startswith("layers.head.")}, Path("bad.pt"), smoothing=False)


def test_checkpoints_of_the_earlier_layout_load_bit_for_bit(tiny: Path) -> None:
    """Runs trained before the layers (``head.field.*``, ``head_fine.field.*``, ``torso.*``,
    ``head_occupancy.*``) load into the layers' model with every tensor in its place."""
    model, _ = _model(tiny)
    model.layers["head"].occupancy.density.uniform_(0, 1)
    new = model.state_dict()
    back = {"layers.head.coarse.": "head.field.", "layers.head.fine.": "head_fine.field.", "layers.torso.coarse.": "torso.field.", "layers.torso.fine.": "torso_fine.field.", "layers.head.occupancy.": "head_occupancy.", "layers.torso.occupancy.": "torso_occupancy."}
    old = {}
    for key, value in new.items():
        prefix = next((p for p in back if key.startswith(p)), None)
        old[key if prefix is None else back[prefix] + key[len(prefix) :]] = value
    assert any(k.startswith("head_fine.field.") for k in old) and not any(k.startswith("layers.") for k in old)
    assert migrate_state_dict(new) == new
    fresh, _ = _model(tiny)
    with torch.no_grad():
        for p in fresh.parameters():
            p.add_(1.0)  # so that only loading can bring the weights back
    load_model_state(fresh, old, Path("old.pt"), smoothing=False)
    for key, value in fresh.state_dict().items():
        assert torch.equal(value, new[key]), key


def test_bench_model_configs(tiny: Path) -> None:
    meta = load_dataset(tiny, truth=False).meta
    by = {c.name: bench_model_config(meta, c) for c in CONFIGS}
    assert by["paper"].head.encoding == "pe" and by["paper"].head.width == 256 and by["paper"].head_samples == (64, 128)
    assert by["fast"].occupancy_resolution > 0 and by["fast-no-skip"].occupancy_resolution == 0
    assert by["fast-coarse-only"].head_samples == (32, 0) and by["fast-coarse-only"].head == by["fast"].head_fine


def test_reference_times() -> None:
    def row(name: str, psnrs: list[float]) -> dict:
        return {"config": name, "budget_s": 300.0, "psnr_final": psnrs[-1], "checkpoints": [{"seconds": t, "psnr": p} for t, p in zip((10.0, 30.0, 300.0), psnrs)]}

    rows = [row("paper", [15.0, 18.0, 20.0]), row("fast", [19.0, 20.5, 30.0]), row("slow", [10.0, 11.0, 12.0])]
    _reference_times(rows, "paper")
    assert rows[1]["seconds_to_reference_psnr"] == 30.0 and rows[1]["speedup_vs_reference"] == 10.0
    assert rows[0]["seconds_to_reference_psnr"] == 300.0 and rows[2]["seconds_to_reference_psnr"] is None


def test_bench_fields_runs_and_plots(tiny: Path, tmp_path: Path) -> None:
    rows = bench_fields(tiny, configs=["fast", "fast-coarse-only"], budget=1.5, checkpoints=(0.5, 1.0), isolate=False, progress=False)
    assert [r["config"] for r in rows] == ["fast", "fast-coarse-only"]
    for r in rows:
        assert [c["seconds"] for c in r["checkpoints"]] == [0.5, 1.0, 1.5]
        its = [c["iterations"] for c in r["checkpoints"]]
        assert its == sorted(its) and its[-1] == r["iterations"] >= 3
        assert all(c["elapsed"] >= c["seconds"] or c["iterations"] == r["iterations"] for c in r["checkpoints"])
        assert all(5 < c["psnr"] < 60 for c in r["checkpoints"])
        assert r["train_samples_per_s"] > 0 and r["render_fps"] > 0 and r["peak_memory_mb"] > 0
    table = format_fields_table(rows)
    assert "fast-coarse-only" in table and "1.5 s" in table
    saved = tmp_path / "rows.jsonl"
    saved.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert load_rows(saved) == rows
    png = tmp_path / "plot.png"
    plot_fields(rows, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_fields_synthesises_its_scene_in_a_fresh_process(tmp_path: Path) -> None:
    small = SynthConfig(seconds=1.6, size=24, voice="formant", seed=2)
    (row,) = bench_fields(configs=["fast"], budget=0.5, checkpoints=(), synth_config=small, isolate=True, progress=False)
    assert row["size"] == 24 and [c["seconds"] for c in row["checkpoints"]] == [0.5]


def test_bench_fields_cli_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "fields", "--configs", "nope", "--budget", "1"]) == 2
    assert "unknown field configurations" in capsys.readouterr().err
    assert main(["bench", "fields", "--budget", "0"]) == 2


def test_bf16_autocast_runs_the_fields_in_bf16_and_composites_in_full_precision(tiny: Path, tmp_path: Path) -> None:
    model, ds = _model(tiny)
    model.eval()
    head = model.layers["head"]
    pose, code = ds.head_pose(0), torch.randn(model.config.audio_dim)
    cond = FrameCondition(code, pose)
    rays = ds.meta.camera().rays().flatten()
    near, far = head.crossing(rays, pose)
    rays = rays[far > near]
    with torch.no_grad():
        reference = head.render(rays, cond)
        with mixed_precision("cpu", "bf16"):
            raw = head.coarse(torch.zeros(8, 3), torch.zeros(8, 3), code)
            half = head.render(rays, cond)
    assert raw.density.dtype == torch.bfloat16  # the field really ran in bfloat16
    assert half.final.weights.dtype == reference.final.weights.dtype != torch.bfloat16
    assert torch.isfinite(half.final.rgb).all() and (half.final.rgb - reference.final.rgb).abs().max() < 0.05
    assert isinstance(mixed_precision("cpu", "auto"), contextlib.nullcontext)  # auto: off on CPU
    with pytest.raises(ValueError, match="amp must be one of"):
        mixed_precision("cpu", "fp8")
    run = train(tiny, tmp_path / "amp", config=TrainConfig(head_iters=6, torso_iters=3, rays=64, log_every=3, amp="bf16"), progress=False)
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert all(math.isfinite(r["loss"]) for r in rows) and {r["stage"] for r in rows} == {"head", "torso"}
