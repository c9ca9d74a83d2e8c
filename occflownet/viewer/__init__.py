"""The 3D viewer of occupancy grids: one self-contained HTML file per grid (``occflownet view``, ``predict --html``,
``eval --html``, the quickstart), and the script of the server page (``GET /ui``). Numpy only (OpenCV when camera
images are shrunk into thumbnails), so every stage — predict, eval, quickstart, serve — may use it.

The drawing is ``assets/occflownet-web.js``: three.js (WebGL) and the viewer of ``web/src/``, bundled by
``scripts/build-web`` (npm + esbuild; the bundle is committed, so nothing is built at install time). A viewer file
inlines that script and its data, and declares a Content-Security-Policy that allows no network access at all; the
server serves the same script from this package's data (no CDN). The page: ``assets/page.html``.

Grids it reads (:func:`read_grid`): ``.npy`` uint8 [200, 200, 16] (the server's ``application/x-npy``, the C++
program's ``--out``), ``.npz`` with ``occupancy`` (``predict --out``, ``eval --save-predictions``) or Occ3D
``semantics`` with ``mask_camera`` (``labels.npz``), and the raw 640,000 bytes of ``application/octet-stream``.
"""
from __future__ import annotations

import base64
import html
import json
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.files import atomic_path
from occflownet.options import option
from occflownet.occ3d import CAMERAS, CLASS_COLORS, CLASS_NAMES, FREE, GRID

ASSETS = Path(__file__).resolve().with_name("assets")
BUNDLE = ASSETS / "occflownet-web.js"
PAGE = ASSETS / "page.html"
THUMBNAIL_WIDTH = 480          # camera images are shrunk to this width (JPEG) inside a viewer file
# A viewer file fetches nothing: scripts, styles and images are inline, every other kind of request is refused.
FILE_POLICY = "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; img-src data:"


@dataclass(frozen=True)
class ViewConfig:
    """What a viewer file shows besides its grid (`occflownet view` derives its options from these fields,
    ``occflownet/options.py``): the ground truth beside it, the camera thumbnails and frusta, the title."""

    gt: str | None = option(None, "Occ3D labels.npz shown beside the grid")
    images: str | None = option(None, "folder with CAM_FRONT.jpg ... for thumbnails")
    calib: str | None = option(None, "calibration JSON for the camera frusta (default: the default rig)")
    title: str | None = option(None, "page title (default: the grid's file name)")


@dataclass(frozen=True)
class ViewGrid:
    """One pane of the viewer: a name, occupancy uint8 [200, 200, 16] ([x, y, z], 17 = free) and, for Occ3D
    labels, mask_camera uint8 [200, 200, 16] (the voxels eval scores; the others can be hidden)."""

    name: str
    occupancy: np.ndarray
    mask_camera: np.ndarray | None = None


