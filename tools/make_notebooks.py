"""Write the walkthrough notebooks from their cell sources.

    python tools/make_notebooks.py              # write the cells; keep the stored outputs of unchanged cells
    python tools/make_notebooks.py --execute    # also run them and store their outputs (figures as PNG)

Notebooks are stored with their outputs, so that a reader on a code host sees the figures without
running anything. ``--execute`` runs them at their full size (several minutes on 2 CPU cores;
``--small`` at the test size). The test run executes them again (tests/test_notebooks.py), and a
test checks that the stored cells are the ones this script writes.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import nbformat

ROOT = Path(__file__).resolve().parents[1]
md = nbformat.v4.new_markdown_cell
code = nbformat.v4.new_code_cell


def components() -> nbformat.NotebookNode:
    cells = [
        md("# adnerf components: cameras -> rays -> samples -> field -> compositor -> pixels\n\n"
           "This walkthrough builds every stage by hand on an analytic scene whose answer is known, "
           "then lets the `VolumeRenderer` compose the same parts."),
        code("import math\n\nimport matplotlib\nimport matplotlib.pyplot as plt\nimport torch\n\n"
             "import adnerf as A\nfrom adnerf.analytic import UniformSphere\n\ntorch.manual_seed(0)"),
        md("## 1. A camera and its rays\nOpenCV axes (x right, y down, z forward); pixel centres at +0.5; unit directions."),
        code("size = 64\nK = A.intrinsics_matrix(70.0, 70.0, size / 2, size / 2)\n"
             "rays = A.pixel_rays(K, size, size)\nprint(rays.origins.shape, rays.directions.shape)\n"
             "print('centre ray:', rays.directions[size // 2, size // 2])"),
        md("## 2. Samples along the rays\nStratified intervals in fixed bounds `[near, far]`."),
        code("sampler = A.StratifiedSampler(48, A.NearFarBounds(1.5, 4.5))\n"
             "samples = sampler(rays)\nprint(samples.t_starts.shape, samples.positions().shape)"),
        md("## 3. A field at the samples\nA sphere of uniform density (its opacity is known in closed form)."),
        code("sphere = UniformSphere(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), 1.0, 3.0, color=(0.9, 0.6, 0.3))\n"
             "out = sphere(samples.positions(), samples.directions())\nprint(out.rgb.shape, out.density.shape)"),
        md("## 4. Compositing\nLog-space transmittance; the residual transmittance shows the background."),
        code("bg = torch.tensor([0.1, 0.2, 0.4], dtype=torch.float64)\n"
             "px = A.composite(out.rgb, out.density, samples.t_starts, samples.t_ends, background=bg)\n"
             "truth_opacity, truth_depth, hit = sphere.truth(rays.origins, rays.directions)\n"
             "err = (px.opacity - truth_opacity).abs()[hit].mean().item()\n"
             "print(f'mean |opacity error| on the sphere: {err:.2e}')\nassert err < 0.02"),
        code("ray = (size // 2, size // 2)\nfig, ax = plt.subplots(1, 3, figsize=(12, 3.5))\n"
             "ax[0].plot(samples.t_mids[ray].numpy(), px.weights[ray].numpy(), '.-')\n"
             "ax[0].set(title='weights along the centre ray', xlabel='t (scene units)')\n"
             "ax[1].imshow(px.rgb.clamp(0, 1).numpy()); ax[1].set_title('rgb over background')\n"
             "im = ax[2].imshow(torch.where(px.opacity > 0, px.depth, torch.nan).numpy()); ax[2].set_title('expected depth')\n"
             "plt.colorbar(im, ax=ax[2]); plt.tight_layout(); plt.show()"),
        md("## 5. The renderer composes the same parts\nThe renderer does not own the field; a fine pass adds importance samples."),
        code("renderer = A.VolumeRenderer(A.NearFarBounds(1.5, 4.5), n_coarse=24, n_fine=24)\n"
             "result = renderer.render_chunked(rays, sphere, chunk=1024, background=bg)\n"
             "fine_err = (result.final.depth - truth_depth).abs()[hit].mean().item()\n"
             "coarse_err = (result.coarse.depth - truth_depth).abs()[hit].mean().item()\n"
             "print(f'depth error: coarse {coarse_err:.2e}, fine {fine_err:.2e}')\nassert fine_err < coarse_err"),
        md("## 6. The product's layers\nA talking head is a stack of `RadianceLayer`s over a plate. The head layer lives in the "
           "head's canonical space: camera rays are moved into it by the inverse head pose, and its field reads the frame's "
           "audio code from a `FrameCondition`. Here an (untrained) fast field shows that turning the head by 20 degrees turns its render."),
        code("cfg = A.fast_config(cond_dim=8, aabb_min=(-1, -1, -1), aabb_max=(1, 1, 1))\n"
             "field = A.RadianceField(cfg)\n"
             "head = A.RadianceLayer('head', field, None, ((-1, -1, -1), (1, 1, 1)), (32, 0), space='canonical', conditions=('audio',))\n"
             "pose = A.HeadPose(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))\n"
             "audio = torch.randn(8)\nflat = rays.flatten()\n"
             "with torch.no_grad():\n"
             "    a = head.render(flat, A.FrameCondition(audio, pose)).final\n"
             "    b = head.render(flat, A.FrameCondition(audio, pose.perturbed(yaw=math.radians(20)))).final\n"
             "fig, ax = plt.subplots(1, 2, figsize=(7, 3.5))\n"
             "ax[0].imshow(a.rgb.reshape(size, size, 3).numpy()); ax[0].set_title('pose')\n"
             "ax[1].imshow(b.rgb.reshape(size, size, 3).numpy()); ax[1].set_title('yaw + 20 deg'); plt.show()\n"
             "assert not torch.allclose(a.rgb, b.rgb)"),
    ]
    return _notebook(cells)


def _notebook(cells: list) -> nbformat.NotebookNode:
    for i, cell in enumerate(cells):
        cell["id"] = f"cell-{i:02d}"  # stable ids: regenerating a notebook changes only what changed
    nb = nbformat.v4.new_notebook(cells=cells)
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    return nb


def quickstart() -> nbformat.NotebookNode:
    cells = [
        md("# Quickstart: a talking head from a synthetic video\n\n"
           "The demo in small: synthesise a scene with exact ground truth, train the head (stage 1) and the "
           "torso (stage 2), render the held-out audio, turn the head, replace the background, and measure. "
           "The test run executes this notebook at a tiny size (`ADNERF_NOTEBOOK_SMALL=1`); unset it for a "
           "larger run (a few minutes on a laptop CPU)."),
        code("import os\nimport tempfile\nfrom pathlib import Path\n\nimport matplotlib.pyplot as plt\nimport numpy as np\n\n"
             "from adnerf.model.data import load_dataset\nfrom adnerf.commands.demo import new_background\n"
             "from adnerf.evaluation.evaluate import evaluate_run\nfrom adnerf.commands.render_video import render_frames\n"
             "from adnerf.synth import SynthConfig, synthesize\nfrom adnerf.model.train import TrainConfig, load_run, train\n\n"
             "small = os.environ.get('ADNERF_NOTEBOOK_SMALL') == '1'\n"
             "synth_cfg = SynthConfig(seconds=2.0, size=40, voice='formant') if small else SynthConfig(seconds=8.0, size=96)\n"
             "train_cfg = TrainConfig(head_iters=40, torso_iters=20, rays=256) if small else TrainConfig(head_iters=1200, torso_iters=500)\n"
             "work = Path(tempfile.mkdtemp())"),
        md("## 1. A synthetic scene\nA trimesh head wearing a real photograph's face, a jaw that opens with the audio, "
           "a torso that follows the head a little, a static background; `truth/` holds the exact poses, labels, depth and jaw."),
        code("data = synthesize(work / 'data', synth_cfg)\nds = load_dataset(data)\n"
             "print(ds.meta.n_frames, 'frames;', len(ds.meta.train), 'train,', len(ds.meta.test), 'test; features', ds.features.shape)\n"
             "k = int(np.argmax(ds.truth.jaw))\nfig, ax = plt.subplots(1, 4, figsize=(12, 3))\n"
             "ax[0].imshow(ds.frames[0]); ax[0].set_title('frame 0')\nax[1].imshow(ds.frames[k]); ax[1].set_title(f'mouth open (frame {k})')\n"
             "ax[2].imshow(ds.parsing[k], vmin=0, vmax=2); ax[2].set_title('labels: bg / head / torso')\n"
             "ax[3].plot(ds.truth.jaw); ax[3].set_title('true jaw opening'); ax[3].set_xlabel('frame'); plt.tight_layout(); plt.show()"),
        md("## 2. Two-stage training\nStage 1: the head in canonical space over the background plate. "
           "Stage 2: the torso in camera space over the stage-1 render."),
        code("run_dir = train(data, work / 'run', config=train_cfg, progress=False)\n"
             "import json\nrows = [json.loads(l) for l in (run_dir / 'log.jsonl').read_text().splitlines()]\n"
             "for stage in ('head', 'torso'):\n"
             "    r = [x for x in rows if x['stage'] == stage]\n"
             "    plt.plot([x['step'] for x in r], [x['psnr'] for x in r], label=stage)\n"
             "plt.xlabel('iteration'); plt.ylabel('batch PSNR (dB)'); plt.legend(); plt.show()"),
        md("## 3. Render the held-out audio, turn the head, replace the background"),
        code("run = load_run(run_dir)\nmetrics, plain = evaluate_run(run, ds, 'test')\nprint({k: round(v, 3) if isinstance(v, float) else v for k, v in metrics.items()})\n"
             "test = list(ds.meta.test)\nplate = ds.background.astype(np.float32) / 255\n"
             "turned = render_frames(run, ds.features[test], ds.poses[test], plate, yaw=15.0)\n"
             "replaced = render_frames(run, ds.features[test], ds.poses[test], new_background(ds.meta.height, ds.meta.width))\n"
             "i = len(test) // 2\nfig, ax = plt.subplots(1, 4, figsize=(12, 3))\n"
             "for a, img, title in zip(ax, [ds.frames[test[i]], plain.frames[i], turned.frames[i], replaced.frames[i]], ['truth', 'render', 'yaw +15', 'new background']):\n"
             "    a.imshow(img); a.set_title(title); a.axis('off')\nplt.show()\n"
             "assert np.isfinite(metrics['psnr'])"),
    ]
    return _notebook(cells)


def error_vs_runtime() -> nbformat.NotebookNode:
    cells = [
        md("# Error against run time\n\n"
           "Two trade-offs, measured: (1) how fast each field configuration learns the head of the synthetic scene "
           "(`adnerf bench fields`: held-out PSNR after equal budgets of training time), and (2) how the volume-rendering "
           "quadrature error falls with samples per ray, stratified against importance sampling (`adnerf bench render`, "
           "an analytic sphere whose opacity and depth are known in closed form).\n\n"
           "Part 1 draws the saved result of the project's bench run (`docs/bench/fields_cpu.jsonl`). To measure your own "
           "machine: `adnerf bench fields --json --plot fields.png > fields.jsonl` (about 25 minutes on 2 CPU cores)."),
        code("import os\nfrom pathlib import Path\n\nimport matplotlib.pyplot as plt\n\nimport adnerf\n"
             "from adnerf.bench.render import bench_render\nfrom adnerf.bench.fields import bench_fields, format_fields_table, load_rows, plot_fields\n\n"
             "small = os.environ.get('ADNERF_NOTEBOOK_SMALL') == '1'\n"
             "saved = Path(adnerf.__file__).resolve().parents[2] / 'docs' / 'bench' / 'fields_cpu.jsonl'\n"
             "print(saved, 'exists' if saved.exists() else 'not found (installed without the source tree)')"),
        md("## 1. Held-out PSNR against training time\n"
           "Every configuration trains stage 1 (the audio-conditioned head) for the same wall time; the clock stops while "
           "the PSNR is measured on a fixed set of held-out rays. Without the saved file, a short live run stands in."),
        code("if saved.exists():\n    rows = load_rows(saved)\nelse:\n"
             "    rows = bench_fields(configs=['fast', 'fast-no-skip'], budget=3.0, checkpoints=(1.0, 2.0), size=32, synth_seconds=1.6, isolate=False, progress=False)\n"
             "print(format_fields_table(rows))\nfig, ax = plt.subplots(figsize=(7, 4.5))\nplot_fields(rows, ax=ax)\nplt.show()"),
        code("paper = next((r for r in rows if r['config'] == 'paper'), None)\n"
             "for r in rows:\n"
             "    if paper is None or r['config'] == 'paper':\n"
             "        continue\n"
             "    reach = r.get('seconds_to_reference_psnr')\n"
             "    when = 'never' if reach is None else f\"within {reach:g} s, {r['speedup_vs_reference']:g}x sooner\"\n"
             "    print(f\"{r['config']:<17} reaches the paper's {paper['budget_s']:g}-second PSNR ({paper['psnr_final']:.2f} dB): {when}\")"),
        md("## 2. Quadrature error against samples per ray\n"
           "Stratified sampling against NeRF's coarse + importance sampling at the same total number of samples."),
        code("samples = (8, 16, 32, 64) if small else (8, 16, 32, 64, 128, 256)\n"
             "quad = bench_render(samples, size=48 if small else 128, repeats=1 if small else 3)\n"
             "fig, ax = plt.subplots(1, 2, figsize=(11, 4))\n"
             "for method, marker in (('stratified', 'o'), ('importance', 's')):\n"
             "    r = [q for q in quad if q.method == method]\n"
             "    ax[0].loglog([q.samples_per_ray for q in r], [q.opacity_rel_err for q in r], marker=marker, label=method)\n"
             "    ax[1].loglog([q.samples_per_ray for q in r], [q.depth_rel_err for q in r], marker=marker, label=method)\n"
             "ax[0].set(xlabel='samples per ray', ylabel='relative opacity error', title='opacity')\n"
             "ax[1].set(xlabel='samples per ray', ylabel='relative depth error', title='depth')\n"
             "for a in ax:\n    a.grid(True, which='both', alpha=0.3); a.legend()\nplt.tight_layout(); plt.show()"),
        code("by = {(q.samples_per_ray, q.method): q for q in quad}\n"
             "for n in samples:\n"
             "    s, i = by[(n, 'stratified')], by[(n, 'importance')]\n"
             "    print(f'{n:>4} samples: depth error stratified {s.depth_rel_err:.2e}, importance {i.depth_rel_err:.2e}; {s.seconds_per_mrays:.2f} vs {i.seconds_per_mrays:.2f} s per million rays')\n"
             "errs = [by[(n, 'importance')].depth_rel_err for n in samples]\n"
             "assert errs[-1] < errs[0], 'the error must fall with samples per ray'"),
    ]
    return _notebook(cells)


def real_clip() -> nbformat.NotebookNode:
    cells = [
        md("# A real clip: parsing with landmarks, head poses, a render, the metrics\n\n"
           "adnerf on footage of a real person. The clip is `$ADNERF_REAL_CLIP`, else the development clip "
           "`shared/data/talking_head_512.mp4` when it lies beside the checkout, else (so this notebook always runs) "
           "a synthetic clip. The test run executes it small (`ADNERF_NOTEBOOK_SMALL=1`: 128 px, a few seconds of "
           "training); unset that for 256 px and three minutes of training. `adnerf bench real VIDEO` does the same "
           "steps with a training budget and writes the full table (docs/cli.md, docs/benchmarks.md)."),
        code("import json\nimport os\nimport tempfile\nfrom pathlib import Path\n\n"
             "import matplotlib.pyplot as plt\nimport numpy as np\nfrom scipy.spatial.transform import Rotation\n\n"
             "import adnerf\nfrom adnerf.bench.real import resized_video\nfrom adnerf.model.data import load_dataset\n"
             "from adnerf.evaluation.evaluate import evaluate_run, mouth_boxes\nfrom adnerf.preprocess import PreprocessConfig, preprocess_video\n"
             "from adnerf.synth import SynthConfig, synthesize\nfrom adnerf.model.train import TrainConfig, load_run, train\n\n"
             "small = os.environ.get('ADNERF_NOTEBOOK_SMALL') == '1'\nwork = Path(tempfile.mkdtemp())\n"
             "shared = Path(adnerf.__file__).resolve().parents[3] / 'shared' / 'data' / 'talking_head_512.mp4'\n"
             "clip = Path(os.environ.get('ADNERF_REAL_CLIP', shared))\n"
             "if not clip.is_file():\n"
             "    print(f'{clip} is not here: using a synthetic clip instead')\n"
             "    clip = synthesize(work / 'synthetic', SynthConfig(seconds=4.0, size=128, voice='formant')) / 'video.mp4'\n"
             "size = 128 if small else 256\n"
             "train_cfg = TrainConfig(head_iters=60, torso_iters=30) if small else TrainConfig(head_iters=1300, torso_iters=1000)\n"
             "print('clip:', clip)"),
        md("## 1. Preprocess: parsing, landmarks, the jaw-line cut, the clothes\n"
           "The classical parser finds the person by motion; the 68 dlib landmarks give the face; head and torso meet at the jaw "
           "line, so the mouth and chin are in the head layer that the audio drives. Clothes that never move look like the "
           "wall to a motion parser: below the chin they are added to the torso by colour (`face_clothes`), and `torso` "
           "measures how much of the bottom edge under the face is person. The report counts both."),
        code("video, info = resized_video(clip, size, work)\n"
             "if small:  # the first 5 s are enough to see every step\n"
             "    from adnerf.io import read_video, write_video\n"
             "    v = read_video(video)\n"
             "    keep = int(5 * v.fps)\n"
             "    video = write_video(work / 'short.mp4', v.frames[:keep], v.fps, v.audio.samples[: int(5 * v.audio.sample_rate)], sample_rate=v.audio.sample_rate)\n"
             "data = work / 'data'\nreport = preprocess_video(video, data, PreprocessConfig(test_fraction=0.15))\n"
             "print(report['face_head_torso_cut'])\nprint(json.dumps(report['layers'], indent=1))\n"
             "print(json.dumps({'clothes': report.get('face_clothes'), 'torso': report.get('torso')}, indent=1))\n"
             "plt.figure(figsize=(14, 4))\nplt.imshow(plt.imread(data / 'preprocess_report.png'))\nplt.axis('off'); plt.show()\n"
             "assert report['layers']['lip_in_head'] >= 0.98"),
        md("## 2. Head poses\nFrom optical-flow tracks on the rigid upper head and bundle adjustment; the canonical axes are "
           "the mean head orientation, so the mean rotation is the identity."),
        code("ds = load_dataset(data, truth=False)\n"
             "angles = Rotation.from_matrix(ds.poses[:, :3, :3]).as_euler('yxz', degrees=True)\n"
             "for k, name in enumerate(('yaw', 'pitch', 'roll')):\n"
             "    plt.plot(angles[:, k], label=name)\n"
             "plt.xlabel('frame'); plt.ylabel('degrees'); plt.legend(); plt.show()\n"
             "mean = Rotation.from_matrix(ds.poses[:, :3, :3]).mean().magnitude()\n"
             "print(f'mean head rotation: {np.degrees(mean):.3f} degrees from the identity')"),
        md("## 3. Train briefly and render the held-out tail\nThe held-out frames are rendered with their own audio and poses."),
        code("run_dir = train(data, work / 'run', config=train_cfg, progress=False)\n"
             "metrics, clip_out = evaluate_run(load_run(run_dir), ds, 'test', landmarks=True)\n"
             "test = list(ds.meta.test)\ni = len(test) // 2\n(x0, y0, x1, y1), = mouth_boxes(ds, [test[i]])\n"
             "fig, ax = plt.subplots(1, 4, figsize=(12, 3))\n"
             "for a, img, title in zip(ax, [ds.frames[test[i]], clip_out.frames[i], ds.frames[test[i]][y0:y1, x0:x1], clip_out.frames[i][y0:y1, x0:x1]],\n"
             "                         ['true', 'render', 'true mouth', 'rendered mouth']):\n"
             "    a.imshow(img); a.set_title(title); a.axis('off')\nplt.show()"),
        md("## 4. The metrics\nPSNR / SSIM on the full frame, the head and the mouth; LMD (landmark distance, from dlib on "
           "render and truth; absent when the detector finds no face in the renders of a run this short); the "
           "mouth-opening correlation and the audio-visual offset."),
        code("keys = ['psnr', 'ssim', 'psnr_head', 'psnr_mouth', 'landmarks_found_render', 'lmd_mouth_px', 'lmd_mouth', 'mouth_open_corr', 'av_offset_frames']\n"
             "for k in keys:\n    v = metrics.get(k)\n    print(f'{k:>24}: {v:.4f}' if isinstance(v, float) else f'{k:>24}: {v}')\n"
             "assert np.isfinite(metrics['psnr'])"),
        md("## 5. What the clip can teach the mouth\n`adnerf lip-signal`: how well a ridge map from the audio windows "
           "predicts the true inner-lip opening, on the held-out tail and cross-validated over six blocks of the clip, and "
           "how the opening follows the voice's loudness. A rendered mouth-opening correlation near the cross-validated "
           "figure is as much as the clip can teach; near zero, film longer (AD-NeRF trains on 3-5 minutes)."),
        code("from adnerf.evaluation.lip_signal import dataset_lip_signal\n"
             "signal = dataset_lip_signal(data)\nprint(json.dumps(signal.to_dict(), indent=1))\n"
             "print(f\"rendered mouth-opening correlation {metrics.get('mouth_open_corr')}, the clip's cross-validated ceiling {signal.ridge_cv_corr:.3f}\")\n"
             "assert len(signal.ridge_cv_blocks) == 6"),
    ]
    return _notebook(cells)


NOTEBOOKS: dict[str, Callable[[], nbformat.NotebookNode]] = {
    "01_components.ipynb": components,
    "02_quickstart.ipynb": quickstart,
    "03_error_vs_runtime.ipynb": error_vs_runtime,
    "04_real_clip.ipynb": real_clip,
}


def keep_outputs(new: nbformat.NotebookNode, old: nbformat.NotebookNode) -> nbformat.NotebookNode:
    """``new`` with the outputs of ``old``'s code cells whose id and source are unchanged."""
    stored = {c.get("id"): c for c in old.cells if c.cell_type == "code"}
    for cell in new.cells:
        before = stored.get(cell.get("id"))
        if cell.cell_type == "code" and before is not None and before.source == cell.source:
            cell.outputs, cell.execution_count = before.get("outputs", []), before.get("execution_count")
    return new


