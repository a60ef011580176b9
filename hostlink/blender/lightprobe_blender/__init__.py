# SPDX-License-Identifier: Apache-2.0
"""lightprobe for Blender: light the scene with a lightprobe unit's live lighting.

World properties > Light Probe: pick a probe (Discover: DNS-SD on the LAN; or its URL) and its
token (``lightprobe token`` on the unit), then

- **Go live**: the World's environment becomes the probe's HDR map without its primary light
  (``/api/v1/environment_ambient_latlong.exr``) and a Sun lamp ("lightprobe primary light") the
  primary light (direction, colour, strength = its irradiance in W/m^2 at normal incidence,
  angle = its solid angle), refreshed by a timer every ``interval`` seconds while you work (the
  download runs in a thread; Blender only swaps the image and moves the lamp);
- **Freeze**: stop updating and keep the last lighting (the image packed into the .blend file).

The probe's frame (+y up) is posed into Blender's +Z-up world as Blender's glTF importer does
(``probe_io``'s docstring has the matrices), after the probe's own pose. Needs nothing of the
lightprobe package: HTTP and the standard library.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time

import bpy
from mathutils import Matrix, Vector

from . import probe_io

bl_info = {
    "name": "lightprobe",
    "author": "lightprobe developers",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "Properties > World > Light Probe",
    "description": "Light the scene with a lightprobe unit's live HDR lighting",
    "category": "Lighting",
}

WORLD_NAME = "lightprobe"
IMAGE_NAME = "lightprobe ambient"
SUN_NAME = "lightprobe primary light"


class _Live:
    """The add-on's state outside Blender's data: the fetch thread and its last result."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.thread: threading.Thread | None = None
        self.result: tuple[dict, bytes] | None = None
        self.error: str | None = None
        self.running = False
        self.tmpdir = tempfile.mkdtemp(prefix="lightprobe-blender-")
        self.found: list[dict] = []
        self.applied = 0


LIVE = _Live()


def _settings(context=None):
    return (context or bpy.context).scene.lightprobe


def _fetch(base: str, token: str) -> None:
    try:
        result = probe_io.fetch_lighting(base, token)
        with LIVE.lock:
            LIVE.result, LIVE.error = result, None
    except probe_io.ProbeError as e:
        with LIVE.lock:
            LIVE.error = str(e)


def start_fetch(context=None) -> None:
    """One download in a thread (none while one runs)."""
    s = _settings(context)
    if LIVE.thread is not None and LIVE.thread.is_alive():
        return
    base = probe_io.normalise_url(s.url)
    LIVE.thread = threading.Thread(target=_fetch, args=(base, s.token), name="lightprobe-fetch", daemon=True)
    LIVE.thread.start()


def apply_lighting(sh: dict, exr: bytes, scene=None) -> None:
    """Put one fetch into the scene: the world's image, its rotation, the Sun lamp."""
    scene = scene or bpy.context.scene
    s = scene.lightprobe
    path = os.path.join(LIVE.tmpdir, f"ambient-{LIVE.applied % 2}.exr")  # never overwrite the image in use
    with open(path, "wb") as f:
        f.write(exr)
    img = bpy.data.images.get(IMAGE_NAME)
    if img is None:
        img = bpy.data.images.load(path, check_existing=False)
        img.name = IMAGE_NAME
    else:
        img.filepath = path
        img.reload()
    world = _world(scene)
    nodes = world.node_tree.nodes
    nodes["lightprobe map"].image = img
    rot = Matrix(probe_io.environment_rotation(sh))
    nodes["lightprobe pose"].inputs["Rotation"].default_value = rot.to_euler("XYZ")
    _sun(scene, sh)
    s.frame = int(sh.get("frame", -1))
    s.captured = float(sh.get("captured") or sh.get("timestamp") or 0.0)
    s.status = f"frame {s.frame}" + (" (stale)" if sh.get("stale") else "")
    LIVE.applied += 1


def _world(scene):
    """The scene's world, set up once: Texture Coordinate -> Mapping (the pose) -> Environment
    Texture (the map) -> Background (strength 1: the map is radiance) -> World Output."""
    world = bpy.data.worlds.get(WORLD_NAME) or bpy.data.worlds.new(WORLD_NAME)
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    if "lightprobe map" not in nt.nodes:
        nt.nodes.clear()
        coord = nt.nodes.new("ShaderNodeTexCoord")
        mapping = nt.nodes.new("ShaderNodeMapping")
        mapping.name = "lightprobe pose"
        mapping.vector_type = "POINT"
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        tex.name = "lightprobe map"
        tex.interpolation = "Linear"
        bg = nt.nodes.new("ShaderNodeBackground")
        bg.inputs["Strength"].default_value = 1.0
        out = nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
        nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
        for i, n in enumerate((coord, mapping, tex, bg, out)):
            n.location = (i * 260.0 - 600.0, 0.0)
    return world


def _sun(scene, sh: dict) -> None:
    obj = bpy.data.objects.get(SUN_NAME)
    if obj is None:
        lamp = bpy.data.lights.new(SUN_NAME, type="SUN")
        obj = bpy.data.objects.new(SUN_NAME, lamp)
    if obj.name not in scene.collection.all_objects:
        scene.collection.objects.link(obj)
    prim = sh.get("primary_light")
    lamp = obj.data
    if not prim:
        lamp.energy = 0.0
        return
    strength, colour, angle = probe_io.sun_from_primary(prim)
    lamp.energy, lamp.color, lamp.angle = strength, colour, angle
    d = Vector(probe_io.to_blender(prim["direction"], sh))
    # a Sun lamp shines along its local -Z: its +Z points at the light
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = Vector((0.0, 0.0, 1.0)).rotation_difference(d)


