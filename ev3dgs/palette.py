"""The one colour convention of every figure that shows events: ON (brighter) events red, OFF (darker) events
blue, no event white, as DV's and most event-vision papers' red/blue pictures; and titles that fit their figure.

Read by the demo strips (ev3dgs/demo.py), `ev3dgs view --out` (view/figure.py), the browser viewer
(view/server.py, through view/data.event_image) and `ev3dgs-sim compare`'s compare.png (calib/compare.py).
Figures look the colours up when they draw (``palette.ON_RGB``, not a copy taken at import), so a test can
check that every figure follows this module."""
from __future__ import annotations

ON_RGB = (220, 40, 40)          # red
OFF_RGB = (40, 60, 220)         # blue
BACKGROUND_RGB = (255, 255, 255)

ON_NAME, OFF_NAME = "red", "blue"


def legend_text() -> str:
    """"ON red, OFF blue": the words every figure's legend or label uses."""
    return f"ON {ON_NAME}, OFF {OFF_NAME}"


def hex_colour(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def net_colormap():
    """A matplotlib colormap for ON minus OFF counts: OFF_RGB at the low end, white at 0, ON_RGB at the high
    end (use it with a range symmetric about 0)."""
    from matplotlib.colors import LinearSegmentedColormap

    return LinearSegmentedColormap.from_list(
        "ev3dgs_polarity", [tuple(c / 255 for c in OFF_RGB), tuple(c / 255 for c in BACKGROUND_RGB),
                            tuple(c / 255 for c in ON_RGB)])


def legend_handles():
    """Two matplotlib patches, ON and OFF, for ``fig.legend(handles=...)``."""
    from matplotlib.patches import Patch

    return [Patch(facecolor=hex_colour(ON_RGB), edgecolor="0.3", label="ON event (brighter)"),
            Patch(facecolor=hex_colour(OFF_RGB), edgecolor="0.3", label="OFF event (darker)")]


def fit_suptitle(fig, text: str, fontsize: float = 9, margin: float = 0.98):
    """Set `text` as the figure's title, wrapped onto as many lines as it needs to lie inside the figure's
    width (times `margin`), measured with the figure's renderer; returns the Text."""
    import textwrap

    renderer = fig.canvas.get_renderer()
    limit = fig.bbox.width * margin
    title = fig.suptitle(text, fontsize=fontsize)
    width = len(text)
    while title.get_window_extent(renderer).width > limit and width > 20:
        width = int(width * 0.9)
        title.set_text("\n".join(textwrap.wrap(text, width, break_long_words=True)))
    return title
