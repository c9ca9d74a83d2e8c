"""`occflownet eval` / occflownet.eval.evaluate: known answers (ground truth as prediction scores 1.0, a camera-mask-only
prediction scores 1.0 only with the mask), wiring of the model inputs and ray origins, saved predictions, JSON
layout, ONNX = torch without importing torch, and errors that name the problem before anything runs."""
import hashlib
import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest

from occflownet.cli import main
from occflownet.occ3d import CLASS_NAMES, FREE, NUM_CLASSES
from occflownet.data.index import load_index, save_index
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.eval import OccupancyMetric, RayIoUMetric, scene_ray_origins
from occflownet.eval.evaluate import EvalSamples, evaluate, select_samples

CLASSES = list(CLASS_NAMES[:NUM_CLASSES])


def _labels_by_images(root):
    """{sha1 of a sample's six images: its Occ3D labels} over the whole root."""
    index = load_index(root)
    table = {}
    for p in range(len(index)):
        sample = index[p]
        table[hashlib.sha1(load_sample_images(root, sample).tobytes()).hexdigest()] = \
            load_occupancy(root, sample.occupancy_path)
    return table


def _label_predictor(root, corrupt=None):
    """A batched predictor that recognises each sample by its images and returns (a function of) its labels."""
    table = _labels_by_images(root)

    def predict(inputs):
        images = inputs.images
        assert images.dtype == np.uint8 and images.ndim == 5 and images.shape[1] == 6
        assert inputs.intrinsics.shape == (len(images), 6, 3, 3) and inputs.cam2ego.shape == (len(images), 6, 4, 4)
        labels = [table[hashlib.sha1(im.tobytes()).hexdigest()] for im in images]
        occ = np.stack([lab.semantics if corrupt is None else corrupt(lab) for lab in labels])
        return occ, (occ != FREE).astype(np.float32)

    return predict


def test_ground_truth_as_prediction_scores_one(prepared_synth_root):
    root, _ = prepared_synth_root
    samples = select_samples(root, split="val", max_samples=3)
    result = evaluate(samples, _label_predictor(root), batch_size=2, progress=False)   # batches of 2 and 1
    assert result["samples"] == 3 and result["split"] == "val"
    for key in ("camera_mask", "all_voxels"):
        assert result["occupancy"][key]["miou"] == pytest.approx(1.0)
        assert result["occupancy"][key]["geometry_iou"] == pytest.approx(1.0)
    ray = result["rayiou"]
    assert ray["samples"] == 3 and ray["rays_with_gt_hit"] > 0
    for key in ("rayiou", "rayiou@1", "rayiou@2", "rayiou@4"):
        assert ray[key] == pytest.approx(1.0)
    fog = result["fog"]  # the labels as prediction: exactly as many occupied voxels as labelled, everywhere
    for part in ("camera_mask", "crossed", "never_crossed"):
        assert fog[part]["false_positive"] == 0 and fog[part]["predicted"] == fog[part]["labelled"]
    assert fog["camera_mask"]["fog_factor"] == pytest.approx(1.0) and 0.2 < fog["crossed_fraction"] < 0.9


def test_camera_mask_is_applied(prepared_synth_root):
    """Right inside the camera mask, wrong outside: 1.0 with the mask, < 1 without; voxel count = mask size."""
    root, _ = prepared_synth_root

    def outside_mask_wrong(lab):
        wrong = np.where(lab.semantics == FREE, 0, (lab.semantics + 1) % NUM_CLASSES).astype(np.uint8)
        return np.where(lab.mask_camera.astype(bool), lab.semantics, wrong)

    samples = select_samples(root, split="val", max_samples=2)
    result = evaluate(samples, _label_predictor(root, outside_mask_wrong), rayiou=False, progress=False)
    assert result["rayiou"] is None
    cam, full = result["occupancy"]["camera_mask"], result["occupancy"]["all_voxels"]
    assert cam["miou"] == pytest.approx(1.0)
    assert full["miou"] < 0.9
    masks = [load_occupancy(root, samples.index[int(p)].occupancy_path).mask_camera for p in samples.positions]
    assert cam["voxels"] == sum(int(m.astype(bool).sum()) for m in masks) < full["voxels"] == 2 * 200 * 200 * 16


