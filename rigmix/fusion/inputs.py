"""From characters and a composition plan to the plain-array inputs of :func:`fuse_surfaces`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..sparse_weights import influence_matrix
from .fuse import FusionAction, FusionInput

__all__ = ["MAX_DENSE_WEIGHT_ENTRIES", "check_dense_weights", "fusion_input", "fusion_inputs_from_plan"]

#: The most entries (vertices x joints) of a dense skin-weight matrix compose allocates. Skin
#: weights are held per influence (:mod:`rigmix.sparse_weights`) from the reader to the written
#: file, and the junction band's rows are dense only over the band; what still solves over the whole
#: fused surface with every output joint holds a dense ``(N, J_R)`` float64 matrix (8 bytes an
#: entry, several copies at once): the junction fill (:func:`rigmix.weights.blend.fill_junction`,
#: when some junction vertex is not matched), the seam smoothing
#: (:func:`rigmix.weights.blend.smooth_seam`, ``[weights] smoothing > 0``) and the harmonic
#: continuation of far, jumping closest-point rows (:func:`rigmix.weights.junction.continue_far_parts`).
#: Each is checked by :func:`check_dense_weights` before it is allocated: 2**24 entries is 128 MiB
#: a matrix, and keeps compose's peak memory under 2 GB.
MAX_DENSE_WEIGHT_ENTRIES = 2**24


def check_dense_weights(num_vertices: int, num_joints: int, what: str) -> None:
    """Refuse a dense ``(num_vertices, num_joints)`` weight matrix past :data:`MAX_DENSE_WEIGHT_ENTRIES`.

    Parameters
    ----------
    num_vertices, num_joints : int
    what : str
        The object, for the message (e.g. ``"fusion: character 'body'"``).

    Raises
    ------
    InputError
        Naming ``what``, the counts and the fix.
    """
    n = int(num_vertices) * int(num_joints)
    if n > MAX_DENSE_WEIGHT_ENTRIES:
        raise InputError(
            f"{what}: {int(num_vertices)} vertices x {int(num_joints)} joints = {n:,} dense skin-weight entries, "
            f"over the limit of {MAX_DENSE_WEIGHT_ENTRIES:,} (128 MiB a weight matrix); remove the joints that "
            "carry no weight, or use fewer vertices")


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
        ``W`` is a ``(n, J)`` CSR matrix of the meshes' influences (memory ``O(n k)``, values
        those of the dense matrix); ``mesh_of_vertex`` indexes ``character.meshes``; UVs (set 0)
        and normals are given only when every skinned mesh has them.
    """
    J = character.skeleton.num_joints
    Vs, Fs, mv, uvs, nrm, col, rows, cols, vals = [], [], [], [], [], [], [], [], []
    base = 0
    meshes = [(k, m) for k, m in enumerate(character.meshes) if m.skinned and len(m.faces)]
    n = sum(len(m.positions) for _, m in meshes)
    for k, m in meshes:
        Vs.append(np.asarray(m.positions, np.float64))
        Fs.append(np.asarray(m.faces, np.int64) + base)
        rows.append(base + np.repeat(np.arange(len(m.positions)), m.joints.shape[1]))  # as Mesh.dense_weights
        cols.append(m.joints.ravel())
        vals.append(m.weights.ravel())
        mv.append(np.full(len(m.positions), k, np.int64))
        uvs.append(m.uvs[0] if m.uvs else None)
        nrm.append(m.normals)
        col.append(m.colors)
        base += len(m.positions)
    if not meshes:
        z = np.zeros((0, 3))
        return FusionInput(z, np.zeros((0, 3), np.int64), influence_matrix([], [], [], (0, J)), np.asarray(used, bool),
                           name=name, parents=np.asarray(character.skeleton.parents, np.int64),
                           joint_positions=character.skeleton.rest_worlds()[:, :3, 3])
    W = influence_matrix(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals), (n, J))

    def cat(parts):
        return np.concatenate(parts) if all(p is not None for p in parts) else None

    colors = None
    if any(c is not None for c in col):
        colors = np.concatenate([c if c is not None else np.ones((len(v), 4)) for c, v in zip(col, Vs)])
    return FusionInput(
        V=np.concatenate(Vs), F=np.concatenate(Fs), W=W, used=np.asarray(used, bool),
        mesh_of_vertex=np.concatenate(mv), uvs=cat(uvs), normals=cat(nrm), colors=colors,
        name=name or character.name, parents=np.asarray(character.skeleton.parents, np.int64),
        joint_positions=character.skeleton.rest_worlds()[:, :3, 3],
    )


def fusion_inputs_from_plan(plan):
    """Fusion inputs and actions of a composition plan (:class:`rigmix.operations.Plan`).

    Parameters
    ----------
    plan : rigmix.operations.Plan

    Returns
    -------
    inputs : list of FusionInput
        One per character id, in ``plan.positioned`` order; a ``replace``'s target has its fused
        joint marked ``replaced``.
    actions : list of FusionAction
        ``replace`` in blend mode -> ``"replace"``; ``attach`` and ``replace`` in union mode ->
        ``"attach"``; ``remove`` adds no action (its cut is capped).
    ids : list of str
        The character id of each input.
    """
    ids = list(plan.positioned)
    index = {cid: i for i, cid in enumerate(ids)}
    inputs = [fusion_input(plan.positioned[cid], plan.used[cid], name=cid) for cid in ids]
    # the target's fused joint of a replace: its rigid pieces go with the part the source replaces
    for a in plan.actions:
        if a.op == "replace" and a.source is not None and a.source != a.target:
            x = inputs[index[a.target]]
            replaced = np.zeros(len(x.used), bool) if x.replaced is None else x.replaced.copy()
            replaced[a.target_joint] = True
            inputs[index[a.target]] = replace(x, replaced=replaced)
    actions = []
    for a in plan.actions:
        if a.op == "remove" or a.source is None:
            continue
        kind = "replace" if (a.op == "replace" and (a.mode or "blend") == "blend") else "attach"
        if a.source == a.target:
            continue  # a character composed with itself needs no fusion between two copies
        actions.append(FusionAction(kind, index[a.target], index[a.source]))
    return inputs, actions, ids