def _tick():
    """The live timer: apply a finished download, start the next one."""
    if not LIVE.running:
        return None
    try:
        scene = bpy.context.scene
        s = scene.lightprobe
        with LIVE.lock:
            result, LIVE.result = LIVE.result, None
            error = LIVE.error
        if result is not None:
            apply_lighting(*result, scene=scene)
        elif error:
            s.status = error
        start_fetch()
        return max(0.1, float(s.interval))
    except Exception as e:  # the timer must not die with an exception in Blender's log only
        print(f"lightprobe: {e}")
        return 1.0


# ---- operators ------------------------------------------------------------------------------------
class LIGHTPROBE_OT_discover(bpy.types.Operator):
    """Find lightprobe units on the LAN (DNS-SD)"""

    bl_idname = "lightprobe.discover"
    bl_label = "Discover"

    def execute(self, context):
        s = _settings(context)
        try:
            LIVE.found = probe_io.discover(1.5)
        except OSError as e:
            self.report({"ERROR"}, f"discovery failed: {e}")
            return {"CANCELLED"}
        s.found.clear()
        for p in LIVE.found:
            item = s.found.add()
            item.name, item.url, item.probe_id = p["name"], p["url"], p["id"]
        if LIVE.found and not s.url:
            s.url = LIVE.found[0]["url"]
        self.report({"INFO"}, f"{len(LIVE.found)} probe(s) found")
        return {"FINISHED"}


class LIGHTPROBE_OT_use(bpy.types.Operator):
    """Use this discovered probe"""

    bl_idname = "lightprobe.use"
    bl_label = "Use"
    url: bpy.props.StringProperty()

    def execute(self, context):
        _settings(context).url = self.url
        return {"FINISHED"}


class LIGHTPROBE_OT_live(bpy.types.Operator):
    """Light the scene with the probe's live lighting (updated while you work)"""

    bl_idname = "lightprobe.live"
    bl_label = "Go live"

    def execute(self, context):
        s = _settings(context)
        try:
            base = probe_io.normalise_url(s.url)
            sh, exr = probe_io.fetch_lighting(base, s.token)  # the first one now: errors show at once
        except probe_io.ProbeError as e:
            s.status = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        apply_lighting(sh, exr, context.scene)
        s.live = True
        if not LIVE.running:
            LIVE.running = True
            bpy.app.timers.register(_tick, first_interval=float(s.interval), persistent=True)
        return {"FINISHED"}


class LIGHTPROBE_OT_freeze(bpy.types.Operator):
    """Stop updating and keep the current lighting (packed into the .blend file)"""

    bl_idname = "lightprobe.freeze"
    bl_label = "Freeze snapshot"

    def execute(self, context):
        s = _settings(context)
        LIVE.running = False
        if bpy.app.timers.is_registered(_tick):
            bpy.app.timers.unregister(_tick)
        s.live = False
        img = bpy.data.images.get(IMAGE_NAME)
        if img is not None:
            img.pack()
        s.status = f"frozen at frame {s.frame}"
        return {"FINISHED"}


# ---- properties and panel -------------------------------------------------------------------------
class LightprobeFound(bpy.types.PropertyGroup):
    url: bpy.props.StringProperty()
    probe_id: bpy.props.StringProperty()


class LightprobeSettings(bpy.types.PropertyGroup):
    url: bpy.props.StringProperty(name="Probe", description="http://HOST:PORT of the probe")
    token: bpy.props.StringProperty(name="Token", subtype="PASSWORD",
                                    description="the probe's token (lightprobe token): its map is private")
    interval: bpy.props.FloatProperty(name="Interval", default=1.0, min=0.1, max=60.0, unit="TIME_ABSOLUTE",
                                      description="seconds between updates while live")
    live: bpy.props.BoolProperty(name="Live", default=False)
    frame: bpy.props.IntProperty(name="Frame", default=-1)
    captured: bpy.props.FloatProperty(name="Captured", default=0.0)
    status: bpy.props.StringProperty(name="Status", default="")
    found: bpy.props.CollectionProperty(type=LightprobeFound)


class LIGHTPROBE_PT_world(bpy.types.Panel):
    bl_label = "Light Probe"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "world"

    def draw(self, context):
        s = _settings(context)
        col = self.layout.column()
        row = col.row(align=True)
        row.prop(s, "url")
        row.operator("lightprobe.discover", text="", icon="VIEWZOOM")
        for p in s.found:
            col.operator("lightprobe.use", text=f"{p.name} ({p.url})").url = p.url
        col.prop(s, "token")
        col.prop(s, "interval")
        row = col.row(align=True)
        row.operator("lightprobe.live", icon="PLAY")
        row.operator("lightprobe.freeze", icon="FREEZE")
        if s.status:
            age = f", {time.time() - s.captured:.1f} s old" if s.captured > 0 and s.live else ""
            col.label(text=s.status + age)


CLASSES = (LightprobeFound, LightprobeSettings, LIGHTPROBE_OT_discover, LIGHTPROBE_OT_use, LIGHTPROBE_OT_live,
           LIGHTPROBE_OT_freeze, LIGHTPROBE_PT_world)


def register() -> None:
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.lightprobe = bpy.props.PointerProperty(type=LightprobeSettings)


def unregister() -> None:
    LIVE.running = False
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    del bpy.types.Scene.lightprobe
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