def execute(nb: nbformat.NotebookNode, small: bool) -> nbformat.NotebookNode:
    """Run a notebook in a fresh kernel in a scratch folder; figures come back as PNGs (100 dpi)."""
    from nbclient import NotebookClient

    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend
    if small:
        os.environ["ADNERF_NOTEBOOK_SMALL"] = "1"
    else:
        os.environ.pop("ADNERF_NOTEBOOK_SMALL", None)
    with tempfile.TemporaryDirectory() as scratch:
        NotebookClient(nb, timeout=3600, kernel_name="python3", record_timing=False, resources={"metadata": {"path": scratch}}).execute()
    return nb


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="write (and run) the walkthrough notebooks")
    parser.add_argument("--execute", action="store_true", help="run each notebook and store its outputs")
    parser.add_argument("--small", action="store_true", help="with --execute: at the test size (ADNERF_NOTEBOOK_SMALL=1)")
    parser.add_argument("--only", action="append", choices=sorted(NOTEBOOKS), help="only this notebook (repeatable)")
    args = parser.parse_args(argv)
    for name in args.only or NOTEBOOKS:
        out = ROOT / "notebooks" / name
        nb = NOTEBOOKS[name]()
        if args.execute:
            start = time.perf_counter()
            nb = execute(nb, args.small)
            print(f"ran {name} in {time.perf_counter() - start:.0f} s")
        elif out.exists():
            nb = keep_outputs(nb, nbformat.read(out, as_version=4))
        nbformat.write(nb, out)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
