"""From characters and a composition plan to the plain-array inputs of :func:`fuse_surfaces`."""

from __future__ import annotations

import numpy as np

from .fuse import FusionAction, FusionInput

__all__ = ["fusion_input", "fusion_inputs_from_plan"]


def fusion_input(character, used, *, name: str = "") -> FusionInput:
    """The skinned meshes of a character, concatenated, as one :class:`FusionInput`.

    Parameters
    ----------
    character : rigmix.character.Character
        Positions are taken as they are: pass a positioned character (``Plan.positioned``:
        world space at rest, bind = rest), or any character whose meshes are all in the same
        space when composing it with itself.
    used : (J,) bool array
        Joints kept in the output.

    Returns
    -------
    FusionInput
        ``mesh_of_vertex`` indexes ``character.meshes``; UVs (set 0) and normals are given only
        when every skinned mesh has them.
    """
    J = character.skeleton.num_joints
    Vs, Fs, Ws, mv, uvs, nrm, col = [], [], [], [], [], [], []
    base = 0
    meshes = [(k, m) for k, m in enumerate(character.meshes) if m.skinned and len(m.faces)]
    for k, m in meshes:
        Vs.append(np.asarray(m.positions, np.float64))
        Fs.append(np.asarray(m.faces, np.int64) + base)
        Ws.append(m.dense_weights(J))
        mv.append(np.full(len(m.positions), k, np.int64))
        uvs.append(m.uvs[0] if m.uvs else None)
        nrm.append(m.normals)
        col.append(m.colors)
        base += len(m.positions)
    if not meshes:
        z = np.zeros((0, 3))
        return FusionInput(z, np.zeros((0, 3), np.int64), np.zeros((0, J)), np.asarray(used, bool), name=name)

    def cat(parts):
        return np.concatenate(parts) if all(p is not None for p in parts) else None

    colors = None
    if any(c is not None for c in col):
        colors = np.concatenate([c if c is not None else np.ones((len(v), 4)) for c, v in zip(col, Vs)])
    return FusionInput(
        V=np.concatenate(Vs), F=np.concatenate(Fs), W=np.concatenate(Ws), used=np.asarray(used, bool),
        mesh_of_vertex=np.concatenate(mv), uvs=cat(uvs), normals=cat(nrm), colors=colors,
        name=name or character.name,
    )


def fusion_inputs_from_plan(plan):
    """Fusion inputs and actions of a composition plan (:class:`rigmix.operations.Plan`).

    Parameters
    ----------
    plan : rigmix.operations.Plan

    Returns
    -------
    inputs : list of FusionInput
        One per character id, in ``plan.positioned`` order.
    actions : list of FusionAction
        ``replace`` in blend mode -> ``"replace"``; ``attach`` and ``replace`` in union mode ->
        ``"attach"``; ``remove`` adds no action (its cut is capped).
    ids : list of str
        The character id of each input.
    """
    ids = list(plan.positioned)
    index = {cid: i for i, cid in enumerate(ids)}
    inputs = [fusion_input(plan.positioned[cid], plan.used[cid], name=cid) for cid in ids]
    actions = []
    for a in plan.actions:
        if a.op == "remove" or a.source is None:
            continue
        kind = "replace" if (a.op == "replace" and (a.mode or "blend") == "blend") else "attach"
        if a.source == a.target:
            continue  # a character composed with itself needs no fusion between two copies
        actions.append(FusionAction(kind, index[a.target], index[a.source]))
    return inputs, actions, ids
