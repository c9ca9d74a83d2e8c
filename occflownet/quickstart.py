"""The README's main job as library calls: synthetic world → prepare → train ``small`` for a bounded time → eval →
export (with its parity check) → the side-by-side picture and an example folder for ``predict``.

Every stage calls the same library function its command-line verb calls (``synth.generate``, ``data.prepare``,
``train.train``, ``eval.evaluate``, ``export.export_model``) and announces the equivalent ``occflownet ...``
command first, so the output doubles as a transcript of the workflow. Finished stages are reused on a re-run:
the world is kept when it exists and training resumes from its last checkpoint.
"""
from __future__ import annotations

import json
import shlex
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from occflownet.choices import PRESET_NAMES
from occflownet.contract import calibration_json
from occflownet.data.index import load_index
from occflownet.files import atomic_path
from occflownet.options import check_fields, config_argv, option
from occflownet.train.recipe import TrainConfig
from occflownet.train.recipes import RECIPE_NAMES, REFERENCE_GFLOPS, recipe

if TYPE_CHECKING:
    from occflownet.synth.generate import SynthConfig


@dataclass(frozen=True)
class QuickstartConfig:
    """The quickstart's choices; `occflownet quickstart` derives its options from these fields
    (``occflownet/options.py``)."""

    out: str = option("quickstart", "folder for the world, the run, the model and the pictures")
    scenes: int = option(12, "synthetic scenes, the val split's included; more, shorter scenes generalise better "
                                  "than few long ones at the same cost (docs/results.md#the-quickstart)", minimum=2)
    frames: int = option(4, "keyframes per training scene", minimum=1)
    val_scenes: int = option(1, "scenes of the val split (the last ones); fewer than --scenes", minimum=1)
    val_frames: int = option(8, "keyframes of each val scene (0: --frames)", minimum=0)
    preset: str = option("small", "model preset; small (tiny with a denser lifting and a backbone twice as wide) "
                                  "scores higher on unseen scenes in the quickstart's minutes "
                                  "(docs/results.md#the-quickstart)", choices=PRESET_NAMES)
    recipe: str = option("quickstart", "training recipe (`occflownet recipes`): quickstart = 3D labels inside the "
                                       "camera mask, rendered LiDAR rays of the current frame and the LiDAR points' "
                                       "classes on the image features; quickstart-3d = the labels alone, the "
                                       "cheapest step", choices=RECIPE_NAMES)
    seed: int = option(0, "seed of the world and of the training run")
    train_minutes: float = option(7.0, "training time budget in minutes", minimum=0)
    max_steps: int = option(3000, "step cap (the time budget stops a run first on the 2-core reference CPU)",
                            minimum=1)

    def __post_init__(self):
        check_fields(self)
        if self.val_scenes >= self.scenes:
            raise ValueError(f"val_scenes ({self.val_scenes}) must be fewer than scenes ({self.scenes}): the "
                             f"quickstart trains on the others")


@dataclass(frozen=True)
class StageCosts:
    """What each stage of the quickstart costs per unit of work on the reference machine (float32 matmul rate
    ``matmul_gflops``; a training step costs its recipe's ``step_seconds``, measured on the same machine): the
    basis of the estimate printed at the start (:func:`estimate_minutes`). Measured on the 2-core development
    machine (AMD EPYC, AVX-512 with bf16) by ``python -m benchmarks.perf.bench_quickstart``, which runs the
    quickstart and divides each stage's seconds by its units (docs/results.md)."""

    matmul_gflops: float = REFERENCE_GFLOPS  # the reference machine's float32 matmul rate
    synth_per_keyframe: float = 1.16       # seconds: render, LiDAR, sweeps, labels of one keyframe
    prepare_per_keyframe: float = 0.013
    train_setup: float = 5.0               # seconds before the first step (class counts, spawned data workers,
                                           # numba compilation, first batches)
    eval_per_keyframe: float = 0.19
    export: float = 14.1                   # export with its parity checks, the picture and the viewer file


def matmul_gflops(size: int = 1024, seconds: float = 0.3) -> float:
    """This machine's float32 matmul rate (GFLOP/s) with torch's threads: repeated ``size``³ products for about
    ``seconds`` after one warm-up product."""
    import torch

    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        torch.mm(a, b)
        n += 1
    return 2 * size ** 3 * n / (time.perf_counter() - t0) / 1e9


