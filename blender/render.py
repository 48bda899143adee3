"""Render worker API (runs inside a process that imports bpy).

    init_scene(builder, params, blend_path, width, height, K, samples, denoise, background, seed,
               denoise_prefilter) -> dict
    render(c2w_opencv (n, 4, 4)) -> (frames float32 (n, H, W, 3) linear RGB, poses float64 (n, 4, 4))

Camera model. Blender's camera with sensor_fit HORIZONTAL and sensor width S has fx = lens * W / S pixels, and
its shift is measured in units of the image WIDTH for both axes (the fit dimension). With zero shift the optical
axis hits Blender's image centre, continuous coordinate W/2 (pixel i spans [i, i+1]), i.e. OpenCV coordinate
(W - 1) / 2. A positive shift_x moves the view window right (the axis appears further left), a positive
shift_y moves it up (Blender image y points up, so the axis appears further DOWN in a top-down image):
    shift_x = -(cx + 0.5 - W/2) / W,        shift_y = (cy + 0.5 - H/2) / W
(verified by tests/test_blender.py::test_projection, which renders a tiny emissive sphere).
"""
from __future__ import annotations

import os
import tempfile

import bpy
import numpy as np
from mathutils import Matrix

from ev3dgs.geometry import blender_to_opencv, opencv_to_blender
from ev3dgs.sim.scenes import PREFILTERS, RENDER_DEVICES

from . import builders

_STATE: dict = {}


def camera_shift(K, width: int, height: int) -> tuple[float, float]:
    """Blender (shift_x, shift_y) honouring the principal point of K (OpenCV pixel convention)."""
    K = np.asarray(K, dtype=np.float64)
    return -(K[0, 2] + 0.5 - width / 2) / width, (K[1, 2] + 0.5 - height / 2) / width


def _setup_world(background) -> None:
    world = bpy.data.worlds.new("ev3dgs_world")
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (*[float(c) for c in background[:3]], 1.0)
    bg.inputs["Strength"].default_value = 1.0
    bpy.context.scene.world = world


def _setup_render(width, height, samples, denoise, seed, prefilter="accurate") -> None:
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = int(samples)
    cy.use_adaptive_sampling = False  # same noise pattern everywhere, every frame
    cy.seed = int(seed)
    cy.use_animated_seed = False  # fixed Monte-Carlo pattern across sub-frames: no spurious events
    cy.use_denoising = bool(denoise)
    if denoise:
        cy.denoiser = "OPENIMAGEDENOISE"
        # how OIDN treats its albedo and normal guides: "accurate" denoises them first (two more filter runs,
        # whose set-up dominates at small sizes: ~0.13 s a frame at 96x72), "fast" uses them as rendered
        cy.denoising_prefilter = prefilter.upper()  # Cycles' enum: ACCURATE, FAST, NONE
    cy.use_preview_denoising = False
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = int(width), int(height), 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = False
    r.use_border = False
    r.use_motion_blur = False
    r.use_compositing = False
    r.use_sequencer = False
    # Cycles keeps its session, scene and BVH from one render to the next: only the camera moves between frames,
    # so each frame skips the session set-up, scene sync and tear-down (about 5 % of a frame's CPU time at
    # 173x130, 8 spp: tools/bench/bench_record_render.py); the frames are bit-identical
    # (tests/test_blender.py::test_persistent_data_same_frames)
    r.use_persistent_data = True
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    im = r.image_settings
    im.file_format = "OPEN_EXR"
    im.color_depth = "32"
    im.color_mode = "RGBA"
    im.exr_codec = "NONE"


# what --render-device auto tries, in order: CUDA first (Blender ships CUDA kernels for every recent NVIDIA
# architecture), then OptiX
AUTO_KINDS = ("CUDA", "OPTIX")


def _cycles_preferences():
    return bpy.context.preferences.addons["cycles"].preferences


def setup_device(device: str = "auto") -> str:
    """Point Cycles at a device: "cpu"; "cuda" or "optix" (that kind's GPUs, the CPU left out; RuntimeError when
    Cycles finds none); "auto" (AUTO_KINDS in order, the first that Cycles finds, else the CPU). Sets the Cycles
    add-on's compute_device_type and the scene's cycles.device; returns the device used ("cpu", "cuda",
    "optix"). Call after read_factory_settings (which resets the preferences)."""
    if device not in RENDER_DEVICES:
        raise ValueError(f"render device must be one of {', '.join(RENDER_DEVICES)}, got {device!r}")
    scene = bpy.context.scene
    prefs = _cycles_preferences()
    for kind in (() if device == "cpu" else AUTO_KINDS if device == "auto" else (device.upper(),)):
        try:
            found = [d for d in prefs.get_devices_for_type(kind) if d.type == kind]
        except (TypeError, ValueError):  # a Blender built without this kind
            found = []
        if found:
            prefs.compute_device_type = kind
            for d in prefs.get_devices_for_type(kind):
                d.use = d.type == kind
            scene.cycles.device = "GPU"
            return kind.lower()
        if device != "auto":
            raise RuntimeError(f"Cycles finds no {kind} device (render device {device!r}; 'auto' falls back to "
                               "the CPU)")
    prefs.compute_device_type = "NONE"
    scene.cycles.device = "CPU"
    return "cpu"


