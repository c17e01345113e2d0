"""Render one particle bed with Blender Cycles. Runs INSIDE Blender's Python (the `bpy` module,
in its own environment with numpy<2), so it imports only bpy, mathutils, numpy and the
standard library — never the psdfactory package.

    <blender-python> -P blender_job.py JOB_DIR

JOB_DIR holds ``scene.json`` (camera, lights, materials, Cycles settings) and ``scene.npz``
(particle meshes in mm, poses, colours) written by ``psdfactory.scene.render.cycles``. Writes
``image.png`` (8-bit sRGB, Blender's "Standard" view), ``ids.npy`` (uint16 instance ids from
the object-index pass: 0 = table, k = particle_id + 1) and ``result.json`` (device, seconds).
Lengths are converted from mm to Blender metres.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

MM = 0.001  # Blender unit (m) per mm
# The standard deviation of the Noise Texture's Fac about its mean 0.5 (measured on Blender 4.5,
# Detail 6 and 8): the textures divide by it, so that a texture amplitude means the same as in
# the fast backend — the standard deviation of the relative brightness.
NOISE_STD = 0.073


def srgb_to_linear(c):
    c = np.asarray(c, dtype=float)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def choose_device(scene, want: str) -> str:
    """GPU (OptiX, CUDA, HIP, oneAPI, Metal — the first with a device) unless `want` is cpu."""
    scene.cycles.device = "CPU"
    if want == "cpu":
        return "CPU"
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for kind in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
        try:
            prefs.compute_device_type = kind
            prefs.get_devices()
        except (TypeError, ValueError):
            continue
        gpus = [d for d in prefs.devices if d.type == kind]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == kind
            scene.cycles.device = "GPU"
            return f"GPU ({kind}: {', '.join(d.name for d in gpus)})"
    if want == "gpu":
        raise SystemExit("render.cycles.device is 'gpu' but Blender finds no CUDA/OptiX/HIP/oneAPI/Metal device")
    return "CPU"


def object_attribute(nt, name: str):
    node = nt.nodes.new("ShaderNodeAttribute")
    node.attribute_type = "OBJECT"
    node.attribute_name = name
    return node


def math_node(nt, operation: str, a, b=None, c=None):
    """A Math node: each input a socket (linked) or a number."""
    node = nt.nodes.new("ShaderNodeMath")
    node.operation = operation
    for i, v in enumerate((a, b, c)):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            node.inputs[i].default_value = float(v)
        else:
            nt.links.new(v, node.inputs[i])
    return node.outputs["Value"]


def particle_material(bump_mm: float):
    """One material for every particle: colour, roughness and texture amplitude per object
    (Object Info colour, 'roughness' and 'detail' properties), a noise bump for surface detail
    and colour mottling of standard deviation `detail` (relative), as the fast backend's."""
    m = bpy.data.materials.new("particle")
    m.use_nodes = True
    nt = m.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    info = nt.nodes.new("ShaderNodeObjectInfo")
    rough = object_attribute(nt, "roughness")
    detail = object_attribute(nt, "detail").outputs["Fac"]
    coord = nt.nodes.new("ShaderNodeTexCoord")
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 1.0 / (bump_mm * MM)
    noise.inputs["Detail"].default_value = 6.0
    nt.links.new(coord.outputs["Object"], noise.inputs["Vector"])
    bump = nt.nodes.new("ShaderNodeBump")
    nt.links.new(math_node(nt, "MINIMUM", math_node(nt, "MULTIPLY", detail, 4.0), 1.0), bump.inputs["Strength"])
    bump.inputs["Distance"].default_value = bump_mm * MM
    nt.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    # mottling: 1 + detail * z, z = the noise at unit standard deviation
    z = math_node(nt, "MULTIPLY_ADD", noise.outputs["Fac"], 1 / NOISE_STD, -0.5 / NOISE_STD)
    mottle = math_node(nt, "MAXIMUM", math_node(nt, "MULTIPLY_ADD", z, detail, 1.0), 0.0)
    tint = nt.nodes.new("ShaderNodeVectorMath")
    tint.operation = "SCALE"
    nt.links.new(info.outputs["Color"], tint.inputs[0])
    nt.links.new(mottle, tint.inputs["Scale"])
    nt.links.new(tint.outputs["Vector"], bsdf.inputs["Base Color"])
    nt.links.new(rough.outputs["Fac"], bsdf.inputs["Roughness"])
    return m