def test_rayiou_origins_are_the_scene_lidar_origins(prepared_synth_root):
    """A prediction shifted by 3 voxels: the run's RayIoU equals one computed here from the sample records'
    LiDAR poses (origins of all keyframes of the scene, in the current ego frame)."""
    root, _ = prepared_synth_root

    def shift(lab):
        return np.roll(lab.semantics, 3, axis=0)

    samples = select_samples(root, split="val")
    chosen = samples.positions[[1, 4]]
    subset = EvalSamples(samples.dataroot, samples.index, samples.split, chosen)
    result = evaluate(subset, _label_predictor(root, shift), progress=False)["rayiou"]

    expected = RayIoUMetric()
    for p in chosen:
        sample = samples.index[int(p)]
        scene = [samples.index[int(q)] for q in range(*samples.index.scene_range(int(p)))]
        origins = scene_ray_origins(np.stack([s.lidar.sensor2ego for s in scene]),
                                    np.stack([s.ego2global for s in scene]), sample.index_in_scene)
        assert len(origins) > 1 and not np.allclose(origins[0], origins[-1])   # the ego moves in the scene
        gt = load_occupancy(root, sample.occupancy_path).semantics
        expected.update(np.roll(gt, 3, axis=0), gt, origins)
    expected = expected.compute()
    assert 0.0 < result["rayiou@1"] < result["rayiou@4"] < 1.0
    assert result["rays_cast"] == expected["rays_cast"]
    for key in ("rayiou", "rayiou@1", "rayiou@2", "rayiou@4"):
        assert result[key] == pytest.approx(expected[key], abs=1e-12)


# ----------------------------------------------------------------------------------------------- real models
@pytest.fixture(scope="module")
def informative_model(prepared_synth_root, tmp_path_factory):
    """(model, checkpoint path, ONNX path) of a random-init tiny whose output is not trivial: the density head is
    rescaled so about half the voxels pass τ, the semantic head so that more than one class wins (an untouched
    random tiny predicts every voxel free, which would make the parity check below vacuous)."""
    import torch

    from occflownet.export.onnx_export import export_model
    from occflownet.export.parity import ParitySample
    from occflownet.model import create_model, get_preset, save_checkpoint

    root, _ = prepared_synth_root
    folder = tmp_path_factory.mktemp("eval_models")
    cfg = get_preset("tiny")
    model = create_model(cfg, seed=0).eval()
    sample = load_index(root)[0]
    inputs = (load_sample_images(root, sample)[None], sample.intrinsics.astype(np.float32)[None],
              sample.cam2current_ego().astype(np.float32)[None])
    with torch.no_grad():
        _, density = model.inference(*map(torch.from_numpy, inputs))
        logit = torch.logit(density.double())
        median, spread = float(logit.median()), float(logit.std())
        head = model.decoder.sigma_head[-1]
        head.weight.mul_(3.0 / spread)
        head.bias.copy_((head.bias - median) * (3.0 / spread) + math.log(cfg.threshold / (1 - cfg.threshold)))
        model.decoder.semantic_head[-1].weight.mul_(30.0)
    ckpt = save_checkpoint(folder / "tiny.pt", model, cfg)
    parity = [ParitySample("synth sample 0", *inputs)]
    onnx_path = export_model(model, cfg, folder / "tiny.onnx", parity_samples=parity).path
    return model, ckpt, onnx_path


def _run_cli(argv, capsys):
    rc = main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def test_eval_checkpoint_json_and_saved_predictions(prepared_synth_root, informative_model, tmp_path, capsys):
    import torch

    root, _ = prepared_synth_root
    model, ckpt, _ = informative_model
    preds, out_json = tmp_path / "preds", tmp_path / "eval.json"
    rc, out, err = _run_cli(["eval", "--checkpoint", str(ckpt), "--dataroot", str(root), "--max-samples", "3",
                             "--batch-size", "2", "--save-predictions", str(preds), "--output", str(out_json),
                             "--quiet"], capsys)
    assert rc == 0, err
    result = json.loads(out)
    assert result == json.loads(out_json.read_text())
    assert "Occ3D mIoU" in err and "RayIoU" in err and "static mean" in err          # the table on stderr
    assert (result["source"], result["source_kind"], result["split"], result["samples"]) == \
        (str(ckpt), "checkpoint", "val", 3)
    for key in ("camera_mask", "all_voxels"):
        occ = result["occupancy"][key]
        assert {"miou", "miou_static", "miou_dynamic", "geometry_iou", "iou_per_class", "voxels"} <= set(occ)
        assert list(occ["iou_per_class"]) == CLASSES
        assert 0.0 <= occ["miou"] <= 1.0
    ray = result["rayiou"]
    assert {"rayiou", "rayiou@1", "rayiou@2", "rayiou@4"} <= set(ray) and list(ray["iou_per_class"]) == CLASSES
    assert ray["samples"] == 3 and 0.0 <= ray["rayiou"] <= 1.0

    # one file per sample, named by token; the grid is the model's output for the training-style inputs
    index = load_index(root)
    tokens = [index.tokens[p] for p in index.split_positions("val")[:3]]
    assert sorted(f.name for f in preds.iterdir()) == sorted(f"{t}.npz" for t in tokens)
    metric = OccupancyMetric()
    for token in tokens:
        sample = index[index.position_of(token)]
        with np.load(preds / f"{token}.npz") as z:
            occupancy, density = z["occupancy"], z["density"]
        assert occupancy.shape == density.shape == (200, 200, 16)
        assert occupancy.dtype == np.uint8 and density.dtype == np.float32
        with torch.no_grad():
            ref_occ, ref_dens = model.inference(torch.from_numpy(load_sample_images(root, sample)[None]),
                                                torch.from_numpy(sample.intrinsics.astype(np.float32)[None]),
                                                torch.from_numpy(sample.cam2current_ego().astype(np.float32)[None]))
        np.testing.assert_allclose(density, ref_dens[0].numpy(), atol=1e-5)
        assert np.mean(occupancy == ref_occ[0].numpy()) > 0.9999
        gt = load_occupancy(root, sample.occupancy_path)
        metric.update(occupancy, gt.semantics, gt.mask_camera)
    recomputed = np.asarray(metric.compute()["camera_mask"]["confusion"])
    assert recomputed.tolist() == result["occupancy"]["camera_mask"]["confusion"]


