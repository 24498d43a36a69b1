"""Runs inside Blender (``blender -b --factory-startup --python tools/interop_blender.py -- JOB.json``):
imports one of our BVH or GLB files with the settings docs/exports.md gives and writes what
Blender made of it as JSON, for tools/interop_test.py to compare with poses.jsonl.

JOB.json: {"kind": "bvh"|"glb", "file": path, "fps": frames per second, "frames": count,
"points": [[bone name, "head"|"tail"], ...] (the joints to read, in poses.jsonl's order),
"out": path}. The output: Blender's version, the scene's frame rate, the imported action's frame
range, the armature's bone names, the number of keys of each animated bone, the meshes, and per
frame the world position (metres, Blender's z-up world) of every point asked for.

Only Blender's own modules are used (its Python has none of the project's packages).
"""
import builtins
import json
import sys

import bpy
import numpy

BVH_CM_TO_M = 0.01  # our BVH is in centimetres; Blender's scene in metres


def _without_universal_newlines(real_open):
    """Blender 3.4's BVH importer opens its file with mode 'rU', which Python 3.11 refuses
    ('U' has meant nothing since Python 3); drop the 'U' and open as usual."""
    def patched(file, mode="r", *args, **kwargs):
        return real_open(file, mode.replace("U", "") if isinstance(mode, str) else mode, *args, **kwargs)
    return patched


def _numpy_bool_alias():
    """Blender 3.4's glTF importer uses ``numpy.bool``, which numpy 1.24 (Debian 12's) removed:
    put the alias back (it always meant the builtin bool)."""
    if "bool" not in numpy.__dict__:
        numpy.bool = bool


def import_file(job):
    scene = bpy.context.scene
    if job["kind"] == "bvh":
        builtins.open = _without_universal_newlines(builtins.open)
        # the importer's defaults (forward -Z, up Y) and the file's frame rate and length
        bpy.ops.import_anim.bvh(filepath=job["file"], global_scale=BVH_CM_TO_M, axis_forward="-Z", axis_up="Y",
                                rotate_mode="NATIVE", update_scene_fps=True, update_scene_duration=True)
        first = scene.frame_start  # the importer keys BVH frame i at frame_start + i
    else:
        _numpy_bool_alias()
        # Blender keys a glTF animation at time x the scene's frame rate: set the file's first
        scene.render.fps, scene.render.fps_base = round(job["fps"]), 1.0
        bpy.ops.import_scene.gltf(filepath=job["file"])
        first = 0  # the first key is at time 0
    armature = next(o for o in scene.objects if o.type == "ARMATURE")
    return armature, first


def main():
    with open(sys.argv[sys.argv.index("--") + 1]) as fh:
        job = json.load(fh)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    armature, first = import_file(job)
    scene = bpy.context.scene
    action = armature.animation_data.action
    keys = {}
    for fc in action.fcurves:  # data paths: pose.bones["Name"].rotation_quaternion etc.
        if fc.data_path.startswith("pose.bones"):
            name = fc.data_path.split('"')[1]
            keys[name] = max(keys.get(name, 0), len(fc.keyframe_points))
    positions = []
    for f in range(job["frames"]):
        scene.frame_set(first + f)
        world = armature.matrix_world
        row = []
        for bone, end in job["points"]:
            pb = armature.pose.bones[bone]
            row.append(list(world @ (pb.head if end == "head" else pb.tail)))
        positions.append(row)
    out = {
        "blender": bpy.app.version_string,
        "scene_fps": scene.render.fps / scene.render.fps_base,
        "action_range": list(action.frame_range),
        "bones": [b.name for b in armature.data.bones],
        "keys": keys,
        "meshes": [o.name for o in scene.objects if o.type == "MESH"],
        "positions": positions,
    }
    with open(job["out"], "w") as fh:
        json.dump(out, fh)


main()