def table_material(rgb, texture: float, grain_mm: float):
    m = bpy.data.materials.new("table")
    m.use_nodes = True
    nt = m.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 0.85
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 1.0 / (grain_mm * MM)
    noise.inputs["Detail"].default_value = 8.0
    # colour = rgb * (1 + texture * z), z = the noise at unit standard deviation, over ±3 sd
    spread = nt.nodes.new("ShaderNodeMapRange")
    spread.clamp = True
    spread.inputs["From Min"].default_value = 0.5 - 3 * NOISE_STD
    spread.inputs["From Max"].default_value = 0.5 + 3 * NOISE_STD
    nt.links.new(noise.outputs["Fac"], spread.inputs["Value"])
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    lo = srgb_to_linear(np.clip(np.asarray(rgb) * (1 - 3 * texture), 0, 1))
    hi = srgb_to_linear(np.clip(np.asarray(rgb) * (1 + 3 * texture), 0, 1))
    ramp.color_ramp.elements[0].color = (*lo, 1)
    ramp.color_ramp.elements[1].color = (*hi, 1)
    nt.links.new(spread.outputs["Result"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bump = nt.nodes.new("ShaderNodeBump")
    bump.inputs["Strength"].default_value = 0.3
    nt.links.new(noise.outputs["Fac"], bump.inputs["Height"])
    nt.links.new(bump.outputs["Normal"], bsdf.inputs["Normal"])
    return m


def add_mesh(name: str, verts: np.ndarray, faces: np.ndarray, smooth: bool):
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(verts, dtype=np.float32).ravel())
    mesh.loops.add(3 * len(faces))
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(faces, dtype=np.int32).ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(faces), 3, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.full(len(faces), smooth))
    mesh.update(calc_edges=True)
    mesh.validate()
    return mesh


