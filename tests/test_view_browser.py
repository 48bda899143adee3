"""`ev3dgs view` as a person sees it: the page loaded in a real headless Chromium (the system's /usr/bin/chromium,
driven by playwright; no browser is downloaded), on a scene and on a short training run. Checks: the 3D canvas
is not blank (the training frusta are drawn in their colour, and for the run the splats add colours of their
own), the panel's images are exactly the selected view's blurry and sharp frames (PNG, lossless), the "look
through camera" button moves the 3D view, and the browser's console shows no error on either page.

`make test-slow` installs Chromium from the system packages when it is missing (apt-get install chromium)."""
import base64
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None:
    pytest.skip("no system Chromium (apt-get install chromium; `make test-slow` does it)", allow_module_level=True)
pytest.importorskip("viser")
pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install ev3dgs[dev])")

from test_view_server import _free_port, _start, _stop, _url  # noqa: E402
from view_scene import make_scene  # noqa: E402

FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]
SELECT = 2
TRAIN_RGB = np.array([230, 120, 20])   # ev3dgs.view.server.TRAIN_COLOUR


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("browser") / "scene.h5")


@pytest.fixture(scope="module")
def run_dir(scene_path, tmp_path_factory):
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer

    out = tmp_path_factory.mktemp("browser_run") / "run"
    cfg = TrainConfig(scene=scene_path, iterations=40, init_points=400, checkpoint_every=20, threads=1, seed=0,
                      sh_degree=0)
    Trainer(cfg, out, quiet=True).fit()
    return out


def _page_images(page) -> list[np.ndarray]:
    """Every blob: image on the page, decoded (the panel's images are PNG)."""
    b64 = page.evaluate("""async () => {
        const out = [];
        for (const img of document.querySelectorAll('img')) {
            if (!img.src.startsWith('blob:')) continue;
            const buf = new Uint8Array(await (await fetch(img.src)).arrayBuffer());
            let s = ''; for (const b of buf) s += String.fromCharCode(b);
            out.push(btoa(s));
        }
        return out;
    }""")
    imgs = []
    for item in b64:
        a = cv2.imdecode(np.frombuffer(base64.b64decode(item), np.uint8), cv2.IMREAD_UNCHANGED)
        if a is not None and a.ndim == 3:
            imgs.append(cv2.cvtColor(a, cv2.COLOR_BGR2RGB if a.shape[2] == 3 else cv2.COLOR_BGRA2RGB))
    return imgs


def _look(path: str, shot: Path):
    """Load the page; returns its text, its panel images, the 3D canvas's box and the console's errors. After
    the screenshot, presses "look through camera" once and writes a second screenshot beside `shot`."""
    from playwright.sync_api import sync_playwright

    proc = _start([path, "--port", str(_free_port()), "--select", str(SELECT)])
    errors = []
    try:
        url = _url(proc, timeout=180)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.on("console", lambda m: errors.append(f"console: {m.text}") if m.type == "error" else None)
                page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
                page.goto(url)
                page.wait_for_function("document.querySelectorAll('img[src^=\"blob:\"]').length >= 3",
                                       timeout=120_000)
                page.wait_for_timeout(8000)  # software WebGL: let a few frames render
                page.screenshot(path=str(shot))
                text = page.inner_text("body")
                images = _page_images(page)
                box = page.evaluate("""() => { let best = null;
                    for (const c of document.querySelectorAll('canvas')) { const r = c.getBoundingClientRect();
                        if (!best || r.width * r.height > best.w * best.h) best = {x: r.x, y: r.y, w: r.width, h: r.height}; }
                    return best; }""")
                page.get_by_role("button", name="look through camera").click()
                page.wait_for_timeout(4000)
                page.screenshot(path=str(_through(shot)))
            finally:
                browser.close()
    finally:
        rc, err = _stop(proc)
    assert rc == 0, err
    return text, images, box, errors


def _through(shot: Path) -> Path:
    return shot.with_name(shot.stem + "_through" + shot.suffix)


def _check_moved(shot: Path, box: dict):
    """The look-through button changed the 3D view (the training camera's view is not the opening one)."""
    a, b = _canvas_pixels(shot, box), _canvas_pixels(_through(shot), box)
    assert np.abs(a - b).max(axis=1).astype(bool).mean() > 0.01, "look through camera did not move the view"


def _canvas_pixels(shot: Path, box: dict) -> np.ndarray:
    img = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
    x0, y0 = int(box["x"]), int(box["y"])
    # the left 60% of the canvas: the GUI panel floats over its right side
    return img[y0:y0 + int(box["h"]), x0:x0 + int(0.6 * box["w"])].reshape(-1, 3).astype(int)


def _check_panel(text: str, images: list, scene_path: str):
    from ev3dgs.view import data

    c = data.load_scene(scene_path)
    assert f"view {SELECT}" in text
    assert any(im.shape == c.frame(SELECT).shape and np.array_equal(im, c.frame(SELECT)) for im in images)
    assert any(im.shape == c.sharp(SELECT).shape and np.array_equal(im, c.sharp(SELECT)) for im in images)
    assert not any(im.shape == c.frame(0).shape and np.array_equal(im, c.frame(0)) for im in images)


def test_scene_in_the_browser(scene_path, tmp_path):
    shot = tmp_path / "scene.png"
    text, images, box, errors = _look(scene_path, shot)
    assert errors == []
    _check_panel(text, images, scene_path)
    _check_moved(shot, box)
    px = _canvas_pixels(shot, box)
    assert box["w"] > 600 and box["h"] > 400
    assert len(np.unique(px, axis=0)) > 50, "the 3D canvas is blank"
    near_train = np.abs(px - TRAIN_RGB).max(axis=1) < 40
    assert near_train.sum() > 30, "no training frustum drawn"


def test_run_in_the_browser(scene_path, run_dir, tmp_path):
    shot = tmp_path / "run.png"
    text, images, box, errors = _look(str(run_dir), shot)
    assert errors == []   # a page with Gaussians logged a NaN bounding sphere (see server.CLIENT_FIX)
    _check_panel(text, images, scene_path)
    _check_moved(shot, box)
    assert "Gaussians from model.pt" in text
    px = _canvas_pixels(shot, box)
    assert len(np.unique(px, axis=0)) > 50, "the 3D canvas is blank"
    # the same page without the splats: their colours are what the model adds
    _, _, box2, errors2 = _look(scene_path, tmp_path / "scene_only.png")
    assert errors2 == []
    base = _canvas_pixels(tmp_path / "scene_only.png", box2)
    assert np.abs(px - base).max(axis=1).astype(bool).mean() > 0.002, "the Gaussians are not drawn"
