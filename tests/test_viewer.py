"""occflownet/viewer and the server page's routes, without a browser (tests/test_viewer_browser.py and
tests/test_serve_page.py open them in Chromium): the grid files it reads, the HTML it writes (self-contained,
no network), the committed script built from web/ (sources hash), ``occflownet view`` / ``predict --html``, and
``GET /ui`` (its headers, the API key, ``OCCFLOWNET_UI=0``)."""
from __future__ import annotations

import base64
import hashlib
import json
import re
import zlib
from pathlib import Path

import numpy as np
import pytest
from serve_fixtures import build_fake_model, wait_app_ready
from starlette.testclient import TestClient

from occflownet.cli import main
from occflownet.occ3d import CAR, FREE, GRID, VEGETATION
from occflownet.viewer import BUNDLE, FILE_POLICY, ViewGrid, read_grid, viewer_data, viewer_html, write_viewer

REPO = Path(__file__).resolve().parents[1]
LABELS = REPO.parent / "shared" / "data" / "occ3d-sample" / "labels.npz"
FRAME = REPO.parent / "shared" / "data" / "nuscenes-frame"


def small_grid() -> np.ndarray:
    occ = np.full(GRID.shape, FREE, np.uint8)
    occ[100:110, 95:100, 2:6] = CAR
    occ[20:30, 20:30, 0:10] = VEGETATION
    return occ


def _payload(html: str) -> dict:
    text = re.search(r'<script type="application/json" id="occ-data">(.*?)</script>', html, re.S).group(1)
    return json.loads(text)


def _grid_of(pane: dict) -> np.ndarray:
    assert pane["encoding"] == "zlib-base64"
    return np.frombuffer(zlib.decompress(base64.b64decode(pane["data"])), np.uint8).reshape(GRID.shape)


# ------------------------------------------------------------------------------------------ reading grids
def test_reads_every_grid_file_the_tools_write(tmp_path):
    occ = small_grid()
    np.savez_compressed(tmp_path / "predict.npz", occupancy=occ, density=np.zeros(GRID.shape, np.float32))
    np.save(tmp_path / "server.npy", occ)
    (tmp_path / "grid.bin").write_bytes(occ.tobytes())
    mask = np.zeros(GRID.shape, np.uint8)
    mask[100:105] = 1
    np.savez_compressed(tmp_path / "labels.npz", semantics=occ, mask_lidar=mask, mask_camera=mask)
    for name in ("predict.npz", "server.npy", "grid.bin"):
        g = read_grid(tmp_path / name)
        assert g.name == "prediction" and g.mask_camera is None
        np.testing.assert_array_equal(g.occupancy, occ)
    gt = read_grid(tmp_path / "labels.npz")
    assert gt.name == "ground truth"
    np.testing.assert_array_equal(gt.mask_camera, mask)


@pytest.mark.parametrize("write, match", [
    (lambda p: np.save(p / "g.npy", np.zeros((10, 10, 10), np.uint8)), "shape"),
    (lambda p: np.save(p / "g.npy", np.zeros(GRID.shape, np.float32)), "integer class ids"),
    (lambda p: np.save(p / "g.npy", np.full(GRID.shape, 40, np.uint8)), "0..17"),
    (lambda p: np.savez(p / "g.npz", other=np.zeros(3)), "neither 'occupancy' nor 'semantics'"),
    (lambda p: (p / "g.bin").write_bytes(b"abc"), "not a raw uint8 grid"),
])
def test_bad_grid_files_are_refused_naming_the_file(tmp_path, write, match):
    write(tmp_path)
    path = next(tmp_path.iterdir())
    with pytest.raises(ValueError, match=match) as exc:
        read_grid(path)
    assert str(path) in str(exc.value)


# ------------------------------------------------------------------------------------------ the HTML file
def test_viewer_file_is_self_contained_and_carries_the_grids(tmp_path):
    occ = small_grid()
    mask = (occ == CAR).astype(np.uint8)
    path = write_viewer(tmp_path / "v.html", [ViewGrid("ground truth", occ, mask), ViewGrid("prediction", occ)],
                        title="a <test>")
    html = path.read_text()
    assert f'content="{FILE_POLICY}"' in html and "default-src 'none'" in FILE_POLICY
    assert "<title>a &lt;test&gt;</title>" in html
    assert BUNDLE.read_text() in html                                   # the script is inside, not linked
    assert not re.search(r"<(script|link|img)[^>]+(src|href)=", html)   # nothing to fetch
    data = _payload(html)
    assert [g["name"] for g in data["grids"]] == ["ground truth", "prediction"]
    np.testing.assert_array_equal(_grid_of(data["grids"][0]["occupancy"]), occ)
    np.testing.assert_array_equal(_grid_of(data["grids"][0]["mask_camera"]), mask)
    assert data["shape"] == [200, 200, 16] and data["free_index"] == FREE and len(data["colors"]) == 18
    assert [c["name"] for c in data["cameras"]][:2] == ["CAM_FRONT", "CAM_FRONT_RIGHT"]   # default rig frusta
    assert all(c["image"] is None and c["image_size"] == [1600, 900] for c in data["cameras"])


