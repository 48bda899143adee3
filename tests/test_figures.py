"""One polarity colour convention for every figure (ev3dgs/palette.py: ON red, OFF blue), legends, titles that
fit inside their figure, event panels over a stated window, and labelled demo strips (issue 52, item 5).

Each figure is checked to follow the palette by changing the palette's colours to ones no figure uses
otherwise and finding them in the figure's pixels."""
import ast
from pathlib import Path

import numpy as np
import pytest

from ev3dgs import palette, schema
from ev3dgs.view import data

from view_scene import EXPOSURE_US, PERIOD_US, make_scene

ROOT = Path(__file__).resolve().parents[1]
GREEN, MAGENTA = (0, 255, 0), (255, 0, 255)     # test colours: nothing else in these figures is pure


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    # 12 frames that failed to register: the title that used to run off both sides of the figure
    return make_scene(tmp_path_factory.mktemp("fig") / "scene.h5",
                      registration=[{"frame": i, "exposure": [1000 * i, 2000 * i]} for i in range(12)])


@pytest.fixture
def test_colours(monkeypatch):
    monkeypatch.setattr(palette, "ON_RGB", GREEN)
    monkeypatch.setattr(palette, "OFF_RGB", MAGENTA)


def _find(img: np.ndarray, part: np.ndarray) -> tuple[int, int] | None:
    """(row, column) where `part` lies in `img` pixel for pixel (cv2 finds the candidate, numpy checks it:
    matchTemplate's float sums are not exact), or None."""
    import cv2

    score = cv2.matchTemplate(img, part, cv2.TM_SQDIFF)
    y, x = np.unravel_index(int(score.argmin()), score.shape)
    h, w = part.shape[:2]
    return (int(y), int(x)) if np.array_equal(img[y:y + h, x:x + w], part) else None


def _has(img: np.ndarray, rgb, tol: int = 0) -> int:
    return int((np.abs(img[..., :3].astype(int) - np.array(rgb)) <= tol).all(-1).sum())


def _pixels(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3]