def build_scene(job: dict, arrays) -> str:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cyc = job["cycles"]
    device = choose_device(scene, cyc["device"])
    scene.cycles.samples = int(cyc["samples"])
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = bool(cyc["denoise"])
    if cyc["denoise"]:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
    scene.cycles.max_bounces = int(cyc["max_bounces"])
    for k in ("diffuse_bounces", "glossy_bounces", "transmission_bounces"):
        setattr(scene.cycles, k, min(getattr(scene.cycles, k), int(cyc["max_bounces"])))
    scene.cycles.seed = int(job["seed"]) % (2**31)
    if cyc.get("threads"):
        scene.render.threads_mode = "FIXED"
        scene.render.threads = int(cyc["threads"])
    r = int(job["resolution"])
    scene.render.resolution_x = scene.render.resolution_y = r
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.color_depth = "8"
    scene.view_layers[0].use_pass_object_index = True

    # camera: the fast backend's — straight down from camera_height, +y up in the image
    H = job["camera_height_mm"] * MM
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "AUTO"
    cam_data.lens_unit = "FOV"
    cam_data.angle = math.radians(job["fov_deg"])
    cam_data.clip_start = max(H - job["top_mm"] * MM - 0.01, 0.01)
    cam_data.clip_end = H + 0.01
    cam = bpy.data.objects.new("camera", cam_data)
    cam.location = (0.0, 0.0, H)
    scene.collection.objects.link(cam)
    scene.camera = cam

    # table: a textured plane larger than the view, at the ground level (0: the floor the
    # particles lie on; above it, the ground buries their lower parts)
    T = job["table_size_mm"] * 1.5 * MM / 2
    z = job["ground_mm"] * MM
    corners = np.array([[-T, -T, z], [T, -T, z], [T, T, z], [-T, T, z]])
    table_mesh = add_mesh("table", corners, np.array([[0, 1, 2], [0, 2, 3]]), False)
    table = bpy.data.objects.new("table", table_mesh)
    table.pass_index = 0
    table_mesh.materials.append(table_material(job["table_rgb"], job["table_texture"], job["grain_mm"]))
    scene.collection.objects.link(table)

    # particles: one object each (the object-index pass needs objects), one shared material
    mat = particle_material(job["bump_mm"])
    v, f = arrays["vertices"] * MM, arrays["faces"]
    vo, fo = arrays["vert_offsets"], arrays["face_offsets"]
    pos, quat = arrays["positions_mm"] * MM, arrays["quats_xyzw"]
    rgb, rough, detail = srgb_to_linear(arrays["rgb"]), arrays["roughness"], arrays["detail"]
    for i in range(len(pos)):
        mesh = add_mesh(f"p{i}", v[vo[i] : vo[i + 1]], f[fo[i] : fo[i + 1]], job["smooth"])
        mesh.materials.append(mat)
        ob = bpy.data.objects.new(f"p{i}", mesh)
        ob.location = tuple(pos[i])
        ob.rotation_mode = "QUATERNION"
        x, y, z, w = quat[i]
        ob.rotation_quaternion = (w, x, y, z)
        ob.pass_index = i + 1
        ob.color = (*rgb[i], 1.0)
        ob["roughness"] = float(rough[i])
        ob["detail"] = float(detail[i])
        scene.collection.objects.link(ob)

    # sun from the drawn direction and colour, plus a uniform sky
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = float(job["sun_strength"])
    sun.color = tuple(job["light_rgb"])  # a multiplier of the sun's energy per channel
    sun.angle = math.radians(job["sun_angle_deg"])
    sun_ob = bpy.data.objects.new("sun", sun)
    sun_ob.rotation_mode = "QUATERNION"
    sun_ob.rotation_quaternion = Vector(job["light_dir"]).to_track_quat("Z", "Y")
    scene.collection.objects.link(sun_ob)
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*srgb_to_linear(job["sky_rgb"]), 1.0)
    bg.inputs["Strength"].default_value = float(job["sky_strength"])
    scene.world = world

    # compositor: the image to the output, the object index to a 32-bit float EXR (exact
    # integers; the Viewer node's pixels are not filled in background mode)
    scene.use_nodes = True
    nt = scene.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    layers = nt.nodes.new("CompositorNodeRLayers")
    comp = nt.nodes.new("CompositorNodeComposite")
    nt.links.new(layers.outputs["Image"], comp.inputs["Image"])
    out = nt.nodes.new("CompositorNodeOutputFile")
    out.base_path = job["out_dir"]
    out.format.file_format = "OPEN_EXR"
    out.format.color_depth = "32"
    out.format.color_mode = "BW"
    out.format.exr_codec = "ZIP"
    out.file_slots[0].path = "ids_"
    nt.links.new(layers.outputs["IndexOB"], out.inputs[0])
    return device


def read_ids(path: Path) -> np.ndarray:
    img = bpy.data.images.load(str(path))
    img.colorspace_settings.name = "Non-Color"
    w, h = img.size
    px = np.empty(w * h * img.channels, dtype=np.float32)
    img.pixels.foreach_get(px)
    return np.rint(px.reshape(h, w, img.channels)[::-1, :, 0]).astype(np.uint16)  # rows run bottom-up


def main(job_dir: Path) -> None:
    t0 = time.perf_counter()
    job = json.loads((job_dir / "scene.json").read_text())
    job["out_dir"] = str(job_dir)
    arrays = dict(np.load(job_dir / "scene.npz"))
    device = build_scene(job, arrays)
    t1 = time.perf_counter()
    bpy.ops.render.render(write_still=False)
    t2 = time.perf_counter()
    bpy.data.images["Render Result"].save_render(filepath=str(job_dir / "image.png"))
    exr = sorted(job_dir.glob("ids_*.exr"))
    if not exr:
        raise SystemExit("Blender wrote no object-index pass")
    np.save(job_dir / "ids.npy", read_ids(exr[0]))
    (job_dir / "result.json").write_text(json.dumps({
        "device": device, "blender": bpy.app.version_string,
        "build_s": round(t1 - t0, 3), "render_s": round(t2 - t1, 3),
    }))


if __name__ == "__main__":
    main(Path(sys.argv[-1]))