def test_a_closing_script_tag_in_the_data_cannot_end_the_script():
    html = viewer_html(viewer_data([ViewGrid("x</script><b>", small_grid())]))
    assert "x</script>" not in html and _payload(html)["grids"][0]["name"] == "x</script><b>"


@pytest.mark.skipif(not FRAME.is_dir(), reason=f"real frame not found at {FRAME}")
def test_view_command_with_images_and_calibration(tmp_path, capsys):
    out = tmp_path / "view.html"
    assert main(["view", str(LABELS), "--images", str(FRAME), "--calib", str(FRAME / "calib.json"),
                 "--out", str(out)]) == 0
    assert "39092 occupied voxels" in capsys.readouterr().out
    data = _payload(out.read_text())
    cams = {c["name"]: c for c in data["cameras"]}
    calib = json.loads((FRAME / "calib.json").read_text())["cameras"]
    np.testing.assert_allclose(cams["CAM_FRONT"]["intrinsic"], calib["CAM_FRONT"]["intrinsic"], rtol=1e-6)
    np.testing.assert_allclose(cams["CAM_BACK"]["cam2ego"], calib["CAM_BACK"]["cam2ego"], rtol=1e-6, atol=1e-6)
    assert cams["CAM_FRONT"]["image_size"] == [1600, 900]
    assert cams["CAM_FRONT"]["image"].startswith("data:image/jpeg;base64,")
    assert out.stat().st_size < 2 * 2**20                              # thumbnails, not the 1600x900 originals


def test_view_command_errors(tmp_path, capsys):
    assert main(["view", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "v.html")]) == 1
    assert "grid file not found" in capsys.readouterr().err
    np.save(tmp_path / "g.npy", small_grid())
    assert main(["view", str(tmp_path / "g.npy"), "--images", str(tmp_path), "--out", str(tmp_path / "v.html")]) == 1
    assert "missing camera images" in capsys.readouterr().err


def test_committed_script_is_built_from_the_current_sources():
    """The bundle's first line records the SHA-256 of web/'s sources (web/build.mjs computes it the same way):
    after a change under web/, run scripts/build-web and commit the new occflownet/viewer/assets script."""
    web = REPO / "web"
    inputs = ["package.json", "package-lock.json", "build.mjs",
              *sorted(f"src/{p.name}" for p in (web / "src").glob("*.js"))]
    h = hashlib.sha256()
    for name in inputs:
        h.update(name.encode() + b"\0" + (web / name).read_text().replace("\r\n", "\n").encode() + b"\0")
    first = BUNDLE.read_text().split("\n", 1)[0]
    assert f"sources-sha256={h.hexdigest()}" in first, f"stale bundle ({first}): run scripts/build-web"


# ------------------------------------------------------------------------------------------ GET /ui
@pytest.fixture(scope="module")
def fake_model(tmp_path_factory):
    return build_fake_model(tmp_path_factory.mktemp("viewer-serve") / "fake.onnx")


def _client(model, **settings):
    from occflownet.serve.app import create_app
    from occflownet.serve.settings import ServeSettings

    return TestClient(create_app(ServeSettings(model_path=str(model), **settings)))


def test_ui_page_and_script_are_served_with_a_strict_policy(fake_model):
    with _client(fake_model) as c:
        wait_app_ready(c)
        r = c.get("/", follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"] == "/ui"
        page = c.get("/ui")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        policy = page.headers["content-security-policy"]
        assert "default-src 'none'" in policy and "script-src 'self'" in policy and "connect-src 'self'" in policy
        srcs = re.findall(r'(?:src|href)="([^"]+)"', page.text)
        assert srcs == ["/ui/occflownet-web.js"]                        # the one asset, from this server
        script = c.get(srcs[0])
        assert script.status_code == 200 and script.content == BUNDLE.read_bytes()
        assert script.headers["content-type"].startswith("text/javascript")
        assert 'route="/ui"' in c.get("/metrics").text


def test_ui_can_be_switched_off(fake_model, monkeypatch):
    from occflownet.serve.settings import ServeSettings

    monkeypatch.setenv("OCCFLOWNET_UI", "0")
    assert ServeSettings.from_env().ui is False
    with _client(fake_model, ui=False) as c:
        wait_app_ready(c)
        for path in ("/", "/ui", "/ui/occflownet-web.js"):
            r = c.get(path)
            assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
        assert c.get("/v1/metadata").status_code == 200


def test_with_an_api_key_the_page_loads_but_the_api_still_needs_the_key(fake_model):
    with _client(fake_model, api_key="s3cret") as c:
        assert c.get("/ui").status_code == 200 and c.get("/ui/occflownet-web.js").status_code == 200
        assert c.get("/v1/metadata").status_code == 401
        assert c.post("/v1/occupancy").status_code == 401
        assert c.get("/v1/metadata", headers={"Authorization": "Bearer s3cret"}).status_code == 200


def test_eval_html_needs_save_predictions(tmp_path, capsys):
    assert main(["eval", "--model", str(tmp_path / "m.onnx"), "--dataroot", str(tmp_path), "--html", "1"]) == 2
    assert "--html needs --save-predictions" in capsys.readouterr().err
