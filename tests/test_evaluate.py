"""`occflownet eval`: known answers (ground truth as prediction scores 1.0), saved predictions, ONNX = torch, errors."""
import json
import subprocess
import sys

import numpy as np
import pytest

from occflownet.cli import main
from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy
from occflownet.evaluate import evaluate


def _ground_truth_predictor(root):
    """A predictor that looks the sample up by its images and returns its own labels (σ = 1 where occupied)."""
    index = load_index(root)
    by_first_pixel = {}
    for p in range(len(index)):
        sample = index[p]
        from occflownet.data.loaders import load_sample_images

        by_first_pixel[load_sample_images(root, sample).tobytes()] = sample.occupancy_path

    def predict(images, intrinsics, cam2ego):
        occ = load_occupancy(root, by_first_pixel[images.tobytes()]).semantics
        return occ, (occ != 17).astype(np.float32)

    return predict


def test_ground_truth_as_prediction_scores_one(prepared_synth_root):
    root, _ = prepared_synth_root
    result = evaluate(root, _ground_truth_predictor(root), split="all", max_samples=2, progress=False)
    assert result["samples"] == 2
    assert result["occupancy"]["camera_mask"]["miou"] == pytest.approx(1.0)
    assert result["occupancy"]["all_voxels"]["miou"] == pytest.approx(1.0)
    assert result["rayiou"]["rayiou"] == pytest.approx(1.0)
    assert {"rayiou@1", "rayiou@2", "rayiou@4"} <= set(result["rayiou"])


def test_eval_checkpoint_and_onnx_agree_and_save_predictions(prepared_synth_root, tmp_path):
    import torch

    from occflownet.model import create_model, get_preset, save_checkpoint

    root, _ = prepared_synth_root
    cfg = get_preset("tiny")
    model = create_model(cfg, seed=0)
    with torch.no_grad():  # make the random model predict something: bias the density head upwards
        for m in model.modules():
            if getattr(m, "bias", None) is not None and m.bias.numel() == 1:
                m.bias.fill_(0.5)
    ckpt = save_checkpoint(tmp_path / "m.pt", model, cfg)
    preds = tmp_path / "preds"
    out_json = tmp_path / "eval.json"
    assert main(["eval", "--checkpoint", str(ckpt), "--dataroot", str(root), "--split", "all", "--max-samples", "2",
                 "--save-predictions", str(preds), "--output", str(out_json), "--quiet"]) == 0
    torch_result = json.loads(out_json.read_text())
    index = load_index(root)
    files = sorted(preds.glob("*.npz"))
    assert [f.stem for f in files] == sorted(index.tokens[:2])
    with np.load(files[0]) as z:
        assert z["occupancy"].shape == (200, 200, 16) and z["occupancy"].dtype == np.uint8
        assert z["density"].dtype == np.float32

    from export.onnx_export import export_model

    onnx_path = export_model(model.eval(), cfg, tmp_path / "m.onnx").path
    code = (f"import sys, json; from occflownet.cli import main; "
            f"rc = main(['eval', '--model', {str(onnx_path)!r}, '--dataroot', {str(root)!r}, '--split', 'all', "
            f"'--max-samples', '2', '--output', {str(tmp_path / 'onnx.json')!r}, '--quiet']); "
            f"assert 'torch' not in sys.modules, 'eval --model imported torch'; sys.exit(rc)")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    onnx_result = json.loads((tmp_path / "onnx.json").read_text())
    for key in ("camera_mask", "all_voxels"):
        a, b = torch_result["occupancy"][key], onnx_result["occupancy"][key]
        assert a["voxels"] == b["voxels"]
        assert np.allclose(np.array(a["confusion"]), np.array(b["confusion"]), atol=0.0001 * a["voxels"])


def test_eval_errors_name_the_problem(prepared_synth_root, tmp_path, capsys):
    root, _ = prepared_synth_root
    assert main(["eval", "--checkpoint", str(tmp_path / "missing.pt"), "--dataroot", str(root), "--quiet"]) == 1
    assert "missing.pt" in capsys.readouterr().err
    assert main(["eval", "--model", str(tmp_path / "missing.onnx"), "--dataroot", str(root), "--quiet"]) == 1
    assert "missing.onnx" in capsys.readouterr().err
    assert main(["eval", "--model", str(tmp_path / "x.onnx"), "--dataroot", str(tmp_path), "--quiet"]) == 1
