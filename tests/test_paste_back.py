"""Paste-back: the rendered square goes back into the source video's full frames, in the order the
render took the training poses; outside the crop the source is untouched, inside it is the render,
with a feathered seam between."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from adnerf.commands.paste_back import PasteBackError, feather_mask, paste, paste_back_frames, source_frames_of_dataset
from adnerf.commands.render_video import RenderError, pingpong, plan_paste_back, render_audio_video
from adnerf.io import AudioTrack, FrameReader, read_video, write_video
from adnerf.model.run_folder import load_run
from adnerf.model.train import TrainConfig, train
from adnerf.preprocess.framing import Framing
from adnerf.synth import SynthConfig, synthesize

W, H = 96, 64


def _numbered_video(path: Path, n: int, fps: float = 10.0, size: tuple[int, int] = (W, H), audio: bool = False) -> Path:
    """Frames whose left half's grey level is 8 * k (frame k) and whose right half holds a gradient."""
    w, h = size
    frames = np.zeros((n, h, w, 3), np.uint8)
    for k in range(n):
        frames[k, :, : w // 2] = 8 * k % 256
        frames[k, :, w // 2 :] = np.linspace(0, 255, w - w // 2, dtype=np.uint8)[None, :, None]
    track = AudioTrack((0.3 * np.sin(2 * np.pi * 220 * np.arange(int(n / fps * 16000)) / 16000)).astype(np.float32), 16000, 0.0) if audio else None
    return write_video(path, frames, fps, track)


def test_the_feather_is_one_inside_and_ramps_to_the_edges_inside_the_frame() -> None:
    f = Framing((W, H), (20, 0, 50, 64), (25, 32))
    mask = feather_mask(f, feather=0.1)  # 5 px
    assert mask.shape == (64, 50)
    assert np.all(mask[:, 5:-5] == 1)
    np.testing.assert_allclose(mask[30, :6], [1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6, 1], rtol=1e-6)
    np.testing.assert_allclose(mask[30, -6:], [1, 5 / 6, 4 / 6, 3 / 6, 2 / 6, 1 / 6], rtol=1e-6)
    # The crop spans the frame's height: its top and bottom edges are the frame's and are not blended.
    assert np.all(mask[0, 5:-5] == 1) and np.all(mask[-1, 5:-5] == 1)
    assert mask.min() > 0


def test_outside_the_crop_the_frame_is_untouched_and_inside_it_is_the_render() -> None:
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    f = Framing((W, H), (30, 8, 40, 40), (20, 20))
    square = rng.integers(0, 256, (20, 20, 3), dtype=np.uint8)
    out = paste(square, frame, f, feather_mask(f))
    outside = np.ones((H, W), bool)
    outside[8:48, 30:70] = False
    np.testing.assert_array_equal(out[outside], frame[outside])
    up = cv2.resize(square, (40, 40), interpolation=cv2.INTER_LINEAR)
    n = max(1, round(0.04 * 40))
    np.testing.assert_array_equal(out[8 + n : 48 - n, 30 + n : 70 - n], up[n:-n, n:-n])
    with pytest.raises(PasteBackError, match="96x64"):
        paste(square, frame[:, :50], f, feather_mask(f))


def test_the_reader_gives_any_order_of_frames_as_a_full_decode(tmp_path: Path) -> None:
    video = _numbered_video(tmp_path / "v.mp4", 23)
    every = read_video(video, audio=False).frames
    order = pingpong(np.arange(23), 60)
    with FrameReader(video, chunk=4) as reader:
        assert len(reader) == 23
        for k in order:
            np.testing.assert_array_equal(reader[int(k)], every[k])
        with pytest.raises(IndexError):
            reader[23]


def test_the_datasets_frames_are_found_in_the_source_after_its_trim(tmp_path: Path) -> None:
    video = _numbered_video(tmp_path / "v.mp4", 30, fps=10.0)
    f = Framing((W, H), (0, 0, 64, 64), (32, 32), start_s=1.0)
    np.testing.assert_array_equal(source_frames_of_dataset(f, video, 15, 10.0), np.arange(10, 25))
    with pytest.raises(PasteBackError, match="20 frames from 1 s on, the dataset has 25"):
        source_frames_of_dataset(f, video, 25, 10.0)


def test_frames_are_pasted_into_the_source_frame_the_render_took_its_pose_from(tmp_path: Path) -> None:
    """Output frame j goes into source frame pingpong(j) (fails with the frames in plain order,
    looped, or one frame off); outside the crop it is that source frame exactly."""
    video = _numbered_video(tmp_path / "v.mp4", 6)
    every = read_video(video, audio=False).frames
    f = Framing((W, H), (40, 8, 48, 48), (24, 24))
    squares = [np.full((24, 24, 3), 200, np.uint8)] * 14
    index = pingpong(np.arange(6), 14)
    out = list(paste_back_frames(squares, f, video=video, source_index=index))
    assert len(out) == 14
    for j, frame in enumerate(out):
        np.testing.assert_array_equal(frame[:, :40], every[index[j]][:, :40])
        assert np.all(frame[20:40, 50:80] == 200)
    still = np.zeros((H, W, 3), np.uint8)
    assert all(np.all(fr[:, :40] == 0) for fr in paste_back_frames(squares[:3], f, still=still))


@pytest.fixture(scope="module")
def cropped_run(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    """A tiny run whose dataset says it was cropped from a larger source video (made here)."""
    root = tmp_path_factory.mktemp("paste")
    data = synthesize(root / "data", SynthConfig(seconds=1.2, size=32, voice="formant", seed=3))
    run = load_run(train(data, root / "run", config=TrainConfig(head_iters=2, torso_iters=2, rays=64, log_every=2, checkpoint_every=2), progress=False))
    n, fps = int(run.meta["n_frames"]), float(run.meta["fps"])
    source = _numbered_video(root / "source.mp4", n, fps=fps, size=(W, H), audio=True)
    run.meta["framing"] = Framing((W, H), (32, 0, 64, 64), (32, 32), 0.0, str(source)).to_dict()
    return run, source


def test_render_pastes_back_at_the_sources_size_by_default(cropped_run: tuple, tmp_path: Path) -> None:
    run, source = cropped_run
    summary = render_audio_video(run, source, tmp_path / "out.mp4")
    assert summary["pasted_back"] and summary["size"] == [W, H]
    out = read_video(tmp_path / "out.mp4")
    assert out.frames.shape[1:] == (H, W, 3) and out.audio is not None
    src = read_video(source, audio=False).frames
    order = pingpong(np.arange(len(src)), len(out.frames))
    # Left of the crop: the source frame of the pose used (to the encoder's precision).
    err = np.abs(out.frames[:, :, :30].astype(int) - src[order][:, :, :30].astype(int)).mean()
    assert err < 3, err
    square = render_audio_video(run, source, tmp_path / "square.mp4", paste_back=False)
    assert not square["pasted_back"] and read_video(tmp_path / "square.mp4", audio=False).frames.shape[1:] == (32, 32, 3)


def test_paste_back_refusals(cropped_run: tuple, tmp_path: Path) -> None:
    run, source = cropped_run
    meta = dict(run.meta)
    with pytest.raises(RenderError, match="was not cropped"):
        plan_paste_back({**meta, "framing": None}, True)
    assert plan_paste_back({**meta, "framing": None}, None) is None
    moved = {**meta, "framing": {**meta["framing"], "video": str(tmp_path / "gone.mp4")}}
    with pytest.raises(RenderError, match="--source VIDEO"):
        plan_paste_back(moved, True)
    with pytest.warns(UserWarning, match="not pasted back"):
        assert plan_paste_back(moved, None) is None
    assert plan_paste_back(moved, None, source=source).video == source
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(RenderError, match="96x64"):
        plan_paste_back(meta, None, still_frame=small)
    full = tmp_path / "full.png"
    cv2.imwrite(str(full), np.full((H, W, 3), 77, np.uint8))
    plan = plan_paste_back(meta, None, background=full)
    assert plan.still is not None and plan.plate.shape == (32, 32, 3) and abs(float(plan.plate.mean()) - 77 / 255) < 1e-6
    assert plan_paste_back(meta, None, background=small).plate is None  # another size: the square only