def estimate_minutes(cfg: QuickstartConfig, gflops: float, costs: StageCosts = StageCosts()) -> dict[str, float]:
    """Minutes per stage on a machine of ``gflops`` (:func:`matmul_gflops`): the reference costs scaled by the matmul
    rates; training is the smaller of its step cap and its time budget (the budget when the recipe's step was not
    measured; ``step_seconds`` is a ``tiny`` step, and the default ``small`` takes about 1.5-1.8× as long in the
    quickstart). A rough guide (±30 % on machines like the reference, more on others), printed so that a user knows
    what to expect; nothing depends on it."""
    scale = costs.matmul_gflops / max(gflops, 1e-3)
    val = cfg.val_scenes * (cfg.val_frames or cfg.frames)    # the last scenes are the val split
    keyframes = (cfg.scenes - cfg.val_scenes) * cfg.frames + val
    per_step = recipe(cfg.recipe).step_seconds
    steps = float("inf") if per_step is None else costs.train_setup + cfg.max_steps * per_step * scale
    seconds = {"synth": keyframes * costs.synth_per_keyframe * scale,
               "prepare": keyframes * costs.prepare_per_keyframe * scale, "train": min(cfg.train_minutes * 60, steps),
               "eval": val * costs.eval_per_keyframe * scale, "export": costs.export * scale}
    return {k: v / 60 for k, v in seconds.items()}


@dataclass(frozen=True)
class QuickstartPaths:
    """Where each stage writes; :meth:`under` lays them out below one folder."""

    world: Path
    run: Path
    checkpoint: Path
    predictions: Path
    eval_json: Path
    onnx: Path
    picture: Path
    viewer: Path
    example: Path
    timings: Path

    @classmethod
    def under(cls, out: Path) -> QuickstartPaths:
        return cls(world=out / "world", run=out / "run", checkpoint=out / "run" / "checkpoints" / "last.pt",
                   predictions=out / "predictions", eval_json=out / "eval.json", onnx=out / "model.onnx",
                   picture=out / "side_by_side.png", viewer=out / "view.html",
                   example=out / "example", timings=out / "timings.json")


def _announce(log: Callable[[str], None], n: int, argv: list[str], note: str = "") -> None:
    log(f"\n[{n}/5] occflownet {shlex.join(argv)}{note}")


def run_quickstart(cfg: QuickstartConfig = QuickstartConfig(),
                   log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True)) -> dict:
    """Run the five stages; returns {"paths": QuickstartPaths, "eval": the eval result, "minutes": wall time}.
    Exceptions of a stage propagate (DatasetError, TrainingError, ExportError, ValueError, OSError ...) after
    ``log`` was told which stage failed."""
    paths = QuickstartPaths.under(Path(cfg.out).resolve())
    t0 = time.monotonic()
    log(_estimate_line(cfg))
    stages = (("synth", _synth), ("prepare", _prepare), ("train", _train), ("eval", _eval), ("export", _export))
    result, seconds = {}, {}
    for n, (name, stage) in enumerate(stages, 1):
        started = time.monotonic()
        try:
            result[name] = stage(cfg, paths, lambda argv, note="": _announce(log, n, argv, note))
        except Exception:
            log(f"quickstart: stage `{name}` failed; fix the error and re-run (finished stages are reused: the "
                "world is kept and training resumes)")
            raise
        seconds[name] = time.monotonic() - started
    started = time.monotonic()
    sample = first_val_sample(result["prepare"].index)
    write_example(paths.world, sample, paths.example)
    write_picture(paths.world, sample, paths.predictions, paths.picture, paths.viewer)
    seconds["export"] += time.monotonic() - started        # the picture and the viewer file count with the export
    with atomic_path(paths.timings) as tmp:
        tmp.write_text(json.dumps({"seconds": seconds, "config": asdict(cfg)}, indent=1) + "\n")
    return {"paths": paths, "eval": result["eval"], "minutes": (time.monotonic() - t0) / 60, "seconds": seconds}


def _estimate_line(cfg: QuickstartConfig) -> str:
    """What the stages should take on this machine (:func:`estimate_minutes`), as one line."""
    gflops = matmul_gflops()
    minutes = estimate_minutes(cfg, gflops)
    parts = ", ".join(f"{name} ~{m:.1f}" for name, m in minutes.items())
    return (f"quickstart: on this machine (float32 matmul {gflops:.0f} GFLOP/s, the reference machine "
            f"{REFERENCE_GFLOPS:.0f}) expect about {sum(minutes.values()):.0f} min: {parts} min "
            f"(training stops at {cfg.max_steps} steps or after {cfg.train_minutes:g} min)")


def synth_settings(cfg: QuickstartConfig, **changes) -> SynthConfig:
    """The quickstart's world as :class:`~occflownet.synth.generate.SynthConfig` (its scenes, keyframes, val split
    and seed, with preview pictures), ``changes`` replacing fields: what ``generate`` is given and, through
    :func:`synth_argv`, what the announced ``occflownet synth`` says."""
    from occflownet.synth.generate import SynthConfig

    world = SynthConfig(scenes=cfg.scenes, frames=cfg.frames, val_scenes=cfg.val_scenes, val_frames=cfg.val_frames,
                        seed=cfg.seed, preview=True)
    return replace(world, **changes)


def synth_argv(world: Path, settings: SynthConfig) -> list[str]:
    """The ``occflownet synth`` arguments that write ``settings`` into ``world``."""
    from occflownet.synth.generate import SynthConfig

    always = ("scenes", "frames", "val_scenes", "val_frames", "seed")
    return ["synth", "--out", str(world), *config_argv(settings, SynthConfig(), always=always)]


