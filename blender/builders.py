"""Procedural scenes in the spirit of the NeRF-synthetic set, built with bpy into the current (empty) scene.

Every builder makes an object near the origin that fits in a sphere of radius ~1.2 (world = Blender's, z up),
textured with NON-repeating procedural noise (Noise / Voronoi textures in object space with random offsets
from the seed) so that SIFT / structure-from-motion finds features, and sets up its own lights.
`build(name, params, seed)` is deterministic for a given seed.
"""
from __future__ import annotations

import math
import random

import bmesh
import bpy
import numpy as np
from mathutils import Matrix, Vector

BUILDER_NAMES = ("lego", "ficus", "materials", "lowlight")
DESCRIPTIONS = {
    "lego": "blocky vehicle of many studded bricks of several sizes with a fine, high-contrast noise texture",
    "ficus": "potted plant: a stem with many thin branches and small leaves (thin structures)",
    "materials": "metallic and glossy spheres/tori on a noise-textured base plate (view-dependent shading)",
    "lowlight": "a textured still life lit by one weak light (mean linear intensity ~0.02-0.05; sensor noise)",
}
# documented defaults: detail = number of parts (bricks / branches / objects / rocks), texture_scale
# multiplies the noise frequency, light_strength multiplies every light's power
DEFAULTS = {
    "lego": {"detail": 24, "texture_scale": 1.0, "light_strength": 1.0},
    "ficus": {"detail": 26, "texture_scale": 1.0, "light_strength": 1.0},
    "materials": {"detail": 7, "texture_scale": 1.0, "light_strength": 1.0},
    "lowlight": {"detail": 6, "texture_scale": 1.0, "light_strength": 1.0},
}


# ---------------------------------------------------------------------------------------------- geometry
class _Geo:
    """Accumulates primitives into one bmesh; `finish` turns it into one object with one material."""

    def __init__(self):
        self.bm = bmesh.new()

    def box(self, center, size, rot=None):
        m = Matrix.Translation(center) @ (rot or Matrix.Identity(4)) @ Matrix.Diagonal((*size, 1.0))
        bmesh.ops.create_cube(self.bm, size=1.0, matrix=m)

    def cylinder(self, p0, p1, r0, r1=None, segments=8):
        p0, p1 = Vector(p0), Vector(p1)
        d = p1 - p0
        rot = d.to_track_quat("Z", "Y").to_matrix().to_4x4()
        m = Matrix.Translation((p0 + p1) / 2) @ rot
        bmesh.ops.create_cone(self.bm, cap_ends=True, segments=segments, radius1=r0,
                              radius2=r0 if r1 is None else r1, depth=d.length, matrix=m)

    def sphere(self, center, radius, scale=(1.0, 1.0, 1.0), rot=None, subdiv=2):
        m = Matrix.Translation(center) @ (rot or Matrix.Identity(4)) @ Matrix.Diagonal((*scale, 1.0))
        bmesh.ops.create_icosphere(self.bm, subdivisions=subdiv, radius=radius, matrix=m)

    def uvsphere(self, center, radius, segments=48):
        bmesh.ops.create_uvsphere(self.bm, u_segments=segments, v_segments=segments // 2, radius=radius,
                                  matrix=Matrix.Translation(center))

    def torus(self, center, major, minor, rot=None, n_major=48, n_minor=16):
        verts = []
        m = Matrix.Translation(center) @ (rot or Matrix.Identity(4))
        for i in range(n_major):
            a = 2 * math.pi * i / n_major
            for j in range(n_minor):
                b = 2 * math.pi * j / n_minor
                rr = major + minor * math.cos(b)
                verts.append(self.bm.verts.new(m @ Vector((rr * math.cos(a), rr * math.sin(a), minor * math.sin(b)))))
        for i in range(n_major):
            for j in range(n_minor):
                i2, j2 = (i + 1) % n_major, (j + 1) % n_minor
                self.bm.faces.new((verts[i * n_minor + j], verts[i2 * n_minor + j],
                                   verts[i2 * n_minor + j2], verts[i * n_minor + j2]))

    def finish(self, name, material, smooth=False):
        mesh = bpy.data.meshes.new(name)
        self.bm.to_mesh(mesh)
        self.bm.free()
        if smooth:
            mesh.shade_smooth()
        mesh.materials.append(material)
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        return obj


