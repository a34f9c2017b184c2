"""The lip patch (``TrainConfig.lip_patch``): where its pixels lie and in which order, what its
loss scores, and that stage 1 draws it, renders it and adds its term to the step's loss."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from kornia.metrics import ssim

from adnerf.formats.dataset import MOUTH_CROP, load_dataset
from adnerf.model.lip_patch import MIN_PATCH, PATCH_REGION, SSIM_WINDOW, patch_loss, patch_pixels, patch_stride
from adnerf.model.talking_head import model_config
from adnerf.model.train import TrainConfig, Trainer
from adnerf.synth import SynthConfig, synthesize


def rows_cols(pix: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    return pix // width, pix % width


@pytest.mark.parametrize("seed", range(4))
def test_patch_pixels_are_a_strided_row_major_grid_in_the_mouth_region(seed: int) -> None:
    width, height, size, side = 200, 120, 8, 96.0  # not square: a swapped axis lands elsewhere
    stride = patch_stride(side, size)
    assert stride == 3  # a quarter of 96 px over 8 rays
    centre = (130.3, 70.8)
    g = torch.Generator().manual_seed(seed)
    pix = patch_pixels(centre, side, size, width, height, g)
    assert pix.shape == (size * size,) and pix.dtype == torch.int64
    r, c = rows_cols(pix.reshape(size, size), width)
    # Row-major: along a row the column grows by the stride, down a column the row does.
    assert torch.all(r[:, 1:] == r[:, :1]) and torch.all(torch.diff(c, dim=1) == stride)
    assert torch.all(c[1:, :] == c[:1, :]) and torch.all(torch.diff(r, dim=0) == stride)
    half = 0.5 * PATCH_REGION * side  # every pixel centre inside the central region
    assert torch.all((c + 0.5 - centre[0]).abs() <= half) and torch.all((r + 0.5 - centre[1]).abs() <= half)


def test_patch_pixels_move_over_the_region_and_stay_in_the_image() -> None:
    width, height, size, side = 64, 48, 8, 64.0
    g = torch.Generator().manual_seed(0)
    corners = {tuple(int(v) for v in rows_cols(patch_pixels((40.0, 24.0), side, size, width, height, g)[0], width)) for _ in range(50)}
    assert len(corners) > 10  # a random place, not one
    # A mouth off the image's corner: the patch is clipped into the image.
    pix = patch_pixels((-20.0, 60.0), side, size, width, height, g)
    r, c = rows_cols(pix, width)
    assert int(c.min()) == 0 and int(r.max()) == height - 1
    with pytest.raises(ValueError, match="spans"):
        patch_pixels((10.0, 10.0), 400.0, size, width, height, g)  # 8 rays 12 px apart: 85 px


def test_patch_loss_is_ssim_of_the_patch_images() -> None:
    width, height, size, side = 90, 70, 12, 96.0
    g = torch.Generator().manual_seed(3)
    render, target = torch.rand(height, width, 3, generator=g), torch.rand(height, width, 3, generator=g)
    pix = patch_pixels((45.0, 35.0), side, size, width, height, g)
    stride = patch_stride(side, size)
    r0, c0 = (int(v) for v in rows_cols(pix[0], width))
    crop = lambda img: img[r0 : r0 + size * stride : stride, c0 : c0 + size * stride : stride].permute(2, 0, 1)[None]  # noqa: E731
    want = (1 - ssim(crop(render), crop(target), SSIM_WINDOW)).mean()
    got = patch_loss(render.reshape(-1, 3)[pix], target.reshape(-1, 3)[pix], size)
    torch.testing.assert_close(got, want)
    assert float(patch_loss(target.reshape(-1, 3)[pix], target.reshape(-1, 3)[pix], size)) == pytest.approx(0.0, abs=1e-6)


def test_patch_loss_scores_a_blurred_mouth_worse_than_a_sharp_one_of_equal_squared_error() -> None:
    """The reason for the term: two half-open mouths averaged (what the squared error settles on
    when the code leaves the state uncertain) against a sharp mouth a row off."""
    size = 16

    def mouth(row: int) -> torch.Tensor:
        img = torch.full((size, size, 3), 0.8)
        img[row : row + 4] = 0.1  # the dark gap between the lips
        return img.reshape(-1, 3)

    truth, blurred, shifted = mouth(6), 0.5 * (mouth(4) + mouth(8)), mouth(7)
    mse = lambda x: float(((x - truth) ** 2).mean())  # noqa: E731
    assert mse(blurred) == pytest.approx(mse(shifted), rel=1e-6)
    assert float(patch_loss(blurred, truth, size)) > float(patch_loss(shifted, truth, size)) + 0.2


def test_config_checks_the_patch_fits_the_mouth_rays() -> None:
    TrainConfig(lip_patch=16).validate()  # 256 mouth rays of 1024
    for bad in (dict(lip_patch=MIN_PATCH - 1), dict(lip_patch=-1), dict(lip_patch=17), dict(lip_patch=16, frames=2), dict(lip_patch=16, lip_patch_weight=-0.1)):
        with pytest.raises(ValueError, match="lip_patch"):
            TrainConfig(**bad).validate()
    assert TrainConfig.from_dict(json.loads(json.dumps({"lip_patch": 8, "lip_patch_weight": 0.5}))).lip_patch_weight == 0.5
    assert TrainConfig.from_stored({"head_iters": 10}).lip_patch == 0  # runs stored before the key: no patch


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("lp") / "data", SynthConfig(seconds=1.6, size=32, voice="formant", seed=5))


def trainer(scene: Path, root: Path, **kw: object) -> Trainer:
    ds = load_dataset(scene)
    root.mkdir()
    return Trainer(root, ds, model_config(ds.meta), TrainConfig(rays=256, head_iters=6, torso_iters=2, log_every=3, **kw), "cpu", progress=False)  # type: ignore[arg-type]


def test_stage_one_rays_end_with_the_patch_and_keep_the_mouths_share(scene: Path, tmp_path: Path) -> None:
    tr = trainer(scene, tmp_path / "run", lip_patch=8)
    frame = tr.ds.meta.train[0]
    pose = tr.ds.head_pose(frame)
    state = tr.generator.get_state()
    pix = tr.head_rays(frame, pose, 256)
    assert pix.shape == (256,)
    # The draws: 192 head-box rays, 0 further mouth rays (64 = round(0.25 * 256)), the patch last.
    tr.generator.set_state(state)
    tr.pick_rays(tr.head_box_pixels(frame, pose), 192)
    torch.testing.assert_close(pix[-64:], tr.lip_patch_pixels(pose))
    uv, depth = tr.ds.meta.mouth_in_image(pose)
    side = MOUTH_CROP * tr.ds.meta.intrinsics[0] / float(depth)
    r, c = rows_cols(pix[-64:], tr.ds.meta.width)
    assert abs(float(c.float().mean()) + 0.5 - float(uv[0])) <= 1 + 0.5 * PATCH_REGION * side  # about the mouth
    assert abs(float(r.float().mean()) + 0.5 - float(uv[1])) <= 1 + 0.5 * PATCH_REGION * side


def test_the_patch_term_is_the_weighted_loss_of_each_frames_last_rays(scene: Path, tmp_path: Path) -> None:
    tr = trainer(scene, tmp_path / "run", lip_patch=8, lip_patch_weight=0.5, frames=2, mouth_rays=0.5)
    groups = tr.step_frames("head", 0, 6, tr.head_rays, tr.codes)
    assert len(groups) == 2 and all(len(pix) == 128 for _, pix, _ in groups)
    extra = (groups[0][0], groups[0][1][:5], groups[0][2])  # a third group (an eye batch's place): not a patch
    part = tr.head_part(tr.batch_of([*groups, extra]))
    penalty = tr.lip_patch_penalty([*groups, extra], part)
    rgb, target = part[0].fine.rgb, part[1]
    want = 0.5 * patch_loss(torch.cat([rgb[64:128], rgb[192:256]]), torch.cat([target[64:128], target[192:256]]), 8)
    torch.testing.assert_close(penalty, want)
    assert penalty.requires_grad
    torch.testing.assert_close(target[192:256], tr.head_target(groups[1][0], groups[1][1][-64:]))


def test_training_logs_the_patch_and_adds_it_to_the_loss(scene: Path, tmp_path: Path) -> None:
    rows = {}
    for name, weight in (("with", 1.0), ("without", 0.0)):
        tr = trainer(scene, tmp_path / name, lip_patch=8, lip_patch_weight=weight)
        tr.fit()
        rows[name] = [json.loads(line) for line in (tmp_path / name / "log.jsonl").read_text().splitlines()]
    first = {name: next(r for r in rs if r["stage"] == "head") for name, rs in rows.items()}
    # Same draws and the same first step, so the first window's losses differ by the patch's term.
    assert first["with"]["lip_patch"] > 0 and math.isfinite(first["with"]["lip_patch"])
    assert first["with"]["loss"] > first["without"]["loss"] + 0.5 * first["with"]["lip_patch"]
    assert all("lip_patch" not in r for r in rows["with"] if r["stage"] == "torso")
