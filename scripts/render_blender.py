# Blender (bpy) side of scripts/render_blender.sh: renders a surfaced Amalgam frame headless with
# Cycles on the CPU. Each input given becomes one panel of the output PNG, left to right:
#   --points frame_NNNN.ply      the particles (PLY point cloud, drawn as spheres via geometry nodes)
#   --mesh surfacing_NNNN.obj|ply the surfaced triangle mesh
#   --vdb surfacing_NNNN.vdb     its `density` fog grid (bpy.ops.object.volume_import)
# Every panel is rendered with the same camera, lights and settings, so they can be compared.
# Amalgam scenes are Y-up (metres); Blender is Z-up: everything imported, and the camera given in
# scene coordinates, is rotated by +90 degrees about X.
# Run as: blender -b --factory-startup --python render_blender.py -- [options] (see the .sh).
import argparse
import math
import os
import sys

import bpy
from mathutils import Matrix, Vector

Y_UP_TO_Z_UP = Matrix.Rotation(math.radians(90.0), 4, "X")


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    ap = argparse.ArgumentParser(prog="render_blender.py")
    ap.add_argument("--points")
    ap.add_argument("--mesh")
    ap.add_argument("--vdb")
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--threads", type=int, default=0)  # 0: Blender's automatic count
    ap.add_argument("--density", type=float, default=0.0)  # volume density scale; 0: from size
    ap.add_argument("--point-radius", type=float, default=0.0)  # 0: from the points' spacing
    ap.add_argument("--camera")  # x,y,z in scene coordinates
    ap.add_argument("--look-at")
    ap.add_argument("--fov", type=float, default=40.0)  # horizontal, degrees
    a = ap.parse_args(argv)
    if not (a.points or a.mesh or a.vdb):
        ap.error("give at least one of --points, --mesh, --vdb")
    return a


def vec3(text):
    v = [float(c) for c in text.split(",")]
    if len(v) != 3:
        raise SystemExit("render_blender.py: expected x,y,z, got " + text)
    return Vector(v)


def fail(msg):
    print("render_blender.py: " + msg, file=sys.stderr)
    sys.exit(1)


def new_objects(before):
    return [o for o in bpy.data.objects if o.name not in before]


def material_surface(name, color):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    bsdf = m.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = color
    bsdf.inputs["Roughness"].default_value = 0.35
    return m


def import_mesh(path):
    before = {o.name for o in bpy.data.objects}
    if path.lower().endswith(".obj"):
        # Blender 3.2+ C++ importer; forward Y / up Z: no axis conversion (done below for all).
        bpy.ops.wm.obj_import(filepath=path, forward_axis="Y", up_axis="Z")
    elif path.lower().endswith(".ply"):
        bpy.ops.import_mesh.ply(filepath=path)  # the io_mesh_ply add-on: no axis conversion
    else:
        fail(path + ": expected a .obj or .ply mesh")
    objs = new_objects(before)
    if not objs:
        fail(path + ": nothing imported")
    return objs


def add_points(path, radius):
    objs = import_mesh(path)  # a PLY with vertices only: a mesh of loose vertices
    mat = material_surface("points", (0.85, 0.45, 0.15, 1.0))
    for o in objs:
        if radius <= 0:  # half the mean spacing: the cube root of bounding volume per point
            d = o.dimensions
            n = max(1, len(o.data.vertices))
            radius = 0.5 * (max(d.x * d.y * d.z, 1e-12) / n) ** (1.0 / 3.0)
        ng = bpy.data.node_groups.new("points", "GeometryNodeTree")
        ng.inputs.new("NodeSocketGeometry", "Geometry")  # Blender 3.x interface API
        ng.outputs.new("NodeSocketGeometry", "Geometry")
        gin = ng.nodes.new("NodeGroupInput")
        gout = ng.nodes.new("NodeGroupOutput")
        to_points = ng.nodes.new("GeometryNodeMeshToPoints")
        to_points.inputs["Radius"].default_value = radius
        set_mat = ng.nodes.new("GeometryNodeSetMaterial")
        set_mat.inputs["Material"].default_value = mat
        ng.links.new(gin.outputs[0], to_points.inputs["Mesh"])
        ng.links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
        ng.links.new(set_mat.outputs["Geometry"], gout.inputs[0])
        o.modifiers.new("points", "NODES").node_group = ng
    return objs


def add_mesh(path):
    objs = import_mesh(path)
    mat = material_surface("surface", (0.20, 0.45, 0.85, 1.0))
    for o in objs:
        o.data.materials.clear()
        o.data.materials.append(mat)
        for p in o.data.polygons:
            p.use_smooth = True
    return objs


def add_volume(path, density):
    before = {o.name for o in bpy.data.objects}
    bpy.ops.object.volume_import(filepath=path, files=[{"name": os.path.basename(path)}],
                                 directory=os.path.dirname(os.path.abspath(path)) + os.sep)
    objs = new_objects(before)
    if not objs:
        fail(path + ": no volume imported")
    for o in objs:
        o.data.grids.load()
        names = [g.name for g in o.data.grids]
        if "density" not in names:
            fail(path + ": no grid named density (grids: " + ", ".join(names) + ")")
    m = bpy.data.materials.new("density")
    m.use_nodes = True
    nodes = m.node_tree.nodes
    for n in list(nodes):
        nodes.remove(n)
    vol = nodes.new("ShaderNodeVolumePrincipled")
    vol.inputs["Color"].default_value = (0.75, 0.85, 1.0, 1.0)
    vol.inputs["Density"].default_value = density
    vol.inputs["Density Attribute"].default_value = "density"
    out = nodes.new("ShaderNodeOutputMaterial")
    m.node_tree.links.new(vol.outputs["Volume"], out.inputs["Volume"])
    for o in objs:
        o.data.materials.clear()
        o.data.materials.append(m)
    return objs


