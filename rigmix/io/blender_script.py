"""Runs inside Blender (``blender -b --factory-startup --python blender_script.py -- IN.glb
REQUEST.json OUT.npz``): imports a glTF with Blender's own importer and writes the deformed
meshes it evaluates. Used by :mod:`rigmix.io.blender_check`; never imports rigmix (Blender's
Python has only numpy).

``REQUEST.json``: ``{"nodes": [glTF mesh node indices], "animations": [{"index": i, "times": [s, ...]},
...]}``. ``OUT.npz``: ``rest/<k>`` ``(n_k, 3)`` and ``anim<i>/<k>`` ``(F, n_k, 3)`` for the
``k``-th requested node, world positions in glTF axes (+Y up), vertices in Blender's order (the
importer's: per primitive, the vertices its indices use, ascending); ``names`` the Blender
object of each node.

The import runs Blender's own operator with its defaults; one of its steps is wrapped
(:func:`capture_import`) to record what the finished scene no longer shows: the rest pose the
importer gives the bones (the glTF nodes' rest TRS, before the first animation is made active
and evaluated over it), the Blender object of each glTF node, and the NLA track name of each
animation (one action per animated object). An animation is evaluated by making its action
active, at frame ``time * scene fps``.
"""

import json
import sys

import numpy

numpy.bool = bool  # Blender 3.4's glTF importer still uses the alias NumPy 1.24 removed


def capture_import():
    """Wrap the importer's animation step: returns a dict that, after the import, holds ``rest``
    (armature name -> pose bone values at the glTF rest), ``objects`` (glTF node index -> Blender
    object name) and ``tracks`` (animation index -> NLA track name)."""
    from io_scene_gltf2.blender.imp import gltf2_blender_scene as scene_module
    from io_scene_gltf2.blender.imp.gltf2_blender_vnode import VNode

    captured = {}
    create_animations = scene_module.BlenderScene.create_animations

    def wrapped(gltf):
        import bpy

        captured["rest"] = {o.name: pose_values(o) for o in bpy.data.objects if o.type == "ARMATURE"}
        captured["objects"] = {i: v.blender_object.name for i, v in gltf.vnodes.items()
                               if isinstance(i, int) and v.type == VNode.Object and v.blender_object is not None}
        captured["tracks"] = [a.track_name for a in gltf.data.animations or []]
        create_animations(gltf)

    scene_module.BlenderScene.create_animations = staticmethod(wrapped)
    return captured


def pose_values(armature):
    """Per pose bone: location, rotation mode, quaternion, Euler angles, scale (copies)."""
    return [(b.location.copy(), b.rotation_mode, b.rotation_quaternion.copy(), b.rotation_euler.copy(),
             b.scale.copy()) for b in armature.pose.bones]


def evaluated_positions(obj):
    """World positions ``(n, 3)`` of a mesh object after its modifiers (the armature), glTF axes."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    mesh = ev.to_mesh()
    co = numpy.empty(len(mesh.vertices) * 3, dtype=numpy.float64)
    mesh.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    M = numpy.array(ev.matrix_world, dtype=numpy.float64)
    P = co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
    return numpy.stack([P[:, 0], P[:, 2], -P[:, 1]], axis=1)  # Blender Z-up -> glTF Y-up


def set_action(armatures, track, poses):
    """Make the action of NLA track ``track`` active on every armature (``None``: no action), the
    pose reset to the one the importer left first."""
    for arm in armatures:
        for bone, (loc, mode, quat, euler, scale) in zip(arm.pose.bones, poses[arm.name]):
            bone.location, bone.rotation_mode = loc, mode
            bone.rotation_quaternion, bone.rotation_euler, bone.scale = quat, euler, scale
        data = arm.animation_data
        if data is None:
            continue
        data.action = None
        for t in data.nla_tracks:
            if track is not None and t.name == track and t.strips:
                data.action = t.strips[0].action


def main(argv):
    import bpy

    glb, request_path, out_path = argv
    with open(request_path) as f:
        request = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    captured = capture_import()
    bpy.ops.import_scene.gltf(filepath=glb)
    scene = bpy.context.scene
    fps = scene.render.fps / scene.render.fps_base
    objects = []
    for i in request["nodes"]:
        obj = bpy.data.objects.get(captured["objects"].get(int(i), ""))
        if obj is None or obj.type != "MESH":
            raise SystemExit("blender_script: glTF node %d is no mesh object after import" % int(i))
        objects.append(obj)
    armatures = [o for o in scene.objects if o.type == "ARMATURE"]
    poses = captured["rest"]
    out = {"names": numpy.array([o.name for o in objects])}
    set_action(armatures, None, poses)
    scene.frame_set(0)
    for k, obj in enumerate(objects):
        out["rest/%d" % k] = evaluated_positions(obj)
    for req in request["animations"]:
        i = int(req["index"])
        set_action(armatures, captured["tracks"][i], poses)
        frames = [[] for _ in objects]
        for t in req["times"]:
            f = float(t) * fps
            whole = int(numpy.floor(f))
            scene.frame_set(whole, subframe=f - whole)
            for k, obj in enumerate(objects):
                frames[k].append(evaluated_positions(obj))
        for k in range(len(objects)):
            out["anim%d/%d" % (i, k)] = numpy.array(frames[k]).reshape(len(req["times"]), -1, 3)
    numpy.savez(out_path, **out)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:])