def _texts_inside(fig) -> None:
    """Everything drawn with text lies inside the figure (1 px slack): each axes with its title, labels and
    the tick labels it draws, the figure's title and legends; and no two titles overlap."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    box = fig.bbox

    def inside(what, e):
        assert e.x0 >= box.x0 - 1 and e.x1 <= box.x1 + 1 and e.y0 >= box.y0 - 1 and e.y1 <= box.y1 + 1, \
            (what, e, box)

    for ax in fig.axes:
        inside(ax.get_title() or ax.get_ylabel() or "an axes", ax.get_tightbbox(r))
    texts = [fig._suptitle] + [t for leg in fig.legends for t in leg.get_texts()]
    for t in texts:
        if t is not None and t.get_text().strip():
            inside(t.get_text(), t.get_window_extent(r))
    titles = [(t.get_text(), t.get_window_extent(r)) for t in [fig._suptitle] + [a.title for a in fig.axes]
              if t is not None and t.get_text().strip()]
    for i, (ta, a) in enumerate(titles):
        for tb, b in titles[i + 1:]:
            assert not a.overlaps(b), (ta, tb)


# --------------------------------------------------------------------------------- the palette

def test_every_figure_module_imports_the_palette_and_defines_no_colours_of_its_own():
    modules = ["ev3dgs/demo.py", "ev3dgs/view/figure.py", "ev3dgs/view/server.py", "ev3dgs/view/data.py",
               "ev3dgs/calib/compare.py"]
    for m in modules:
        src = (ROOT / m).read_text()
        tree = ast.parse(src)
        imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module in (None, "")
                    or isinstance(n, ast.ImportFrom) and n.level and n.module is None for a in n.names}
        imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        assert "palette" in imported, m
        assert "ON blue" not in src and "OFF red" not in src and '"bwr"' not in src, m


def test_palette_is_on_red_off_blue():
    r, g, b = palette.ON_RGB
    assert r > 2 * max(g, b)
    r, g, b = palette.OFF_RGB
    assert b > 2 * max(r, g)
    assert palette.legend_text() == "ON red, OFF blue"
    cmap = palette.net_colormap()
    assert np.allclose(cmap(1.0)[:3], np.array(palette.ON_RGB) / 255)
    assert np.allclose(cmap(0.0)[:3], np.array(palette.OFF_RGB) / 255)
    assert np.allclose(cmap(0.5)[:3], 1.0, atol=1 / 255)


# ---------------------------------------------------------------------------------- windows

def test_event_window_is_the_exposure_when_it_has_events():
    exposure = np.array([[0, 500], [33_000, 33_500], [66_000, 66_500]])
    many = lambda a, b: 10_000                                   # noqa: E731
    assert data.event_window(exposure, 1, many, 346, 260) == (33_000, 33_500, "exposure, 0.50 ms")


def test_event_window_is_the_interval_to_the_next_frame_when_the_exposure_is_nearly_empty():
    exposure = np.array([[0, 500], [33_000, 33_500], [66_000, 66_500]])
    few = lambda a, b: 12 if b - a == 500 else 5000              # noqa: E731
    # 1 % of 346 x 260 is 899.6 events: 12 is too few
    assert data.event_window(exposure, 0, few, 346, 260) == (
        0, 33_000, "to the next frame, 33.0 ms (the 0.50 ms exposure holds 12 events)")
    # the last frame: as long as the interval before it
    assert data.event_window(exposure, 2, few, 346, 260)[:2] == (66_000, 99_000)


# ------------------------------------------------------------------------------- view --out

def test_view_figure_uses_the_palette_has_a_legend_and_titles_fit(scene_path, test_colours):
    from ev3dgs.view import figure

    c = data.load_scene(scene_path)
    fig = figure.draw(c, rows=3)
    img = _pixels(fig)
    assert _has(img, GREEN) > 20 and _has(img, MAGENTA) > 20
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert labels == ["ON event (brighter)", "OFF event (darker)"]
    texts = [t.get_text() for ax in fig.axes for t in (ax.title, ax.xaxis.label)]
    assert "events (ON red, OFF blue)" in texts
    assert any(t.endswith("exposure, 100.0 ms") for t in texts)
    assert "12 failed to register" in fig._suptitle.get_text()
    _texts_inside(fig)


def test_view_figure_long_title_wraps_inside(scene_path):
    from ev3dgs.view import figure

    c = data.load_scene(scene_path)
    c.scene.name = "a-very-long-scene-name-" * 8
    fig = figure.draw(c, rows=2)
    assert "\n" in fig._suptitle.get_text()
    _texts_inside(fig)


# ------------------------------------------------------------------------------ compare.png

def _compare_result(H=26, W=34, seed=0):
    rng = np.random.default_rng(seed)
    net_r = rng.integers(-5, 6, H * W)
    net_s = rng.integers(-5, 6, H * W)
    keep = np.ones(H * W, bool)
    blk = rng.integers(0, 50, 20)
    bins = np.geomspace(10, 1e6, 30)
    return {"recording": "/data/recordings/" + "a-long-folder-name/" * 6 + "street.aedat4",
            "height": H, "width": W, "_maps": (net_r, net_s, keep, blk, blk + 1),
            "count_maps": {"all": {"corr_pair_pixel": 0.4321, "corr_pair_block8": 0.8765}},
            "rate_over_time": {"t_s": [0, 1, 2], "real_hz": [1e3, 2e3, 1e3], "sim_hz": [1.1e3, 2e3, 1e3],
                               "corr": 0.9},
            "iei": {"bins_us": bins.tolist(), "real": rng.integers(0, 9, 29).tolist(),
                    "sim": rng.integers(0, 9, 29).tolist(), "ks_log10": 0.1},
            "frame_interval_ms": 33.0,
            "background": {"real_on_hz": 0.1, "real_off_hz": 0.2, "sim_on_hz": 0.1, "sim_off_hz": 0.2,
                           "static_pixels": 400}}


def test_compare_figure_uses_the_palette_and_titles_fit(test_colours):
    from ev3dgs.calib.compare import draw

    res = _compare_result()
    fig = draw(res, title=f"{res['recording']}: real vs simulated (calibrated.toml)")
    img = _pixels(fig)
    assert _has(img, GREEN, 2) > 20 and _has(img, MAGENTA, 2) > 20    # the count maps' extremes
    assert "more ON" in fig.axes[-1].get_ylabel() or any("more ON" in a.get_ylabel() for a in fig.axes)
    _texts_inside(fig)


# ------------------------------------------------------------------------------ browser

def test_browser_event_image_and_label_follow_the_palette(scene_path, test_colours):
    pytest.importorskip("viser")
    from ev3dgs.view.server import Viewer

    c = data.load_scene(scene_path)
    v = Viewer("127.0.0.1", 0)
    try:
        v.show_scene(c, select=1)
        img = np.asarray(v.event_image.image)
        assert _has(img, GREEN) > 0 and _has(img, MAGENTA) > 0
        assert v.event_image.label == "events (ON red, OFF blue)"
        assert "events shown: exposure, 100.0 ms" in v.caption.content
    finally:
        v.stop()


# --------------------------------------------------------------------------------- demo strips

def test_demo_strip_is_labelled_large_and_uses_the_palette(scene_path, test_colours):
    from ev3dgs import demo

    sc = schema.read(scene_path)
    strip = demo.view_strip(sc, 1)
    H, W = sc.camera.height, sc.camera.width
    k = -(-demo.STRIP_MIN_PANEL // W)
    assert strip.shape[1] > 300 and strip.shape[0] > 76
    assert strip.shape[1] >= 3 * k * W and strip.shape[0] >= k * H + 3 * demo._LINE
    # the sharp panel is the sharp frame, each pixel a k x k block (nearest neighbour)
    sharp = np.asarray(sc.train.sharp[1])
    big = np.repeat(np.repeat(sharp, k, 0), k, 1)
    found = _find(strip, big)
    assert found is not None
    assert _has(strip, GREEN) > 0 and _has(strip, MAGENTA) > 0       # events and legend
    # a label above every panel: dark text pixels in the rows between the title and the images
    y0 = found[0]
    labels = strip[demo._LINE + 4:y0]
    assert labels.size and (labels.min(-1) < 100).any()
    assert (strip[-demo._LINE:].min(-1) < 100).any()                  # the legend's words


def test_demo_strip_event_counts_are_the_window(scene_path):
    """The strip's event panel counts the events of view 1's exposure: the per-pixel count image equals an
    independent count of the scene's events in [start, end)."""
    from ev3dgs import demo

    sc = schema.read(scene_path)
    ev = sc.events.load()
    start, end = 1 * PERIOD_US, 1 * PERIOD_US + EXPOSURE_US
    sel = (ev.t >= start) & (ev.t < end)
    on, off = data.polarity_counts(ev.x[sel], ev.y[sel], ev.p[sel], sc.camera.width, sc.camera.height)
    expect = data.event_image(on, off)
    strip = demo.view_strip(sc, 1)
    k = -(-demo.STRIP_MIN_PANEL // sc.camera.width)
    big = np.repeat(np.repeat(expect, k, 0), k, 1)
    assert _find(strip, big) is not None