def test_eval_onnx_matches_checkpoint_without_torch(prepared_synth_root, informative_model, tmp_path, capsys):
    root, _ = prepared_synth_root
    _, ckpt, onnx_path = informative_model
    common = ["--dataroot", str(root), "--max-samples", "2", "--quiet"]
    rc, out, err = _run_cli(["eval", "--checkpoint", str(ckpt), *common], capsys)
    assert rc == 0, err
    torch_result = json.loads(out)
    code = ("import sys; from occflownet.cli import main; "
            f"rc = main(['eval', '--model', {str(onnx_path)!r}, *{common!r}, '--batch-size', '2']); "
            "assert 'torch' not in sys.modules, 'eval --model imported torch'; sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    onnx_result = json.loads(proc.stdout)
    assert onnx_result["source_kind"] == "onnx"

    cam = np.array(torch_result["occupancy"]["all_voxels"]["confusion"])
    occupied_pred = cam[:, :FREE].sum(axis=0)
    assert cam[:, FREE].sum() > 0 and (occupied_pred > 0).sum() >= 2       # not a trivial (all-free) model
    for key in ("camera_mask", "all_voxels"):
        a, b = torch_result["occupancy"][key], onnx_result["occupancy"][key]
        assert a["voxels"] == b["voxels"]
        diff = np.abs(np.array(a["confusion"]) - np.array(b["confusion"])).sum()
        assert diff <= 2e-4 * a["voxels"]          # the export parity bound: ≥ 99.99 % of voxels identical
        assert b["miou"] == pytest.approx(a["miou"], abs=1e-3)
    for key in ("rayiou", "rayiou@1", "rayiou@2", "rayiou@4"):
        assert onnx_result["rayiou"][key] == pytest.approx(torch_result["rayiou"][key], abs=2e-3)


# ----------------------------------------------------------------------------------------------- errors
def test_eval_errors_name_the_problem(prepared_synth_root, synth_root, tmp_path, capsys):
    root, _ = prepared_synth_root
    unprepared, _ = synth_root
    rc, _, err = _run_cli(["eval", "--checkpoint", str(tmp_path / "missing.pt"), "--dataroot", str(root)], capsys)
    assert rc == 1 and "checkpoint not found" in err and "missing.pt" in err
    rc, _, err = _run_cli(["eval", "--model", str(tmp_path / "missing.onnx"), "--dataroot", str(root)], capsys)
    assert rc == 1 and "ONNX model not found" in err and "missing.onnx" in err

    # data problems are reported before the model is loaded (this "model" is not even ONNX)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(unprepared)], capsys)
    assert rc == 1 and "no sample index" in err and "occflownet prepare --dataroot" in err
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(tmp_path / "nowhere")], capsys)
    assert rc == 1 and "nowhere" in err and "does not exist" in err
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(root), "--split", "test"], capsys)
    assert rc == 1 and "unknown split 'test'" in err and "all, train, val" in err
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(root), "--split", "val"], capsys)
    assert rc == 1 and "junk.onnx" in err and "cannot load" in err                 # the data was fine
    with pytest.raises(SystemExit):
        main(["eval", "--model", str(junk), "--dataroot", str(root), "--batch-size", "0"])


def test_eval_refuses_samples_without_labels(prepared_synth_root, tmp_path, capsys):
    src, _ = prepared_synth_root
    root = tmp_path / "world"
    shutil.copytree(src, root)
    index = load_index(root)
    val = index.split_positions("val")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")

    gone = index[int(val[2])]
    (root / gone.occupancy_path).unlink()                         # labels file deleted after prepare
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(root)], capsys)
    assert rc == 1 and "labels file missing" in err and gone.occupancy_path in err
    # outside the selection it does not matter: the first two samples are fine, so the model is reached
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(root), "--max-samples", "2"], capsys)
    assert rc == 1 and "cannot load" in err

    unlabeled = index[int(val[0])]
    index.arrays["occupancy_path"][unlabeled.position] = b""       # indexed without labels (scene had no gts/)
    save_index(index, root)
    with pytest.raises(ValueError, match=unlabeled.token):
        select_samples(root, split="val", max_samples=1)
    rc, _, err = _run_cli(["eval", "--model", str(junk), "--dataroot", str(root)], capsys)
    assert rc == 1 and unlabeled.token in err and "no Occ3D labels" in err
    assert "of 6 samples" in err and gone.occupancy_path in err
