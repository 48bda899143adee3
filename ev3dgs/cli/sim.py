"""ev3dgs-sim: event and blurry-frame simulation."""
from __future__ import annotations

import sys

from .calibrate import add_calibrate_parsers
from .common import add_output_options, dispatch, finite_float, parser, subparsers

PREFILTERS = ("accurate", "fast", "none")  # ev3dgs.sim.scenes.PREFILTERS, without importing the simulator here
RENDER_DEVICES = ("auto", "cpu", "cuda", "optix")  # ev3dgs.sim.scenes.RENDER_DEVICES, likewise
BLENDER_EXTRA = "pip install 'ev3dgs[blender]' (bpy 5.0.1, Python 3.11)"


def require_blender(command: str) -> None:
    """Fail at once (one line, exit 2) when bpy is not installed: `command` renders in Blender worker processes,
    which would otherwise fail only once spawned. Checked with find_spec: nothing here imports bpy."""
    import importlib.util

    from ..errors import ConfigError

    if importlib.util.find_spec("bpy") is None:
        major, minor = sys.version_info[:2]
        running = "" if (major, minor) == (3, 11) else f"; Python {major}.{minor} is running"
        raise ConfigError(f"{command} renders with Blender, which is not installed: {BLENDER_EXTRA}{running}")


def with_sensor_config(spec, config_path):
    """The scene with a sensor TOML (e.g. from `ev3dgs-sim calibrate`) in place of its [sensor] table: each
    table the TOML has ([dvs] with its effect tables, [isp], [sensor_noise]) replaces the scene's; the ones it
    lacks stay the scene's. Only the effects the resulting [dvs] names run."""
    import dataclasses

    from ..config import load_toml
    from ..sim.config import load_sim_config

    if config_path is None:
        return spec
    given = load_toml(config_path)
    cfg = load_sim_config(config_path)
    return dataclasses.replace(spec, sensor=dataclasses.replace(
        spec.sensor, **{k: getattr(cfg, k) for k in ("dvs", "isp", "sensor_noise") if k in given}))


def scene_toml(spec) -> str:
    """A SceneSpec as a scene TOML that load_scene reads back to the same spec."""
    from ..config import dumps_toml, to_dict

    return dumps_toml(to_dict(spec)) + "\n"


def _events(args) -> int:
    import numpy as np

    from .. import schema
    from ..sim import load_sim_config, simulate_events
    from ..sim.npz import load_frames_npz
    from ..sim.output import event_sensor, provenance

    from ..outputs import check_output_file

    # before simulating; schema.write checks the space it needs
    check_output_file(args.out, make_parents=True, force=args.force)
    from ..claims import claim_output
    claim_output(args.out, force=args.force)  # before any work
    cfg = load_sim_config(args.config)
    frames, t_us = load_frames_npz(args.input)
    ev = simulate_events(frames, t_us, cfg.dvs, seed=args.seed, isp=cfg.isp)
    H, W = frames.shape[1:3]
    scene = schema.Scene(
        name=args.input.rsplit("/", 1)[-1].removesuffix(".npz"), source="ev3dgs-sim events",
        camera=schema.Camera(width=W, height=H), events=ev, sensor=event_sensor(cfg.dvs, cfg.isp),
        config=provenance(cfg, seed=args.seed, input=args.input, frames=int(len(frames)),
                          time_range_us=[int(np.min(t_us)), int(np.max(t_us))]),
    )
    schema.write(scene, args.out)
    if not args.quiet:
        rep = ev.report
        effects = ", ".join(f"{k} {1e3 * rep.seconds.get(k, 0.0):.1f} ms" for k in rep.effects) or "none"
        print(f"{len(ev)} events ({ev.on_count} ON, {ev.off_count} OFF) from {len(frames)} frames "
              f"{W}x{H} in {1e3 * sum(rep.seconds.values()):.1f} ms; effects: {effects} -> {args.out}")
    return 0