def _setup_camera(K, width, height):
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    fx, fy = K[0, 0], K[1, 1]
    if abs(fx - fy) > 1e-6 * fx or abs(K[0, 1]) > 1e-9:
        raise ValueError("Blender cameras need square pixels and zero skew (fx == fy, K[0,1] == 0)")
    cam = bpy.data.cameras.new("ev3dgs_camera")
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = 36.0
    cam.lens_unit = "MILLIMETERS"
    cam.lens = fx * 36.0 / width
    cam.shift_x, cam.shift_y = camera_shift(K, width, height)
    cam.clip_start, cam.clip_end = 0.01, 1000.0
    cam.dof.use_dof = False
    obj = bpy.data.objects.new("ev3dgs_camera", cam)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj
    return obj


def init_scene(builder: str | None, params: dict | None, blend_path: str | None, width: int, height: int,
               K, samples: int = 16, denoise: bool = False, background=(0.05, 0.05, 0.05), seed: int = 0,
               denoise_prefilter: str = "accurate", render_device: str = "cpu") -> dict:
    """Reset bpy and set up the scene, renderer and our camera. builder None and blend_path None gives an
    EMPTY scene (world only; used by tests). denoise_prefilter: OIDN's guide prefilter, "accurate", "fast"
    or "none" (only with denoise). render_device: see setup_device. Returns {"bounds": (2,3) list, "K": 3x3 list,
    "build": info, "render_device": the device Cycles renders on}."""
    if builder is not None and blend_path is not None:
        raise ValueError("give either a builder or a blend_path, not both")
    if denoise_prefilter not in PREFILTERS:
        raise ValueError(f"denoise_prefilter must be one of {', '.join(PREFILTERS)}, got {denoise_prefilter!r}")
    if render_device not in RENDER_DEVICES:
        raise ValueError(f"render_device must be one of {', '.join(RENDER_DEVICES)}, got {render_device!r}")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    info: dict = {}
    if blend_path is not None:
        if not os.path.isfile(blend_path):
            raise FileNotFoundError(blend_path)
        bpy.ops.wm.open_mainfile(filepath=os.path.abspath(blend_path), load_ui=False)
        scene = bpy.context.scene
        scene.camera = None  # the file's own cameras are left alone but not used
        # render only the current frame of the file's animation as it stands
        bpy.context.view_layer.update()
        bounds = builders.mesh_bounds([o for o in scene.objects if o.type == "MESH" and not o.hide_render])
    elif builder is not None:
        info = builders.build(builder, params or {}, seed)
        bounds = info["bounds"]
    else:
        if params:
            raise ValueError(f"params given for an empty scene: {sorted(params)}")
        bounds = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    _setup_render(width, height, samples, denoise, seed, denoise_prefilter)
    used = setup_device(render_device)
    _setup_world(background)
    cam = _setup_camera(K, width, height)
    _STATE.clear()
    _STATE.update(camera=cam, width=int(width), height=int(height), K=np.asarray(K, dtype=np.float64).copy(),
                  background=tuple(float(c) for c in background[:3]))
    bpy.context.view_layer.update()
    return {"bounds": bounds, "K": np.asarray(K, dtype=np.float64).tolist(), "build": info, "render_device": used}


def render(c2w_opencv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Render one frame per OpenCV camera-to-world pose. Returns (frames (n,H,W,3) float32 linear RGB, row 0 at
    the top; poses (n,4,4) float64 as read back from Blender after the update)."""
    if not _STATE:
        raise RuntimeError("init_scene() must be called before render()")
    poses = np.asarray(c2w_opencv, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (n, 4, 4), got {poses.shape}")
    scene, cam = bpy.context.scene, _STATE["camera"]
    W, H = _STATE["width"], _STATE["height"]
    frames = np.empty((len(poses), H, W, 3), np.float32)
    out_poses = np.empty((len(poses), 4, 4), np.float64)
    buf = np.empty(W * H * 4, np.float32)
    with tempfile.TemporaryDirectory(prefix="ev3dgs_render_") as td:
        for i, pose in enumerate(poses):
            cam.matrix_world = Matrix(opencv_to_blender(pose).tolist())
            bpy.context.view_layer.update()
            out_poses[i] = blender_to_opencv(np.array(cam.matrix_world))
            path = os.path.join(td, f"frame_{i:05d}.exr")
            scene.render.filepath = path
            bpy.ops.render.render(write_still=True)
            img = bpy.data.images.load(path, check_existing=False)
            try:
                if tuple(img.size) != (W, H) or img.channels != 4:
                    raise RuntimeError(f"unexpected render {tuple(img.size)}x{img.channels}")
                img.pixels.foreach_get(buf)
            finally:
                bpy.data.images.remove(img)
            os.remove(path)
            frames[i] = buf.reshape(H, W, 4)[::-1, :, :3]
    return frames, out_poses