def _synth(cfg: QuickstartConfig, paths: QuickstartPaths, announce) -> None:
    from occflownet.synth.generate import generate

    if (paths.world / "gts" / "labels.json").is_file():
        announce(synth_argv(paths.world, synth_settings(cfg)), "   (the world exists: reused)")
        return
    made_before = (paths.world / "v1.0-trainval" / "sample.json").is_file()
    settings = synth_settings(cfg, overwrite=made_before)
    announce(synth_argv(paths.world, settings),
             "   (a world without pipeline labels, from an older version: written again)" if made_before else
             "   (then labelled as `occflownet labels --dataroot` it would be)")
    generate(paths.world, settings)


def _prepare(cfg: QuickstartConfig, paths: QuickstartPaths, announce):
    from occflownet.data.prepare import prepare

    announce(["prepare", "--dataroot", str(paths.world)])
    return prepare(paths.world, progress=True)


def train_config(cfg: QuickstartConfig, world: Path, run: Path, version: str) -> TrainConfig:
    """The run the quickstart trains: recipe ``cfg.recipe`` with ``cfg.preset`` on ``world``'s train split into
    ``run``, for ``cfg``'s time and step budget."""
    return TrainConfig.from_recipe(cfg.recipe, preset=cfg.preset, dataroot=str(world), out=str(run), version=version,
                                   split="train", time_limit_s=cfg.train_minutes * 60, max_steps=cfg.max_steps,
                                   seed=cfg.seed)


def train_argv(train_cfg: TrainConfig) -> list[str]:
    """The ``occflownet train`` arguments that run ``train_cfg`` (and resume it): parsed again, the same config."""
    baseline = TrainConfig.from_recipe(train_cfg.recipe, preset=train_cfg.preset)
    return ["train", *config_argv(train_cfg, baseline, always=("recipe", "preset", "dataroot", "out", "version")),
            "--resume"]


def _train(cfg: QuickstartConfig, paths: QuickstartPaths, announce) -> Path:
    from occflownet.train.loop import train

    train_cfg = train_config(cfg, paths.world, paths.run, load_index(paths.world, None, check_tables=False).version)
    announce(train_argv(train_cfg))
    return train(train_cfg, resume=True, progress=True)


def _eval(cfg: QuickstartConfig, paths: QuickstartPaths, announce) -> dict:
    from occflownet.eval import dumps_json, format_table
    from occflownet.eval.evaluate import evaluate, select_samples
    from occflownet.model import model_from_source
    from occflownet.runtime import TorchPredictor

    announce(["eval", "--checkpoint", str(paths.checkpoint), "--dataroot", str(paths.world), "--split", "val",
              "--save-predictions", str(paths.predictions), "--output", str(paths.eval_json)])
    result = evaluate(select_samples(paths.world, None, "val"), TorchPredictor(model_from_source(paths.checkpoint)),
                      save_predictions=paths.predictions)
    result = {"source": str(paths.checkpoint), "source_kind": "checkpoint", **result}
    print(format_table(result), file=sys.stderr)
    paths.eval_json.write_text(dumps_json(result) + "\n")
    return result


def _export(cfg: QuickstartConfig, paths: QuickstartPaths, announce) -> None:
    from occflownet.export.onnx_export import export_model
    from occflownet.model import model_from_source

    announce(["export", "--checkpoint", str(paths.checkpoint), "--out", str(paths.onnx)])
    model = model_from_source(paths.checkpoint)
    print(export_model(model, model.cfg, paths.onnx).summary(), file=sys.stderr)


def first_val_sample(index):
    """The first keyframe of the val split of a SampleIndex (a SampleRecord)."""
    return index[int(index.split_positions("val")[0])]


def write_picture(world: Path, sample, predictions: Path, path: Path, viewer: Path | None = None) -> Path:
    """The side-by-side picture (:mod:`occflownet.eval.picture`) of keyframe ``sample`` (a SampleRecord of
    ``world``) from its prediction saved in ``predictions``, and its 3D viewer file at ``viewer`` if given."""
    from occflownet.eval.picture import sample_side_by_side, sample_viewer
    from occflownet.pictures import save_png

    with np.load(predictions / f"{sample.token}.npz") as z:
        occupancy = z["occupancy"]
    if viewer is not None:
        sample_viewer(world, sample, occupancy, viewer)
    return save_png(path, sample_side_by_side(world, sample, occupancy))


def write_example(world: Path, sample, folder: Path) -> Path:
    """Copy the six images of keyframe ``sample`` (a SampleRecord of ``world``) to ``folder/CAM_*.jpg`` with its
    ``calib.json`` (intrinsics and cam2ego as the index holds them), the input ``occflownet predict`` takes."""
    folder.mkdir(parents=True, exist_ok=True)
    for cam in sample.cameras:
        shutil.copyfile(world / cam.path, folder / f"{cam.name}.jpg")
    calib = calibration_json(sample.intrinsics, sample.cam2ego) | {"sample_token": sample.token}
    (folder / "calib.json").write_text(json.dumps(calib, indent=1))
    return folder
