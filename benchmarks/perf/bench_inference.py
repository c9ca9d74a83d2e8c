"""Inference latency per preset, six camera images of the real nuScenes frame → grid, with a regression guard.

    python -m benchmarks.perf.bench_inference [--presets tiny base] [--runs 20] [--occupied 0.25] [--checkpoint CKPT]
        [--baseline FILE | --baseline-commit REV] [--profile] [--variants [int8 fp16]] [--openvino] [--torch]
        [--threads N]

For each preset a model (random-init seed 0 with Φσ's output bias shifted so that a fraction ``--occupied`` of the
voxels is occupied — Φs only runs on those —, or the trained ``--checkpoint``) is exported by today's code
(parity-checked on the real frame). Every graph below runs in ONE loop, in turn run by run (the order rotating),
so machine load hits all alike, and is reported as p50 and as a ratio to the first row:

- ``today``: today's graph fed as ``predict``, the server and the C++ runner feed it (the JPEGs decoded at
  reduced scale, ``occflownet.contract.decode_reduction``, in parallel threads: ``predict.load_frame``);
- ``today, whole images``: the same graph on the six images decoded whole (the graph-only gain);
- ``baseline`` (``--baseline FILE``, an ONNX file of the same preset and weights, or ``--baseline-commit REV``:
  that commit is checked out in a ``git worktree`` and its own exporter writes the same weights, saved as a
  checkpoint by this script) fed whole images (the graph-only ratio against ``today, whole images``), fed
  today's inputs (the graph-only ratio at the scale the inference paths decode) and fed at its own reduced scale
  (with ``--baseline-commit``: the ``decode_reduction`` of that checkout, asked of it; else today's), the six
  decoded one after another as a sequential ``predict`` does — with ``--baseline-commit`` by that commit's own
  ``decode_rgb``, else by today's (the end-to-end ratio a user sees against ``today``);
- with ``--variants``: today's int8 (QDQ, ``export/variants.py``, calibrated on the real frame's variations; 7-bit
  weights, and with ``int8-full`` 8-bit weights for CPUs with VNNI/AMX) and fp16 graphs, with their agreement with
  fp32 (the first row); ``--openvino`` adds today's fp32 and int8 graphs run by OpenVINO CPU (f32 precision hint),
  ``--openvino-bf16`` today's fp32 and int8 graphs with OpenVINO's bf16 hint (on CPUs with AVX512-BF16 or AMX).

``--profile`` prints onnxruntime's own profile of each graph (kernel time per op class, share of the run, and the
costliest nodes; for OpenVINO's rows its own per-layer counters, by layer type and kernel), so a loss shows where it
comes from; for a quantised graph also the float kernel time left outside its int8 kernels and the speed-up over
the first graph that this allows at most (as if every int8 kernel took no time). A 2048³ fp32 matmul (torch) is
measured at the start and the end of the run as the machine's reference: the model's FLOPs (torch's counter, and the
image network's share) at that rate (the higher of the start's and one measured after the timings) are the floor of
an fp32 graph that does them no faster than the matmul, and each baseline row's p50 over that floor the most such a
graph can gain on this machine; ``--torch`` also times torch eager
(``model.inference``). JPEG decoding of the six files (whole or at reduced scale, as each row is fed) is timed
with each inference in the same loop ("with decoding": the end-to-end figure of predict, the server and the C++
runner).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import worktree

ROOT = Path(__file__).resolve().parents[2]
FRAME = ROOT.parent / "shared" / "data" / "nuscenes-frame"
SPINNING = False  # onnxruntime worker threads busy-wait (--ort-spinning) or sleep (default, as in predict/serve)

# Runs the exporter of another checkout (argv: root, checkpoint, out) with that checkout's packages: export/ and
# serve/ install as occflownet.export / occflownet.serve, so they are mapped by hand instead of installed.
_FOREIGN_EXPORT = """
import importlib.util, sys
root, ckpt, out = sys.argv[1:4]
sys.path.insert(0, root)
import occflownet
for name in ("export", "serve"):
    spec = importlib.util.spec_from_file_location(f"occflownet.{name}", f"{root}/{name}/__init__.py",
                                                  submodule_search_locations=[f"{root}/{name}"])
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
from occflownet.cli import main
sys.exit(main(["export", "--checkpoint", ckpt, "--out", out]))
"""

# Prints the scale 1/n another checkout's inference paths decode a JPEG at (argv: root, jpeg, H_in, W_in).
_FOREIGN_REDUCTION = """
import sys
root, jpeg, h, w = sys.argv[1:5]
sys.path.insert(0, root)
from occflownet.contract import decode_reduction, image_header
print(decode_reduction(image_header(open(jpeg, "rb").read()), (int(h), int(w))))
"""


def one_by_one_inputs(reduction: int, decode_rgb=None):
    """(ModelInputs of the real frame's six JPEGs decoded at 1/``reduction``, decode): ``decode()`` → uint8
    [6, H, W, 3] decodes the JPEGs held in memory one after another, as a sequential ``predict`` does, with
    ``decode_rgb`` (a baseline commit's own, :func:`tree_decoder`; default today's); the inputs are built by the
    one feeds function (``occflownet.runtime.frame_inputs``) with that reduction's intrinsics."""
    from occflownet.contract import image_header, load_calibration
    from occflownet.predict import find_camera_images
    from occflownet.runtime import frame_inputs

    if decode_rgb is None:
        from occflownet.contract import decode_rgb
    blobs = [p.read_bytes() for p in find_camera_images(FRAME).values()]
    header = image_header(blobs[0])
    decode = lambda: np.stack([decode_rgb(b, reduction) for b in blobs])  # noqa: E731
    inputs = frame_inputs(decode(), load_calibration(FRAME / "calib.json"),
                          sizes=[(header.width, header.height)] * len(blobs), reductions=[reduction] * len(blobs))
    return inputs, decode


def bench_inputs(input_size):
    """(whole, reduced, one_by_one, source): whole = (ModelInputs of the six images decoded whole, decode), reduced =
    (the same as the inference paths decode them, at reduced scale, decode), one_by_one = the six decoded one after
    another at today's reduced scale (:func:`one_by_one_inputs`), as a sequential ``predict`` decodes them. Every
    ``decode()`` → uint8 [6, H, W, 3], for the end-to-end timings: ``reduced``'s is ``predict.load_frame`` (the
    files read and decoded in parallel threads, as the inference paths do), the others decode the JPEGs held in
    memory in turn."""
    from occflownet.contract import decode_reduction, image_header, load_calibration
    from occflownet.predict import find_camera_images, load_frame
    from occflownet.rig import default_rig
    from occflownet.runtime import frame_inputs

    if not (FRAME / "calib.json").is_file():
        images = np.random.default_rng(0).integers(0, 256, (6, 900, 1600, 3), dtype=np.uint8)
        same = (frame_inputs(images, default_rig(1600, 900)), lambda: images)
        return same, same, same, "random images (no real frame)"
    header = image_header(next(iter(find_camera_images(FRAME).values())).read_bytes())
    calib = load_calibration(FRAME / "calib.json")
    reduced = (load_frame(FRAME, input_size).inputs(calib), lambda: load_frame(FRAME, input_size).images)
    return one_by_one_inputs(1), reduced, one_by_one_inputs(decode_reduction(header, input_size)), \
        "real nuScenes frame"


def matmul_gflops(n: int = 2048, reps: int = 5) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    best = min(_timed(lambda: torch.mm(a, b)) for _ in range(reps))
    return 2 * n ** 3 / best / 1e9


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def model_flops(model, inputs) -> tuple[float, float]:
    """(FLOPs of one torch run of ``model`` on ``inputs`` (ModelInputs), those of its image network alone)."""
    from torch.utils.flop_counter import FlopCounterMode

    from occflownet.runtime import TorchPredictor

    with FlopCounterMode(display=False) as counter:
        TorchPredictor(model)(inputs)
    counts = counter.get_flop_counts()
    backbone = sum(counts.get(type(model.backbone).__name__, {}).values())
    return float(counter.get_total_flops()), float(backbone)


def bench_model(name: str, occupied: float, checkpoint: str | None, inputs):
    """The model to time: the trained checkpoint, or random-init (seed 0) with Φσ's bias shifted so that a fraction
    ``occupied`` of the voxels of the real frame is occupied (``inputs``: its ModelInputs)."""
    from occflownet.model import create_model, get_preset, load_checkpoint

    from occflownet.runtime import TorchPredictor

    if checkpoint:
        return load_checkpoint(checkpoint, expect_preset=name)[0].eval()
    model = create_model(get_preset(name), seed=0).eval()
    density = TorchPredictor(model)(inputs)[1]
    with torch.no_grad():
        logits = torch.logit(torch.from_numpy(density)).flatten()
        cut = torch.quantile(logits[::7], 1.0 - occupied) if occupied > 0 else logits.max() + 1
        model.decoder.sigma_head[-1].bias += torch.logit(torch.tensor(model.cfg.threshold)) - cut
        model.decoder.semantic_head[-1].bias.zero_()
    return model


def tree_decoder(tree: Path):
    """The checkout ``tree``'s own ``decode_rgb``: its ``occflownet/contract/images.py`` (which imports no other
    module of the package) loaded as a module of its own, so that the baseline's end-to-end row decodes as that
    commit's inference paths did; None where the file is not there (today's decoder is used then)."""
    import importlib.util

    source = tree / "occflownet" / "contract" / "images.py"
    if not source.is_file():
        return None
    spec = importlib.util.spec_from_file_location("_baseline_contract_images", source)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module                        # dataclasses look their module up while they are made
    spec.loader.exec_module(module)
    return module.decode_rgb


def export_baseline_commit(rev: str, checkpoint: Path, out: Path, input_size: tuple[int, int]):
    """``rev``'s own exporter on ``checkpoint`` → ``out`` (``rev`` checked out by ``benchmarks.harness.worktree``)
    → (the scale 1/n ``rev``'s inference paths decode the real frame's JPEGs at for ``input_size``, ``rev``'s own
    ``decode_rgb`` (:func:`tree_decoder`)), (None, None) without the frame."""
    with worktree(rev) as tree:
        proc = subprocess.run([sys.executable, "-c", _FOREIGN_EXPORT, str(tree), str(checkpoint), str(out)],
                              capture_output=True, text=True, cwd=tree)
        if proc.returncode != 0:
            raise RuntimeError(f"export at {rev} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
        jpeg = FRAME / "CAM_FRONT.jpg"
        if not jpeg.is_file():
            return None, None
        proc = subprocess.run([sys.executable, "-c", _FOREIGN_REDUCTION, str(tree), str(jpeg), *map(str, input_size)],
                              capture_output=True, text=True, cwd=tree, check=True)
        return int(proc.stdout.strip()), tree_decoder(tree)


def profile(session_path: Path, inputs, runs: int, threads: int) -> tuple[dict, dict, float]:
    """onnxruntime's profiler over ``runs`` runs (after one warm-up) on ``inputs`` (ModelInputs): ({op class: ms per
    run}, {node: (ms per run, output shape)}, kernel ms per run)."""
    import onnxruntime as ort

    from occflownet.runtime import OnnxPredictor

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if SPINNING else "0")
    so.enable_profiling = True
    so.profile_file_prefix = str(session_path.parent / f"profile-{session_path.stem}")
    session = ort.InferenceSession(str(session_path), so, providers=["CPUExecutionProvider"])
    predictor = OnnxPredictor(session)
    for _ in range(runs + 1):
        predictor(inputs)
    events = json.loads(Path(session.end_profiling()).read_text())
    ops, nodes = collections.Counter(), collections.Counter()
    shapes = {}
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            node = e["name"][:-len("_kernel_time")]
            ops[e["args"]["op_name"]] += e["dur"] / 1e3 / (runs + 1)
            nodes[node] += e["dur"] / 1e3 / (runs + 1)
            shapes[node] = e["args"].get("output_type_shape")
    return dict(ops), {k: (v, shapes[k]) for k, v in nodes.items()}, sum(ops.values())


# onnxruntime's op classes that compute in int8 (the fused QDQ kernels) or move between int8 and float
INT8_KERNELS = ("QLinear", "QuantizeLinear", "DequantizeLinear", "MatMulInteger", "ConvInteger",
                "DynamicQuantizeLinear")


def openvino_profile(session: "OpenVinoSession", inputs, runs: int) -> tuple[dict, dict, float]:
    """OpenVINO's own per-layer counters (``PERF_COUNT``) over ``runs`` runs after one warm-up: ({"layer type /
    kernel": ms per run}, {node: (ms per run, kernel)}, ms per run); the kernel name says the precision it ran in
    (``brgconv_avx512_I8``: int8, ``..._f32``: float32)."""
    request = session.compiled.create_infer_request()
    feeds = inputs.feeds()
    request.infer(feeds)
    ops, nodes = collections.Counter(), collections.Counter()
    kernels = {}
    for _ in range(runs):
        request.infer(feeds)
        for layer in request.profiling_info:
            ms = layer.real_time.total_seconds() * 1e3 / runs
            ops[f"{layer.node_type} / {layer.exec_type}"] += ms
            nodes[layer.node_name] += ms
            kernels[layer.node_name] = layer.exec_type
    return dict(ops), {k: (v, kernels[k]) for k, v in nodes.items()}, sum(ops.values())


def print_profile(label: str, ops: dict, nodes: dict, total: float, top: int = 12,
                  reference_total: float | None = None) -> None:
    """Per op class and costliest nodes; for a quantised graph also the float kernel time that remains outside the
    int8 kernels and the speed-up it allows at most (``reference_total`` / that: as if every int8 kernel were
    free), the Amdahl bound of quantising these ops and no others."""
    print(f"  profile {label}: kernel time {total:.1f} ms per run")
    for op, ms in sorted(ops.items(), key=lambda kv: -kv[1])[:top]:
        print(f"    {op:34s} {ms:8.2f} ms {100 * ms / total:5.1f} %")
    for node, (ms, shape) in sorted(nodes.items(), key=lambda kv: -kv[1][0])[:6]:
        print(f"      node {node:40s} {ms:7.2f} ms  {str(shape)[:70]}")
    int8 = sum(ms for op, ms in ops.items() if op.startswith(INT8_KERNELS))
    if int8 and reference_total:
        rest = total - int8
        print(f"    int8 kernels {int8:.1f} ms; float kernels {rest:.1f} ms: with free int8 kernels at most "
              f"{reference_total / rest:.2f}x the first graph's kernel time ({reference_total:.1f} ms)")


class OpenVinoSession:
    """OpenVINO CPU (``INFERENCE_PRECISION_HINT`` f32, as tests/test_runtimes.py) behind onnxruntime's ``run``, so
    that an ``OnnxPredictor`` runs it."""

    def __init__(self, path: Path, threads: int, precision: str = "f32", counters: bool = False):
        import openvino as ov

        self.compiled = ov.Core().compile_model(str(path), "CPU", {"INFERENCE_PRECISION_HINT": precision,
                                                                  "INFERENCE_NUM_THREADS": threads,
                                                                  "PERF_COUNT": counters})

    def run(self, names, feeds):
        result = self.compiled(feeds)
        return [result[self.compiled.output(n)] for n in names]


def _openvino(label: str, path: Path, threads: int, counters: bool = False) -> OpenVinoSession:
    """The OpenVINO session of a graph row: f32 precision, or bf16 for the "[OpenVINO bf16]" row."""
    return OpenVinoSession(path, threads, "bf16" if label.endswith("bf16]") else "f32", counters)


def interleaved(graphs: list[tuple[str, object, tuple]], runs: int) -> tuple[dict, dict]:
    """Each (label, predictor, (inputs, decode)) once per round, the order rotating, 2 warm-up rounds →
    ({label: inference seconds}, {label: decode + inference seconds}) per run (decode: the six JPEGs as that
    graph's code decodes them, then the inference on its result with the frame's intrinsics and cam2ego)."""
    from occflownet.runtime import ModelInputs

    infer = {label: [] for label, _, _ in graphs}
    total = {label: [] for label, _, _ in graphs}
    for i in range(runs + 2):
        order = graphs[i % len(graphs):] + graphs[:i % len(graphs)]
        for label, predictor, (inputs, decode) in order:
            t0 = time.perf_counter()
            images = decode()
            t1 = time.perf_counter()
            predictor(ModelInputs.frame(images, inputs.intrinsics[0], inputs.cam2ego[0]))
            t2 = time.perf_counter()
            if i >= 2:
                infer[label].append(t2 - t1)
                total[label].append(t2 - t0)
    return infer, total


def build_graphs(name: str, args, model, whole, reduced, one_by_one, workdir: Path) -> list[tuple[str, Path, tuple]]:
    """Export today's graph (and the requested baseline and variants) → [(label, path, inputs)]: the graphs to
    time, each with the inputs its own code would feed it (the first is today's, the reference of the ratios)."""
    from occflownet.export.onnx_export import export_model
    from occflownet.export.parity import ParitySample
    from occflownet.model import save_checkpoint

    path = workdir / f"{name}.onnx"
    sample = ParitySample.of("bench", reduced[0])                                         # (inputs, decode)
    export_model(model, model.cfg, path, parity_samples=[sample])
    graphs = [("today", path, reduced), ("today, whole images", path, whole)]
    if args.baseline or args.baseline_commit:
        base = Path(args.baseline) if args.baseline else workdir / f"{name}.baseline.onnx"
        if args.baseline_commit:
            ckpt = workdir / f"{name}.pt"
            save_checkpoint(ckpt, model, model.cfg)
            n, decoder = export_baseline_commit(args.baseline_commit, ckpt, base, model.cfg.input_size)
            if n is not None:       # fed as that commit's own paths decode the frame, one camera after another
                which = "its own decode_rgb" if decoder else "today's decode_rgb (none at that commit)"
                print(f"{name}: the baseline's one-by-one row decodes with {which}")
                one_by_one = one_by_one_inputs(n, decoder)
        label = f"baseline {args.baseline_commit or base.name}"
        (w, h) = one_by_one[0].image_size
        graphs += [(f"{label}, whole images", base, whole), (f"{label}, today's scale", base, reduced),
                   (f"{label}, its scale ({w}x{h}) one by one", base, one_by_one)]
    wanted = [] if args.variants is None else (args.variants or ["int8", "fp16"])
    for variant, int8_range in (("int8", "reduced"), ("int8-full", "full")):
        if variant in wanted:
            from occflownet.export.variants import write_int8

            int8 = write_int8(path, workdir / f"{name}.{variant}.onnx", model.cfg,
                              frame=FRAME if FRAME.is_dir() else None, int8_range=int8_range)
            graphs.append((f"today {variant}", int8, reduced))
    if "fp16" in wanted:
        from occflownet.export.variants import write_fp16

        graphs.append(("today fp16", write_fp16(path, workdir / f"{name}.fp16.onnx"), reduced))
    return graphs


def bench_preset(name: str, args, whole, reduced, one_by_one, workdir: Path, threads: int) -> None:
    from occflownet.contract import create_session
    from occflownet.export.onnx_export import agreement
    from occflownet.runtime import OnnxPredictor, TorchPredictor

    model = bench_model(name, args.occupied, args.checkpoint, reduced[0])
    t = time.perf_counter()
    graphs = build_graphs(name, args, model, whole, reduced, one_by_one, workdir)
    print(f"{name}: exported in {time.perf_counter() - t:.0f} s; {len(graphs)} graphs, {args.runs} interleaved runs",
          flush=True)
    if args.openvino:
        hints = ("OpenVINO", "OpenVINO bf16") if args.openvino_bf16 else ("OpenVINO",)
        graphs += [(f"{label} [{hint}]", path, inputs) for hint in hints for label, path, inputs in graphs
                   if label in ("today", "today int8", "today int8-full")]
    sessions = [(label, OnnxPredictor(_openvino(label, path, threads) if "[OpenVINO" in label
                                      else create_session(path, threads, spinning=SPINNING)), inputs)
                for label, path, inputs in graphs]
    times, totals = interleaved(sessions, args.runs)
    ref = sessions[0][1](reduced[0])
    first, first_total = np.median(times[graphs[0][0]]), np.median(totals[graphs[0][0]])
    flops, backbone_flops = model_flops(model, reduced[0])
    rate = max(args.matmul_gflops, matmul_gflops())  # the machine's best of the run's start and now
    floor = flops / (rate * 1e9)
    print(f"{name}: {flops / 1e9:.2f} GFLOP, the image network {backbone_flops / 1e9:.2f} (torch FLOP counter on the "
          f"reduced-scale frame); fp32 occupied {100 * np.mean(ref[0] != 17):.1f} % of voxels")
    print(f"{name}: at the matmul rate ({rate:.1f} GFLOP/s, the higher of the start's and now) these FLOPs take "
          f"at least {floor * 1e3:.1f} ms (the image network {backbone_flops / rate / 1e6:.1f} ms), the "
          f"floor of an fp32 graph doing them no faster than the matmul"
          + "".join(f"; {label} over it {np.median(times[label]) / floor:.2f}x" for label, _, _ in graphs
                    if label.startswith("baseline")))
    for (label, session, inputs), (_, path, _) in zip(sessions, graphs):
        p50, total = np.median(times[label]), np.median(totals[label])
        out = session(inputs[0])
        a = agreement(ref[0], ref[1], out[0], out[1])
        print(f"  {label:42s} p50 {p50 * 1e3:8.1f} ms (p90 {np.percentile(times[label], 90) * 1e3:7.1f}), "
              f"{p50 / first:5.2f}x of today | with decoding p50 {total * 1e3:8.1f} ms, {total / first_total:5.2f}x "
              f"of today | {flops / 1e9 / p50:5.1f} GFLOP/s | vs today: {100 * a['occupancy_equal_fraction']:.3f} % "
              f"voxels equal, density max |d| {a['density_max_abs_diff']:.1e}", flush=True)
    if args.profile:
        reference_total = None
        for label, path, inputs in graphs:
            if "[OpenVINO" in label:
                print_profile(label, *openvino_profile(_openvino(label, path, threads, counters=True), inputs[0],
                                                       args.profile_runs))
                continue
            ops, nodes, total = profile(path, inputs[0], args.profile_runs, threads)
            reference_total = reference_total or total
            print_profile(label, ops, nodes, total, reference_total=reference_total)
    if args.torch:
        predictor = TorchPredictor(model)
        predictor(reduced[0])
        tt = [_timed(lambda: predictor(reduced[0])) for _ in range(max(3, args.runs // 4))]
        print(f"  torch eager (reduced-scale frame)            p50 {np.median(tt) * 1e3:8.1f} ms")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    from occflownet.choices import PRESET_NAMES

    p.add_argument("--presets", nargs="+", default=["tiny"], choices=PRESET_NAMES)
    p.add_argument("--runs", type=int, default=15, help="timed interleaved runs per graph (after 2 warm-up rounds)")
    p.add_argument("--occupied", type=float, default=0.25, help="fraction of occupied voxels to simulate")
    p.add_argument("--checkpoint", help="time this trained checkpoint (of the one preset given) instead")
    p.add_argument("--baseline", help="an ONNX file of the same preset and weights to time beside today's")
    p.add_argument("--baseline-commit", help="export the same weights with this commit's code (git worktree)")
    p.add_argument("--variants", nargs="*", choices=["int8", "int8-full", "fp16"], default=None,
                   help="also time today's reduced-precision graphs (no value: int8 and fp16; int8-full: 8-bit "
                        "weights, for CPUs with VNNI/AMX)")
    p.add_argument("--profile", action="store_true", help="print onnxruntime's per-op profile of each graph")
    p.add_argument("--profile-runs", type=int, default=5)
    p.add_argument("--torch", action="store_true", help="also time torch eager")
    p.add_argument("--openvino", action="store_true", help="also run today's fp32 (and int8) graph on OpenVINO CPU")
    p.add_argument("--openvino-bf16", action="store_true",
                   help="with --openvino: also today's fp32 and int8 graphs with OpenVINO's bf16 precision hint (the "
                        "layers an int8 graph keeps in float then run in bf16)")
    p.add_argument("--keep", help="write the graphs into this folder and keep them (a baseline for later runs)")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--ort-spinning", action="store_true", help="let onnxruntime's idle threads busy-wait")
    args = p.parse_args(argv)
    global SPINNING
    SPINNING = args.ort_spinning
    torch.set_num_threads(args.threads)
    print(f"threads {args.threads} (onnxruntime spinning {SPINNING}); load average {os.getloadavg()[0]:.2f} at start")
    args.matmul_gflops = matmul_gflops()
    print(f"fp32 matmul 2048^3 (torch): {args.matmul_gflops:.1f} GFLOP/s at start", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        if args.keep:
            tmp = args.keep
            Path(tmp).mkdir(parents=True, exist_ok=True)
        for name in args.presets:
            from occflownet.model import get_preset

            whole, reduced, one_by_one, source = bench_inputs(get_preset(name).input_size)
            (w, h), (rw, rh) = whole[0].image_size, reduced[0].image_size
            print(f"{name}: inputs {source}: whole 6x{w}x{h}, as today's paths decode them 6x{rw}x{rh}")
            bench_preset(name, args, whole, reduced, one_by_one, Path(tmp), args.threads)
    print(f"fp32 matmul 2048^3 (torch): {matmul_gflops():.1f} GFLOP/s at end; load average "
          f"{os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