def _blur(args) -> int:
    import cv2
    import numpy as np

    from ..errors import InputError
    from ..sim import load_sim_config
    from ..sim.blur import blur_frames
    from ..sim.npz import load_frames_npz
    from .common import write_atomic

    from ..outputs import check_output_file

    suffix = "." + args.out.rsplit(".", 1)[-1].lower() if "." in args.out else ""
    if suffix not in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        raise InputError(f"--out must end in .png, .jpg or .tif, got {args.out!r}")
    check_output_file(args.out, force=args.force, make_parents=True)
    from ..claims import claim_output
    claim_output(args.out, force=args.force)  # before any work
    cfg = load_sim_config(args.config)
    frames, _ = load_frames_npz(args.input, need_t=False)
    if frames.ndim == 3:
        frames = np.repeat(frames[..., None], 3, axis=-1)
    image = blur_frames(frames, cfg.isp, cfg.sensor_noise, seed=args.seed)
    ok, data = cv2.imencode(suffix, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not ok:
        raise InputError(f"could not encode {args.out}")
    write_atomic(args.out, data.tobytes())
    if not args.quiet:
        print(f"blurred {len(frames)} frames {image.shape[1]}x{image.shape[0]} in the raw domain -> {args.out}")
    return 0


def _size(text: str) -> tuple[int, int]:
    import argparse

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 400x300, got {text!r}") from None
    return w, h


def _make_dataset(args) -> int:
    if not (args.executor == "ray" and args.address):   # Ray actors on a cluster need bpy on its nodes only
        require_blender("make-dataset")
    from ..outputs import check_output_file
    from ..sim.dataset import make_dataset
    from ..sim.scenes import load_scene, resolve_render

    check_output_file(args.out, force=args.force, make_parents=True)   # before loading the scene and rendering
    from ..claims import claim_output
    claim_output(args.out, force=args.force)  # before Blender starts
    spec = with_sensor_config(load_scene(args.scene), args.config)
    w, h = args.size if args.size else (None, None)
    render = resolve_render(spec, args.quick, width=w, height=h, views=args.views, test_views=args.test_views,
                            subframes=args.subframes, exposure_ms=args.exposure_ms, samples=args.samples,
                            denoise_prefilter=args.denoise_prefilter, device=args.render_device)
    stats = make_dataset(spec, render, args.out, blend=args.blend, workers=args.workers, seed=args.seed,
                         quiet=args.quiet, keep_cache=args.keep_cache, executor=args.executor,
                         address=args.address, force=args.force)
    if not args.quiet:
        sec = stats.seconds
        print(f"{spec.name}: {render.views} views + {render.test_views} test views at {render.width}x{render.height}, "
              f"{render.subframes} sub-frames, {stats.events} events ({stats.views_rendered} views rendered, "
              f"{stats.views_cached} from cache); render {sec['render']:.1f} s, simulate {sec['simulate']:.2f} s, "
              f"ISP {sec['isp']:.2f} s, write {sec['write']:.2f} s; "
              f"{f'rendered on {stats.render_device}' if stats.render_device else 'nothing rendered'} -> {stats.path}")
    return 0


def _record(args) -> int:
    from pathlib import Path

    require_blender("record")
    from ..sim.record import record

    from ..claims import claim_output
    from ..sim.record import outputs as record_outputs

    for option, path in record_outputs(args.out).items():  # all four, before Blender starts
        claim_output(path, force=args.force, option=option)
    w, h = args.size if args.size else (346, 260)
    scene = args.scene
    tmp = None
    if args.config:   # the scene with the sensor TOML in place of its [sensor] tables, as a scene file
        import tempfile

        from ..sim.scenes import load_scene

        spec = with_sensor_config(load_scene(args.scene), args.config)
        tmp = tempfile.TemporaryDirectory(prefix="ev3dgs-record-")
        scene = str(Path(tmp.name) / f"{spec.name}.toml")
        Path(scene).write_text(scene_toml(spec), encoding="utf-8")
    # record checks its outputs (the .aedat4, its .trajectory.npz, .calibration.toml, .sensor.toml) before rendering
    try:
        info = record(scene, args.out, seconds=args.seconds, fps=args.fps, exposure_ms=args.exposure_ms,
                      render_rate_hz=args.render_rate, width=w, height=h, samples=args.samples, seed=args.seed,
                      workers=args.workers, quiet=args.quiet, denoise_prefilter=args.denoise_prefilter,
                      force=args.force)
    finally:
        if tmp is not None:
            tmp.cleanup()
    if not args.quiet:
        print(f"{info['frames']} APS frames, {info['events']} events, {info['imu']} IMU samples over "
              f"{args.seconds} s -> {args.out} (+ ground truth {Path(info['trajectory']).name} and "
              f"{Path(args.out).stem}.calibration.toml, {Path(args.out).stem}.sensor.toml)")
    return 0


def _list_scenes(args) -> int:
    from ..sim.scenes import builtin_scenes, load_scene

    names = builtin_scenes()
    for n in names:
        print(n)
    print()
    for n in names:
        print(f"{n}: {load_scene(n).description}")
    return 0


def build_parser():
    p = parser("ev3dgs-sim", "Simulate event cameras: events and raw-domain motion blur from frames.")
    sub = subparsers(p)
    e = sub.add_parser("events", help="frames (.npz: frames, t_us) -> events in a scene file (.h5)")
    e.add_argument("input", help=".npz with frames (T,H,W[,3]) float linear (1.0 = white) and t_us (T,) int64")
    e.add_argument("--out", required=True, help="output .h5 (written atomically)")
    e.add_argument("--config", help="TOML with [dvs] settings and effect tables, see ev3dgs.sim.config "
                                    "(default: none, the built-in DVS346-like settings)")
    e.add_argument("--seed", type=int, default=0, help="random seed of the noise effects (default %(default)s)")
    add_output_options(e)
    e.set_defaults(func=_events)
    b = sub.add_parser("blur", help="sub-frames (.npz: frames) -> one blurry sRGB image")
    b.add_argument("input", help=".npz with frames (S,H,W,3): uint8 sRGB or float linear")
    b.add_argument("--out", required=True, help="output image (.png/.jpg/.tif, written atomically)")
    b.add_argument("--config", help="TOML with [isp] and [sensor_noise] tables "
                                    "(default: none, the built-in ISP and noise)")
    b.add_argument("--seed", type=int, default=0, help="random seed of the sensor noise (default %(default)s)")
    add_output_options(b)
    b.set_defaults(func=_blur)
    m = sub.add_parser("make-dataset", help="render a scene in Blender -> events + blurry frames -> scene.h5 "
                                            "(needs the Blender extra: pip install 'ev3dgs[blender]')")
    m.add_argument("--scene", required=True, help="built-in scene name (see list-scenes) or a scene .toml")
    m.add_argument("--blend", help="render this .blend (an object near the origin) with our cameras "
                                       "(default: none, the scene's builder makes the geometry)")
    m.add_argument("--out", required=True, help="output scene .h5 (written atomically)")
    m.add_argument("--config", help="sensor TOML ([dvs] and effect tables, [isp], [sensor_noise]), e.g. from "
                                    "`ev3dgs-sim calibrate`: each table it has replaces the scene's [sensor] one "
                                    "(default: none, the scene's sensor)")
    m.add_argument("--views", type=int, help="training views (default: the scene's, 24 for built-ins; 4 with --quick)")
    m.add_argument("--test-views", type=int,
                   help="sharp novel test views (default: the scene's, 6 for built-ins; 2 with --quick)")
    m.add_argument("--size", type=_size, help="image size WxH in pixels (default: the scene's; 96x72 with --quick)")
    m.add_argument("--subframes", type=int,
                   help="sub-frames rendered per exposure (default: the scene's, 17 for built-ins)")
    m.add_argument("--exposure-ms", type=finite_float,
                   help="exposure time in milliseconds (default: the scene's, 100 ms for built-ins)")
    m.add_argument("--samples", type=int,
                   help="Cycles samples per pixel (default: the scene's, 64 for built-ins; 16 with --quick)")
    m.add_argument("--denoise-prefilter", choices=PREFILTERS,
                   help="OpenImageDenoise's albedo/normal guide prefilter (default: the scene's, accurate for "
                        "built-ins; fast with --quick)")
    m.add_argument("--render-device", choices=RENDER_DEVICES,
                   help="where Cycles renders: auto (a CUDA, then an OptiX GPU when Cycles finds one, else the "
                        "CPU; the summary says which), cpu, cuda or optix (an error when Cycles finds none) "
                        "(default: the scene's, auto for built-ins)")
    m.add_argument("--workers", type=int, default=1,
                   help="Blender processes (or Ray actors) rendering in parallel (default %(default)s)")
    m.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="where the Blender workers run: local processes, or Ray actors (needs ev3dgs[ray]) "
                        "(default %(default)s)")
    m.add_argument("--address", help="Ray cluster address (HEAD:6379, auto, ray://HEAD:10001); "
                                     "default: a local Ray instance. Only with --executor ray")
    m.add_argument("--seed", type=int, default=0, help="random seed of the camera shake, views and noise "
                                                      "(default %(default)s)")
    m.add_argument("--quick", action="store_true",
                   help="small images (96x72), 4 views, 16 samples with OIDN's fast prefilter: minutes on 2 cores "
                        "(default: off)")
    m.add_argument("--keep-cache", action="store_true",
                   help="keep the rendered views beside the output (default: off, removed once the "
                        "scene file is written)")
    add_output_options(m)
    m.set_defaults(func=_make_dataset)
    r = sub.add_parser("record", help="a DAVIS346-like AEDAT 4.0 recording of a scene along a hand-held path "
                                      "(needs the Blender extra: pip install 'ev3dgs[blender]')")
    r.add_argument("--scene", required=True, help="built-in scene name or a scene .toml")
    r.add_argument("--out", required=True,
                   help="output .aedat4; the ground truth goes beside it as NAME.trajectory.npz, "
                        "NAME.calibration.toml and NAME.sensor.toml (the simulated sensor, for "
                        "`ev3dgs-ingest davis --sensor`) (no default)")
    r.add_argument("--config", help="sensor TOML ([dvs] and effect tables, [isp], [sensor_noise]), e.g. from "
                                    "`ev3dgs-sim calibrate`: each table it has replaces the scene's [sensor] one "
                                    "(default: none, the scene's sensor)")
    r.add_argument("--seconds", type=finite_float, default=2.0,
                   help="length of the recording in seconds (default %(default)s s)")
    r.add_argument("--fps", type=finite_float, default=10.0, help="APS frames per second (default %(default)s)")
    r.add_argument("--exposure-ms", type=finite_float, default=50.0,
                   help="APS exposure time in milliseconds (default %(default)s ms)")
    r.add_argument("--render-rate", type=finite_float, default=250.0,
                   help="rendered frames per second, the event simulator's input (default %(default)s)")
    r.add_argument("--size", type=_size, help="sensor size WxH (default 346x260)")
    r.add_argument("--samples", type=int, default=8, help="Cycles samples per pixel (default %(default)s)")
    r.add_argument("--denoise-prefilter", choices=PREFILTERS,
                   help="OpenImageDenoise's albedo/normal guide prefilter (default: the scene's, accurate for "
                        "built-ins; at 346x260 '--samples 16 --denoise-prefilter fast' renders ~1.5x faster and "
                        "closer to a converged render, see the render study in the docs: docs/studies.md)")
    r.add_argument("--workers", type=int, default=1, help="Blender processes rendering in parallel "
                                                         "(default %(default)s)")
    r.add_argument("--seed", type=int, default=0, help="random seed of the hand-held path and noise "
                                                      "(default %(default)s)")
    add_output_options(r)
    r.set_defaults(func=_record)
    add_calibrate_parsers(sub)
    ls = sub.add_parser("list-scenes", help="the built-in scenes: names first, then descriptions")
    ls.set_defaults(func=_list_scenes)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