def _checked(array: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(array)
    if a.shape != GRID.shape:
        raise ValueError(f"{what}: expected a grid of shape {GRID.shape}, got {a.shape}")
    if not (np.issubdtype(a.dtype, np.integer) or a.dtype == np.bool_):
        raise ValueError(f"{what}: expected integer class ids, got dtype {a.dtype}")
    if a.size and (int(a.min()) < 0 or int(a.max()) > FREE):
        raise ValueError(f"{what}: class ids must lie in 0..{FREE}, got {int(a.min())}..{int(a.max())}")
    return np.ascontiguousarray(a, dtype=np.uint8)


def read_grid(path: str | Path, name: str | None = None) -> ViewGrid:
    """A grid file (see the module docstring) → :class:`ViewGrid`; ``name`` defaults to "ground truth" for Occ3D
    labels and "prediction" otherwise. FileNotFoundError / ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"grid file not found: {path}")
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if "occupancy" in z:
                    return ViewGrid(name or "prediction", _checked(z["occupancy"], f"{path}: occupancy"))
                if "semantics" in z:
                    mask = _checked(z["mask_camera"], f"{path}: mask_camera") if "mask_camera" in z else None
                    return ViewGrid(name or "ground truth", _checked(z["semantics"], f"{path}: semantics"), mask)
                raise ValueError(f"{path}: an .npz with neither 'occupancy' nor 'semantics' (has {sorted(z)})")
        if path.suffix == ".npy":
            return ViewGrid(name or "prediction", _checked(np.load(path, allow_pickle=False), str(path)))
        data = path.read_bytes()
        if len(data) != int(np.prod(GRID.shape)):
            raise ValueError(f"{path}: not .npy/.npz, and {len(data)} bytes are not a raw uint8 grid "
                             f"({int(np.prod(GRID.shape))} bytes)")
        return ViewGrid(name or "prediction", _checked(np.frombuffer(data, np.uint8).reshape(GRID.shape), str(path)))
    except (OSError, EOFError, zlib.error) as exc:
        raise ValueError(f"{path}: cannot read the grid: {exc}") from None


def _bytes(array: np.ndarray) -> dict:
    return {"encoding": "zlib-base64",
            "data": base64.b64encode(zlib.compress(np.ascontiguousarray(array).tobytes(), 6)).decode("ascii")}


def _thumbnail(data: bytes, name: str) -> tuple[str, tuple[int, int]]:
    """Image bytes → (data URL of a JPEG at most THUMBNAIL_WIDTH wide, (w, h) of the image as given)."""
    import cv2

    from occflownet.contract import decode_rgb

    rgb = decode_rgb(data)
    if rgb is None:
        raise ValueError(f"{name}: not a decodable JPEG/PNG image")
    h, w = rgb.shape[:2]
    if w > THUMBNAIL_WIDTH:
        rgb = cv2.resize(rgb, (THUMBNAIL_WIDTH, round(h * THUMBNAIL_WIDTH / w)), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:  # pragma: no cover - encoding a plain uint8 image does not fail
        raise ValueError(f"{name}: JPEG encoding failed")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii"), (w, h)


def camera_entries(calibration: Mapping | None = None, images: Mapping[str, bytes] | None = None,
                   cameras: Sequence[str] = CAMERAS) -> list[dict]:
    """The cameras the viewer draws (frusta; thumbnails where ``images`` has one): per camera its intrinsic for
    the image size drawn, cam2ego, that size and the thumbnail. ``calibration``: calibration JSON (contract), or
    None = the default rig (:func:`occflownet.rig.default_rig`). Sizes: the image's own, else the calibration's,
    else twice the principal point. CalibrationError / ValueError naming the camera."""
    from occflownet.contract import validate_calibration
    from occflownet.rig import default_rig

    cal = validate_calibration(calibration if calibration is not None else default_rig(), cameras)
    images = images or {}
    thumbs = {cam: _thumbnail(images[cam], cam) for cam in cameras if cam in images}
    sizes = []
    for cam, K, stated in zip(cameras, cal.intrinsics, cal.image_sizes):
        fallback = (round(2 * K[0, 2] + 1), round(2 * K[1, 2] + 1))
        sizes.append(thumbs[cam][1] if cam in thumbs else stated or fallback)
    K, T = cal.arrays_for(sizes, "the calibration")
    return [{"name": cam, "intrinsic": K[i].tolist(), "cam2ego": T[i].tolist(), "image_size": list(sizes[i]),
             "image": thumbs[cam][0] if cam in thumbs else None} for i, cam in enumerate(cameras)]


def viewer_data(grids: Sequence[ViewGrid], cameras: list[dict] | None = None, title: str = "occupancy") -> dict:
    """The JSON the viewer script reads (web/src/viewer.js): grid geometry, classes and colours, the panes
    (occupancy and mask as zlib + base64), the cameras."""
    if not grids:
        raise ValueError("nothing to show: no grid")
    panes = []
    for g in grids:
        pane = {"name": g.name, "occupancy": _bytes(_checked(g.occupancy, g.name))}
        if g.mask_camera is not None:
            pane["mask_camera"] = _bytes(_checked(g.mask_camera, f"{g.name} mask_camera") != 0)
        panes.append(pane)
    return {"title": title, "shape": list(GRID.shape), "lower": list(GRID.lower), "voxel_size": GRID.voxel_size,
            "free_index": FREE, "classes": list(CLASS_NAMES), "colors": CLASS_COLORS.tolist(), "grids": panes,
            "cameras": cameras if cameras is not None else camera_entries()}


def viewer_html(data: dict, subtitle: str = "") -> str:
    """One self-contained HTML page: the viewer script and ``data`` inline, nothing fetched."""
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")     # cannot close the <script>
    script = BUNDLE.read_text(encoding="utf-8")
    title = html.escape(str(data.get("title", "occupancy")))
    return (
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n"
        f"<meta http-equiv=\"Content-Security-Policy\" content=\"{FILE_POLICY}\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{title}</title></head>\n<body class=\"occ-body\">\n<h1 style=\"font-size:18px;margin:0\">{title}</h1>\n"
        f"<p class=\"occ-note\" style=\"margin:2px 0 8px\">{html.escape(subtitle)}</p>\n<div id=\"occ-view\"></div>\n"
        f"<script type=\"application/json\" id=\"occ-data\">{payload}</script>\n"
        f"<script>{script}</script>\n</body></html>\n")


def write_viewer(path: str | Path, grids: Sequence[ViewGrid], calibration: Mapping | None = None,
                 images: Mapping[str, bytes] | None = None, title: str = "occupancy", subtitle: str = "") -> Path:
    """Write the viewer file of ``grids`` (one pane each, side by side) to ``path`` (creating the folder); frusta
    from ``calibration`` (None = the default rig), thumbnails from ``images`` ({camera: JPEG/PNG bytes})."""
    path = Path(path)
    data = viewer_data(grids, camera_entries(calibration, images), title)
    with atomic_path(path) as tmp:                      # the file appears whole or not at all
        tmp.write_text(viewer_html(data, subtitle), encoding="utf-8")
    return path
