"""Viewer files (``occflownet view``, ``eval --html``) opened in a real browser: headless Chromium (Debian's, set up
by scripts/setup-browser) with WebGL in software. Each file must draw (the viewer's drawn flag), fetch nothing, and
its screenshot must not be blank and must show the colours of the classes the grid has on top; the toggles (a
class, the voxels outside mask_camera, the layout) must change what is drawn. Files: a real Occ3D labels.npz, a
briefly trained model's grid for the real nuScenes frame, the ground truth beside the prediction of a synthetic
keyframe, and a 60,000-voxel grid for the size target (≤ 10 MB; how soon it draws is measured by
benchmarks/perf/bench_viewer.py, not asserted here: a timing depends on the machine's load).

Screenshots stay under the test's temporary folder (``<tmp>/screenshots/``); with OCCFLOWNET_UPDATE_DOCS=1 they are
also copied to docs/ (the pictures the README and docs/viewer.md show)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from browser import (browser, check_drawn, colour_pixels, keep_screenshot, png_rgb, setup_browser, top_classes,
                     wait_for)
from exported_models import FRAME, exported_trained_tiny, frame_available, trained_tiny_checkpoint, workdir
from selenium.webdriver.common.by import By

from occflownet.cli import main
from occflownet.occ3d import CAMERAS, CLASS_COLORS, FREE, VEGETATION
from occflownet.viewer import read_grid

REPO = Path(__file__).resolve().parents[1]
LABELS = REPO.parent / "shared" / "data" / "occ3d-sample" / "labels.npz"
needs_labels = pytest.mark.skipif(not LABELS.is_file(), reason=f"real Occ3D sample not found at {LABELS}")
needs_frame = pytest.mark.skipif(not frame_available(), reason=f"real frame not found at {FRAME}")
DRAWN = "window.occViewer && window.occViewer.state().drawn && window.occViewer.state()"


@pytest.fixture(scope="module")
def driver():
    setup_browser()
    with browser() as d:
        yield d


def open_viewer(driver, path: Path) -> tuple[dict, float]:
    """Load a viewer file and wait until it is drawn → (viewer state, seconds from get() to drawn)."""
    t0 = time.perf_counter()
    driver.get(path.as_uri())
    state = wait_for(driver, DRAWN)
    seconds = time.perf_counter() - t0
    fetched = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert fetched == [], f"the viewer file fetched {fetched}"
    return state, seconds


def canvas_rgb(driver) -> np.ndarray:
    return png_rgb(driver.find_element(By.CSS_SELECTOR, ".occ-canvas canvas").screenshot_as_png)


def shown_count(driver, pane: int = 0) -> int:
    return driver.execute_script(f"return window.occViewer.state().panes[{pane}].voxels")


@needs_labels
def test_real_occ3d_labels_draw_with_their_class_colours_and_toggles(driver, tmp_path):
    out = tmp_path / "labels.html"
    assert main(["view", str(LABELS), "--out", str(out), "--title", "Occ3D-nuScenes labels.npz"]) == 0
    gt = read_grid(LABELS)
    inside = (gt.occupancy != FREE) & (gt.mask_camera > 0)
    state, seconds = open_viewer(driver, out)
    print(f"\nlabels.npz viewer: drawn {seconds:.2f} s after get(), first frame at {state['firstFrameMs']:.0f} ms "
          f"after navigation start, {state['panes'][0]['faces']} faces")
    assert state["panes"][0]["voxels"] == int(inside.sum())            # outside mask_camera hidden at first
    found = check_drawn(canvas_rgb(driver), top_classes(gt.occupancy, inside), CLASS_COLORS)
    keep_screenshot(tmp_path, "viewer_occ3d_labels.png", driver.get_screenshot_as_png())
    # the mask toggle shows every labelled voxel, a class toggle hides one class and its colour
    driver.find_element(By.ID, "occ-outside-mask").click()
    assert shown_count(driver) == int((gt.occupancy != FREE).sum())
    assert VEGETATION in found
    driver.find_element(By.CSS_SELECTOR, f'input[data-class="{VEGETATION}"]').click()
    assert shown_count(driver) == int(((gt.occupancy != FREE) & (gt.occupancy != VEGETATION)).sum())
    time.sleep(0.5)                                                    # the next animation frame
    assert colour_pixels(canvas_rgb(driver), CLASS_COLORS[VEGETATION]) == 0


@needs_frame
def test_trained_model_grid_of_the_real_frame_draws_with_thumbnails(driver, tmp_path):
    model = exported_trained_tiny()[0]
    grid, html = tmp_path / "grid.npz", tmp_path / "grid.html"
    assert main(["predict", "--model", str(model), "--images", str(FRAME), "--calib", str(FRAME / "calib.json"),
                 "--out", str(grid), "--html", str(html)]) == 0
    occ = read_grid(grid).occupancy
    expected = top_classes(occ, min_columns=25)
    assert expected, "the trained model's grid has no class on 25 columns: nothing to check"
    state, seconds = open_viewer(driver, html)
    print(f"\ntrained model's grid: {int((occ != FREE).sum())} voxels, drawn {seconds:.2f} s after get()")
    assert state["panes"][0]["voxels"] == int((occ != FREE).sum())
    check_drawn(canvas_rgb(driver), expected, CLASS_COLORS)
    thumbs = driver.execute_script("return [...document.querySelectorAll('.occ-thumbs img')]"
                                   ".map(i => [i.alt, i.naturalWidth])")
    assert sorted(n for n, _ in thumbs) == sorted(CAMERAS) and all(w == 480 for _, w in thumbs)
    keep_screenshot(tmp_path, "viewer_prediction_real_frame.png", driver.get_screenshot_as_png(), docs=False)


def test_eval_html_shows_ground_truth_beside_prediction(driver, tmp_path):
    root = workdir() / "trained-world"
    trained_tiny_checkpoint()                                          # builds the world too
    preds = tmp_path / "predictions"
    assert main(["eval", "--checkpoint", str(trained_tiny_checkpoint()), "--dataroot", str(root), "--split", "val",
                 "--max-samples", "1", "--no-rayiou", "--no-fog", "--quiet", "--save-predictions", str(preds),
                 "--html", "1"]) == 0
    (html,) = preds.glob("*.html")
    state, _ = open_viewer(driver, html)
    assert [p["name"] for p in state["panes"]] == ["ground truth", "prediction"]
    assert all(p["voxels"] > 0 for p in state["panes"])
    keep_screenshot(tmp_path, "viewer_side_by_side.png", driver.get_screenshot_as_png())
    # switchable: one pane at a time
    driver.execute_script("const s = document.getElementById('occ-layout'); s.value = '1';"
                          "s.dispatchEvent(new Event('change'));")
    wait_for(driver, "window.occViewer.state().layout === '1'")


@needs_labels
def test_a_60000_voxel_grid_opens_and_stays_small(driver, tmp_path):
    import sys

    sys.path.insert(0, str(REPO))                    # the benchmarks package, when pytest runs from elsewhere
    from benchmarks.perf.bench_viewer import dense_grid

    occ = dense_grid(60000)
    np.save(tmp_path / "dense.npy", occ)
    out = tmp_path / "dense.html"
    assert main(["view", str(tmp_path / "dense.npy"), "--out", str(out)]) == 0
    size = out.stat().st_size
    state, seconds = open_viewer(driver, out)
    print(f"\n60,000 voxels: {size / 2**20:.2f} MiB, drawn {seconds:.2f} s after get(), first frame "
          f"{state['firstFrameMs'] / 1e3:.2f} s after navigation start, {state['panes'][0]['faces']} faces")
    assert size <= 10 * 2**20
    assert state["drawn"], state            # how soon: benchmarks/perf/bench_viewer.py (first_frame_s), not a test
    check_drawn(canvas_rgb(driver), top_classes(occ), CLASS_COLORS)
