"""Scene definitions for `ev3dgs-sim make-dataset`: TOML files naming a builder, its parameters, the render
settings, the camera shake and the sensor effects the scene calls for (only those run).

```toml
name = "lego"
description = "one line"
builder = "lego"              # a procedural builder in ev3dgs_blender.builders (absent with --blend)
[params]                      # passed to the builder, which rejects unknown keys
[render]                      # see Render
[shake]                       # see ev3dgs_blender.shake.Shake
[sensor]                      # a SimConfig: [sensor.dvs], [sensor.dvs.<effect>], [sensor.isp], [sensor.sensor_noise]
```
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from ..config import check, from_dict, load_toml
from ..errors import ConfigError
from .config import SimConfig

SCENES_DIR = Path(__file__).resolve().parent / "builtin_scenes"  # package data: ships in the wheel
MAX_SIZE = 8192
PREFILTERS = ("accurate", "fast", "none")
# where Cycles renders: "auto" (a CUDA or OptiX GPU when Cycles finds one, else the CPU), or that device
RENDER_DEVICES = ("auto", "cpu", "cuda", "optix")


@dataclass(frozen=True)
class Render:
    width: int = 400
    height: int = 300
    fov_deg: float = 40.0             # horizontal field of view
    samples: int = 64                 # Cycles samples per pixel
    denoise: bool = True              # OpenImageDenoise
    denoise_prefilter: str = "accurate"  # OIDN's albedo/normal guides: "accurate" (denoised first), "fast", "none"
    device: str = "auto"              # Cycles' device, RENDER_DEVICES (not part of the render cache's key)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # linear RGB, stored in the schema
    views: int = 24                   # training views (blurry frame + events + sharp frame each)
    test_views: int = 6               # sharp novel views
    subframes: int = 17               # rendered per exposure, evenly, both ends included
    exposure_ms: float = 100.0        # DAVIS346 setting of the paper
    gap_ms: float = 50.0              # time between one exposure's end and the next one's start
    radius: float = 4.0               # camera distance from the origin
    elevation_deg: tuple[float, float] = (15.0, 60.0)   # views spread over this band of the hemisphere

    def __post_init__(self):
        check(8 <= self.width <= MAX_SIZE and 8 <= self.height <= MAX_SIZE,
              f"render size must be between 8 and {MAX_SIZE} pixels per side, got {self.width}x{self.height}")
        check(1 <= self.fov_deg <= 170, "render.fov_deg must be in [1, 170]")
        check(1 <= self.samples <= 1 << 16, "render.samples must be in [1, 65536]")
        check(self.denoise_prefilter in PREFILTERS,
              f"render.denoise_prefilter must be one of {', '.join(PREFILTERS)}, got {self.denoise_prefilter!r}")
        check(self.device in RENDER_DEVICES,
              f"render.device must be one of {', '.join(RENDER_DEVICES)}, got {self.device!r}")
        check(all(0 <= c <= 1 for c in self.background), "render.background values must be in [0, 1]")
        check(1 <= self.views <= 10000, "render.views must be in [1, 10000]")
        check(0 <= self.test_views <= 10000, "render.test_views must be in [0, 10000]")
        check(2 <= self.subframes <= 1025, "render.subframes must be in [2, 1025]")
        check(0.01 <= self.exposure_ms <= 10000, "render.exposure_ms must be in [0.01, 10000]")
        check(0 <= self.gap_ms <= 1e6, "render.gap_ms must be >= 0")
        check(self.radius > 0, "render.radius must be > 0")
        lo, hi = self.elevation_deg
        check(-90 <= lo <= hi <= 90, "render.elevation_deg must be [low, high] within [-90, 90]")


@dataclass(frozen=True)
class ShakeSpec:
    rotation_deg: float = 1.0
    translation: float = 0.01
    min_hz: float = 2.0
    max_hz: float = 8.0
    components: int = 3

    def __post_init__(self):
        check(0 <= self.rotation_deg <= 45, "shake.rotation_deg must be in [0, 45]")
        check(self.translation >= 0, "shake.translation must be >= 0")
        check(0 < self.min_hz <= self.max_hz <= 1e4, "shake needs 0 < min_hz <= max_hz")
        check(1 <= self.components <= 16, "shake.components must be in [1, 16]")


@dataclass(frozen=True)
class SceneSpec:
    name: str
    description: str = ""
    builder: str | None = None
    params: dict = field(default_factory=dict)
    render: Render = field(default_factory=Render)
    shake: ShakeSpec = field(default_factory=ShakeSpec)
    sensor: SimConfig = field(default_factory=SimConfig)
    quick: dict = field(default_factory=dict)  # [quick]: render overrides for --quick

    def __post_init__(self):
        check(bool(self.name.strip()), "name must not be empty")
        try:
            dataclasses.replace(self.render, **self.quick)
        except (TypeError, ConfigError) as e:
            raise ConfigError(f"quick: {e}") from None


# --quick: small, few samples, and OIDN's fast guide prefilter (at 96x72 the accurate one's two extra filter
# runs cost ~0.13 s of a 0.18 s frame; tools/studies/study_render.py measures what each costs in PSNR)
QUICK = dict(width=96, height=72, samples=16, views=4, test_views=2, denoise_prefilter="fast")


def load_scene(name_or_path: str) -> SceneSpec:
    """A built-in scene by name, or a TOML file by path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = SCENES_DIR / f"{name_or_path}.toml"
        if not path.is_file():
            raise ConfigError(f"unknown scene {name_or_path!r} (built-in: {', '.join(builtin_scenes())})")
    data = load_toml(path)
    try:
        return from_dict(SceneSpec, data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    except TypeError as e:  # a missing required key such as `name`
        raise ConfigError(f"{path}: {e}") from None


def builtin_scenes() -> list[str]:
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def resolve_render(spec: SceneSpec, quick: bool = False, **overrides) -> Render:
    """The scene's render settings, with the --quick preset and command-line overrides (None = keep)."""
    r = spec.render
    if quick:
        r = dataclasses.replace(r, **{**QUICK, **spec.quick})
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        return dataclasses.replace(r, **given)
    except TypeError as e:
        raise ConfigError(str(e)) from None