def bounds(objs):
    """World-space bounds: a mesh's vertices (its bound_box is stale before evaluation), else the
    evaluated object's bounding box (a volume's grids)."""
    lo = Vector((math.inf,) * 3)
    hi = Vector((-math.inf,) * 3)
    deps = bpy.context.evaluated_depsgraph_get()
    for o in objs:
        if o.type == "MESH" and len(o.data.vertices) > 0:
            pts = [o.matrix_world @ v.co for v in o.data.vertices]
        else:
            e = o.evaluated_get(deps)
            pts = [e.matrix_world @ Vector(c) for c in e.bound_box]
        for w in pts:
            lo = Vector(min(a, b) for a, b in zip(lo, w))
            hi = Vector(max(a, b) for a, b in zip(hi, w))
    return lo, hi


def main():
    a = parse_args()
    try:
        width, height = (int(t) for t in a.size.lower().split("x"))
    except ValueError:
        fail("--size: expected WxH, got " + a.size)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = a.samples
    scene.cycles.use_denoising = False  # Debian's Blender 3.4.1 has no OpenImageDenoise
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.seed = 0
    scene.cycles.volume_bounces = 2  # lets light scatter through the fog (default 0: dark)
    if a.threads > 0:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = a.threads
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.view_settings.view_transform = "Standard"

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.35, 0.37, 0.42, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.0
    scene.world = world

    panels = []  # (label, objects)
    if a.points:
        panels.append(("points", add_points(a.points, a.point_radius)))
    if a.mesh:
        panels.append(("mesh", add_mesh(a.mesh)))
    everything = [o for _, objs in panels for o in objs]
    for o in everything:
        o.matrix_world = Y_UP_TO_Z_UP @ o.matrix_world
    bpy.context.view_layer.update()
    lo_hi = bounds(everything) if everything else None
    if a.vdb:
        vol = add_volume(a.vdb, 1.0)
        for o in vol:
            o.matrix_world = Y_UP_TO_Z_UP @ o.matrix_world
        bpy.context.view_layer.update()
        lo, hi = bounds(vol) if lo_hi is None else lo_hi
        # Density scale: optical depth ~ 30 across the body's smallest extent unless given.
        size = max(min(hi - lo), 1e-6)
        dens = a.density if a.density > 0 else 30.0 / size
        vol[0].data.materials[0].node_tree.nodes["Principled Volume"].inputs[
            "Density"].default_value = dens
        panels.append(("density", vol))
        everything += vol
    # The camera frames the points and mesh when given (a volume's bounds are its grid's, padded).
    lo, hi = lo_hi if a.vdb and lo_hi is not None else bounds(everything)

    # Camera: given in scene (Y-up) coordinates, or looking at the bounds from the front right.
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = math.radians(a.fov)
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    if a.look_at:
        target = Y_UP_TO_Z_UP @ vec3(a.look_at)
    else:
        target = (lo + hi) / 2
    if a.camera:
        eye = Y_UP_TO_Z_UP @ vec3(a.camera)
    else:
        radius = max((hi - lo).length / 2, 1e-6)
        dist = radius / math.sin(math.radians(a.fov) / 2 * min(1.0, height / width)) * 1.05
        eye = target + Vector((0.55, -1.0, 0.6)).normalized() * dist
    cam.location = eye
    print("render_blender.py: bounds", tuple(lo), tuple(hi), "eye", tuple(eye))
    cam.rotation_euler = (target - eye).to_track_quat("-Z", "Y").to_euler()
    cam_data.clip_start = 1e-3 * (eye - target).length
    cam_data.clip_end = 100 * (eye - target).length

    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 4.0
    sun.rotation_euler = (math.radians(40), math.radians(10), math.radians(30))
    scene.collection.objects.link(sun)

    # One render per panel, the others hidden; then the panels side by side in one image.
    pixels = []
    for label, objs in panels:
        for _, others in panels:
            for o in others:
                o.hide_render = others is not objs
        path = a.out + "." + label + ".png"
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(path)
        pixels.append(list(img.pixels))
        bpy.data.images.remove(img)
        os.remove(path)
    n = len(pixels)
    out = bpy.data.images.new("panels", width * n, height, alpha=False)
    rows = []
    for y in range(height):  # Blender images are RGBA floats, rows from the bottom
        for k in range(n):
            rows.extend(pixels[k][4 * width * y: 4 * width * (y + 1)])
    out.pixels = rows
    out.filepath_raw = a.out
    out.file_format = "PNG"
    out.save()
    print("render_blender.py: wrote %s (%dx%d, panels: %s)" %
          (a.out, width * n, height, ", ".join(p[0] for p in panels)))


try:
    main()
except SystemExit:
    raise
except Exception as e:  # noqa: BLE001 - any Blender error: a clear message and exit code 1
    fail(str(e))