# ---------------------------------------------------------------------------------------------- materials
def _material(name, *, metallic=0.0, roughness=0.5, color=(0.8, 0.8, 0.8), coat=0.0):
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Coat Weight"].default_value = coat
    return mat, nt, bsdf


def _noise_material(name, rng, c0, c1, scale, *, roughness=0.55, metallic=0.0, spots=0.75, bump=0.15):
    """Principled BSDF whose base colour is 3D fBm noise (object space, random offset) pushed through a
    steep colour ramp c0 -> c1, multiplied by dark Voronoi spots (strength `spots`) for extra contrast."""
    mat, nt, bsdf = _material(name, metallic=metallic, roughness=roughness)
    n = nt.nodes
    coord = n.new("ShaderNodeTexCoord")
    mapping = n.new("ShaderNodeMapping")
    mapping.inputs["Location"].default_value = [rng.uniform(-100, 100) for _ in range(3)]
    mapping.inputs["Rotation"].default_value = [rng.uniform(0, 2 * math.pi) for _ in range(3)]
    nt.links.new(coord.outputs["Object"], mapping.inputs["Vector"])
    noise = n.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = scale
    noise.inputs["Detail"].default_value = 8.0
    noise.inputs["Roughness"].default_value = 0.62
    noise.inputs["Distortion"].default_value = rng.uniform(0.0, 0.6)
    nt.links.new(mapping.outputs["Vector"], noise.inputs["Vector"])
    ramp = n.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].position, ramp.color_ramp.elements[1].position = 0.38, 0.62
    ramp.color_ramp.elements[0].color, ramp.color_ramp.elements[1].color = (*c0, 1.0), (*c1, 1.0)
    nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    vor = n.new("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = scale * 0.8
    vor.inputs["Randomness"].default_value = 1.0
    nt.links.new(mapping.outputs["Vector"], vor.inputs["Vector"])
    vramp = n.new("ShaderNodeValToRGB")
    vramp.color_ramp.elements[0].position, vramp.color_ramp.elements[1].position = 0.05, 0.25
    vramp.color_ramp.elements[0].color = (1 - spots, 1 - spots, 1 - spots, 1.0)
    nt.links.new(vor.outputs["Distance"], vramp.inputs["Fac"])
    mix = n.new("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    nt.links.new(ramp.outputs["Color"], mix.inputs["A"])
    nt.links.new(vramp.outputs["Color"], mix.inputs["B"])
    nt.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    if bump > 0:
        bmp = n.new("ShaderNodeBump")
        bmp.inputs["Strength"].default_value = bump
        nt.links.new(noise.outputs["Fac"], bmp.inputs["Height"])
        nt.links.new(bmp.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


# ---------------------------------------------------------------------------------------------- lights
def _sun(strength, rot_euler, angle_deg=3.0):
    light = bpy.data.lights.new("sun", "SUN")
    light.energy, light.angle = strength, math.radians(angle_deg)
    obj = bpy.data.objects.new("sun", light)
    obj.rotation_euler = rot_euler
    bpy.context.scene.collection.objects.link(obj)
    return {"type": "SUN", "strength": strength, "rotation": list(rot_euler)}


def _area(power, location, size=1.0, target=(0.0, 0.0, 0.0), kind="AREA"):
    light = bpy.data.lights.new(kind.lower(), kind)
    light.energy = power
    if kind == "AREA":
        light.size = size
    else:
        light.shadow_soft_size = size
    obj = bpy.data.objects.new(kind.lower(), light)
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(obj)
    return {"type": kind, "power": power, "location": list(location)}


def _studio(ls):
    return [_sun(3.0 * ls, (math.radians(40), math.radians(10), math.radians(35))),
            _area(250.0 * ls, (-3.0, -2.5, 2.0), size=2.0), _area(120.0 * ls, (2.5, 3.0, 1.0), size=2.0)]


# ---------------------------------------------------------------------------------------------- builders
def _lego(p, rng):
    ts = p["texture_scale"]
    pal = {"red": ((0.35, 0.01, 0.01), (0.9, 0.12, 0.05)), "yellow": ((0.45, 0.25, 0.0), (1.0, 0.8, 0.1)),
           "blue": ((0.0, 0.03, 0.25), (0.15, 0.35, 0.95)), "gray": ((0.08, 0.08, 0.09), (0.75, 0.75, 0.72))}
    geos = {k: _Geo() for k in pal}
    pitch, bh, sh, sr = 0.1, 0.12, 0.035, 0.03
    nx, ny, z0 = 16, 10, -0.18  # base plate of 16 x 10 studs, top at z0
    geos["gray"].box((0, 0, z0 - 0.06), (nx * pitch, ny * pitch, 0.12))
    height = np.full((nx, ny), z0)

    def studs(geo, i0, j0, w, d, ztop):
        for i in range(i0, i0 + w):
            for j in range(j0, j0 + d):
                c = ((i + 0.5 - nx / 2) * pitch, (j + 0.5 - ny / 2) * pitch)
                geo.cylinder((*c, ztop), (*c, ztop + sh), sr, segments=10)

    sizes = [(2, 2), (2, 4), (4, 2), (1, 4), (4, 1), (2, 3), (3, 2), (1, 2), (2, 6)]
    for _ in range(p["detail"]):
        w, d = rng.choice(sizes)
        # bias towards the middle so that the thing looks like a cabin on a chassis
        i0 = min(max(int(rng.gauss(nx / 2 - w / 2, nx / 4)), 0), nx - w)
        j0 = min(max(int(rng.gauss(ny / 2 - d / 2, ny / 4)), 0), ny - d)
        zb = float(height[i0:i0 + w, j0:j0 + d].max())
        if zb + bh > 0.62:
            continue
        geo = geos[rng.choice(["red", "yellow", "blue", "gray"])]
        cx, cy = (i0 + w / 2 - nx / 2) * pitch, (j0 + d / 2 - ny / 2) * pitch
        geo.box((cx, cy, zb + bh / 2), (w * pitch - 0.004, d * pitch - 0.004, bh))
        height[i0:i0 + w, j0:j0 + d] = zb + bh
    for i in range(nx):  # studs on every exposed top face
        for j in range(ny):
            c = ((i + 0.5 - nx / 2) * pitch, (j + 0.5 - ny / 2) * pitch)
            geos["gray" if height[i, j] == z0 else rng.choice(list(pal))].cylinder(
                (*c, height[i, j]), (*c, height[i, j] + sh), sr, segments=10)
    tyre = _Geo()
    for x in (-0.55, 0.55):
        for y in (-0.56, 0.56):
            tyre.cylinder((x, y - 0.06, z0 - 0.14), (x, y + 0.06, z0 - 0.14), 0.15, segments=24)
            geos["gray"].cylinder((x, y - 0.07 * np.sign(y), z0 - 0.14), (x, y + 0.07 * np.sign(y), z0 - 0.14),
                                  0.07, segments=16)
    for k, (c0, c1) in pal.items():
        geos[k].finish(f"lego_{k}", _noise_material(f"brick_{k}", rng, c0, c1, 22.0 * ts, roughness=0.35))
    tyre.finish("lego_tyres", _noise_material("rubber", rng, (0.01, 0.01, 0.01), (0.3, 0.3, 0.3), 25.0 * ts,
                                              roughness=0.8), smooth=True)
    return {"lights": _studio(p["light_strength"])}


def _ficus(p, rng):
    ts = p["texture_scale"]
    pot, soil, stem, leaves = _Geo(), _Geo(), _Geo(), _Geo()
    pot.cylinder((0, 0, -1.0), (0, 0, -0.58), 0.26, 0.36, segments=40)
    soil.cylinder((0, 0, -0.6), (0, 0, -0.56), 0.33, segments=40)
    # stem: a wiggly polyline from the soil to the top
    pts = [Vector((0, 0, -0.6))]
    for k in range(1, 9):
        pts.append(Vector((rng.uniform(-0.06, 0.06), rng.uniform(-0.06, 0.06), -0.6 + 1.45 * k / 8)))
    for k in range(8):
        stem.cylinder(pts[k], pts[k + 1], 0.035 - 0.0025 * k, 0.035 - 0.0025 * (k + 1), segments=10)
        stem.sphere(pts[k + 1], 0.035 - 0.0025 * (k + 1), subdiv=1)
    for b in range(p["detail"]):
        t = rng.uniform(0.2, 0.98)
        k = min(int(t * 8), 7)
        base = pts[k].lerp(pts[k + 1], t * 8 - k)
        az, el = rng.uniform(0, 2 * math.pi), rng.uniform(-0.1, 0.7)
        length = rng.uniform(0.3, 0.6) * (1.15 - 0.5 * t)
        direc = Vector((math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)))
        tip = base + direc * length
        if tip.xy.length > 0.85:
            tip.xy *= 0.85 / tip.xy.length
        tip.z = min(tip.z, 0.92)
        stem.cylinder(base, tip, rng.uniform(0.008, 0.013), 0.004, segments=6)
        for _ in range(rng.randint(3, 6)):
            s = rng.uniform(0.25, 1.0)
            at = base.lerp(tip, s)
            ld = Vector((rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0.3, 0.6))).normalized()
            rot = ld.to_track_quat("X", "Z").to_matrix().to_4x4() @ Matrix.Rotation(rng.uniform(-0.8, 0.8), 4, "X")
            size = rng.uniform(0.05, 0.08)
            leaves.sphere(at + ld * size, 1.0, scale=(size, size * 0.45, size * 0.08), rot=rot, subdiv=1)
    pot.finish("ficus_pot", _noise_material("terracotta", rng, (0.2, 0.05, 0.02), (0.85, 0.4, 0.2), 14.0 * ts),
               smooth=True)
    soil.finish("ficus_soil", _noise_material("soil", rng, (0.01, 0.008, 0.005), (0.3, 0.2, 0.1), 30.0 * ts))
    stem.finish("ficus_stem", _noise_material("bark", rng, (0.08, 0.04, 0.015), (0.5, 0.33, 0.16), 40.0 * ts),
                smooth=True)
    leaves.finish("ficus_leaves", _noise_material("leaf", rng, (0.01, 0.12, 0.01), (0.35, 0.7, 0.08),
                                                  18.0 * ts, roughness=0.4, spots=0.5), smooth=True)
    return {"lights": _studio(p["light_strength"])}


def _materials(p, rng):
    ts = p["texture_scale"]
    plate = _Geo()
    plate.cylinder((0, 0, -0.48), (0, 0, -0.38), 0.9, segments=64)
    plate.finish("plate", _noise_material("plate", rng, (0.03, 0.03, 0.05), (0.9, 0.85, 0.7), 9.0 * ts,
                                          roughness=0.7))
    kinds = [("chrome", dict(metallic=1.0, roughness=0.04, color=(0.95, 0.95, 0.95))),
             ("gold", dict(metallic=1.0, roughness=0.12, color=(1.0, 0.76, 0.33))),
             ("red_gloss", dict(metallic=0.0, roughness=0.08, color=(0.7, 0.03, 0.02), coat=1.0)),
             ("copper", dict(metallic=1.0, roughness=0.2, color=(0.95, 0.45, 0.3))),
             ("textured", None),
             ("blue_gloss", dict(metallic=0.0, roughness=0.05, color=(0.03, 0.12, 0.6), coat=1.0)),
             ("steel", dict(metallic=1.0, roughness=0.3, color=(0.6, 0.62, 0.65)))]
    n = max(1, p["detail"])
    slots = [(math.cos(2 * math.pi * i / n + 0.3) * 0.6, math.sin(2 * math.pi * i / n + 0.3) * 0.6)
             for i in range(n)] if n > 1 else [(0.0, 0.0)]
    for i, (x, y) in enumerate(slots):
        name, spec = kinds[i % len(kinds)]
        mat = (_noise_material(f"diffuse_{i}", rng, (0.05, 0.15, 0.02), (0.95, 0.9, 0.3), 12.0 * ts)
               if spec is None else _material(f"{name}_{i}", **spec)[0])
        geo = _Geo()
        r = rng.uniform(0.14, 0.2)
        if i % 3 == 2:  # torus standing up
            rot = Matrix.Rotation(rng.uniform(0, math.pi), 4, "Z") @ Matrix.Rotation(math.pi / 2, 4, "X")
            geo.torus((x, y, -0.38 + r + 0.06), r, 0.06, rot=rot)
        else:
            geo.uvsphere((x, y, -0.38 + r), r)
        geo.finish(f"obj_{i}_{name}", mat, smooth=True)
    centre = _Geo()
    centre.uvsphere((0, 0, -0.38 + 0.3), 0.3)  # mirror ball in the middle
    centre.finish("obj_centre", _material("mirror", metallic=1.0, roughness=0.02, color=(0.9, 0.9, 0.92))[0],
                  smooth=True)
    return {"lights": _studio(p["light_strength"])}


def _lowlight(p, rng):
    ts = p["texture_scale"]
    base = _Geo()
    base.box((0, 0, -0.5), (1.6, 1.6, 0.1))
    base.finish("table", _noise_material("table", rng, (0.05, 0.03, 0.02), (0.9, 0.7, 0.45), 10.0 * ts))
    vase = _Geo()
    vase.cylinder((0, 0, -0.45), (0, 0, 0.5), 0.25, 0.15, segments=40)
    vase.sphere((0, 0, -0.05), 0.3, scale=(1, 1, 0.9), subdiv=3)
    vase.finish("vase", _noise_material("vase", rng, (0.1, 0.12, 0.3), (0.95, 0.9, 0.8), 12.0 * ts), smooth=True)
    rocks = _Geo()
    for i in range(p["detail"]):
        a = 2 * math.pi * i / max(p["detail"], 1) + rng.uniform(-0.3, 0.3)
        r = rng.uniform(0.08, 0.16)
        rot = Matrix.Rotation(rng.uniform(0, math.pi), 4, "Z")
        rocks.sphere((0.55 * math.cos(a), 0.55 * math.sin(a), -0.45 + 0.6 * r), r,
                     scale=(rng.uniform(0.8, 1.4), rng.uniform(0.7, 1.2), 0.7), rot=rot, subdiv=2)
    rocks.finish("stones", _noise_material("stone", rng, (0.1, 0.1, 0.1), (0.9, 0.85, 0.8), 20.0 * ts))
    ls = p["light_strength"]
    return {"lights": [_area(45.0 * ls, (1.5, -1.2, 1.6), size=0.3, kind="POINT")],
            "suggested_background": [0.004, 0.004, 0.005]}


_BUILDERS = {"lego": _lego, "ficus": _ficus, "materials": _materials, "lowlight": _lowlight}


def mesh_bounds(objects=None) -> list:
    """(2, 3) world AABB of the evaluated mesh vertices of `objects` (default: all mesh objects)."""
    dg = bpy.context.evaluated_depsgraph_get()
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for obj in objects if objects is not None else bpy.context.scene.objects:
        if obj.type != "MESH":
            continue
        ev = obj.evaluated_get(dg)
        mesh = ev.to_mesh()
        co = np.empty(len(mesh.vertices) * 3, np.float64)
        mesh.vertices.foreach_get("co", co)
        ev.to_mesh_clear()
        if co.size == 0:
            continue
        m = np.array(ev.matrix_world)
        w = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
        lo, hi = np.minimum(lo, w.min(0)), np.maximum(hi, w.max(0))
    if not np.all(np.isfinite(lo)):
        return [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    return [lo.tolist(), hi.tolist()]


def build(name: str, params: dict | None = None, seed: int = 0) -> dict:
    """Build scene `name` into the current (empty) scene. Returns {"bounds": (2,3) list, "lights": [...],
    "params": the full parameter set used, ...}."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown builder {name!r}; choose one of {', '.join(BUILDER_NAMES)}")
    params = dict(params or {})
    unknown = sorted(set(params) - set(DEFAULTS[name]))
    if unknown:
        raise ValueError(f"unknown params for builder {name!r}: {unknown}; known: {sorted(DEFAULTS[name])}")
    p = {**DEFAULTS[name], **params}
    p["detail"] = int(p["detail"])
    p["texture_scale"], p["light_strength"] = float(p["texture_scale"]), float(p["light_strength"])
    rng = random.Random(int(seed))
    info = _BUILDERS[name](p, rng)
    bpy.context.view_layer.update()
    return {"bounds": mesh_bounds(), "params": p, **info}
