"""glTF 2.0 / GLB -> :class:`rigmix.character.Character` (the mapping and repair rules are in
:mod:`rigmix.io.gltf`'s docstring).

The reader is a flat list of passes over a :class:`rigmix.io.accessors.Document`, each fixing
one mismatch between glTF and the domain model:

1. ``_node_graph``: parents, local and world matrices of every node (cycles rejected).
2. ``_choose_skin``: the skin with most joints; other skins merged when their joints are a
   subset (their bind space mapped onto the main one), otherwise UnsupportedError.
3. ``_skeleton``: joints (plus non-joint nodes between joints) in a stable topological order,
   unique names, rest TRS, inverse binds, anchors above the roots.
4. ``_meshes``: primitives -> ``Mesh`` (skinned) or ``Prop`` (rigid/static); weights repaired.
5. ``_clips``: channels on joints -> ``Track``.
6. ``read_materials`` (:mod:`rigmix.io.gltf_materials`): materials and base colour textures.

The weight repairs are in :mod:`rigmix.io.repair`.
"""

from __future__ import annotations

import logging

import numpy as np

from ..character import Anchor, Character, Clip, Mesh, Prop, Skeleton, Track
from ..errors import RigmixError, UnsupportedError
from ..rig import topological_order, unique_names
from ..transforms import matrix_to_trs, quat_normalize, trs_to_matrix
from .accessors import Document, load_document
from .gltf_materials import read_materials
from .repair import fill_empty_rows, repair_weights

__all__ = ["read_gltf"]

logger = logging.getLogger(__name__)



class _Log:
    """Collects repair warnings: each is logged and kept for ``Character.warnings``."""

    def __init__(self, name: str):
        self.name = name
        self.items: list[str] = []

    def __call__(self, message: str) -> None:
        text = f"{self.name}: {message}"
        logger.warning(text)
        self.items.append(text)


def read_gltf(path) -> Character:
    """Read a glTF 2.0 file (``.glb``, or ``.gltf`` with embedded or external resources).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Character
        Skeleton in topological order, skinned meshes, props, clips, materials; defects that
        were repaired are listed in ``Character.warnings`` (and logged).

    Raises
    ------
    InputError
        The file cannot be read (truncated, corrupt JSON, out-of-range data...).
    UnsupportedError
        Valid glTF that cannot be mapped (several skins over different joint sets).
    """
    doc = load_document(path)
    log = _Log(doc.name)
    try:
        return _read(doc, log)
    except RigmixError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, IndexError, OverflowError) as exc:
        # A JSON value of the wrong type somewhere we did not check explicitly.
        raise doc.error(f"malformed glTF ({type(exc).__name__}: {exc})") from None


#: Required extensions without which the geometry cannot be read.
UNREADABLE_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression")
#: The only extension rigmix reads that a file may list in ``extensionsRequired``: its integer
#: attributes are read by the accessor reader. Any other required extension is refused, as the
#: glTF 2.0 specification asks of a loader that does not support it (section 3.12).
SUPPORTED_REQUIRED_EXTENSIONS = ("KHR_mesh_quantization",)
#: A quaternion whose length is off 1 by more than this is reported when normalized: the Khronos
#: validator reports ROTATION_NON_UNIT from an error of about 5e-3 on the length, and SimpleSkin's
#: keys (3-digit decimals) are 2.3e-4 off.
UNIT_TOLERANCE = 2e-3
#: Vertex attribute -> the (componentType, normalized) pairs glTF 2.0 allows (section 3.7.2.1).
ATTRIBUTE_TYPES = {
    "POSITION": {(5126, False)},
    "NORMAL": {(5126, False)},
    "TEXCOORD": {(5126, False), (5121, True), (5123, True)},
    "COLOR": {(5126, False), (5121, True), (5123, True)},
    "WEIGHTS": {(5126, False), (5121, True), (5123, True)},
}
#: The pairs ``KHR_mesh_quantization`` adds.
QUANTIZED_TYPES = {
    "POSITION": {(c, n) for c in (5120, 5121, 5122, 5123) for n in (False, True)},
    "NORMAL": {(5120, True), (5122, True)},
    "TEXCOORD": {(5120, False), (5120, True), (5121, False), (5122, False), (5122, True), (5123, False)},
}
_COMPONENT_NAMES = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                    5125: "UNSIGNED_INT", 5126: "FLOAT"}


def _check_extensions(doc: Document) -> None:
    """Refuse any ``extensionsRequired`` entry rigmix cannot read (compressed geometry named)."""
    required = doc.items("extensionsRequired")
    for ext in required:
        if not isinstance(ext, str):
            raise doc.error(f"extensionsRequired must list extension names, got {ext!r}")
        if ext in UNREADABLE_EXTENSIONS:
            raise UnsupportedError(
                f"{doc.name}: compressed geometry ({ext}) is not supported: re-export the file "
                "without mesh compression (e.g. gltf-transform copy, or Blender without Draco)"
            )
        if ext not in SUPPORTED_REQUIRED_EXTENSIONS:
            raise UnsupportedError(
                f"{doc.name}: the file requires extension {ext!r}, which rigmix cannot read (it reads "
                f"{', '.join(SUPPORTED_REQUIRED_EXTENSIONS)}): re-export the file without it"
            )


def _check_scenes(doc: Document, graph: "_Graph", log) -> None:
    """``scene`` and every ``scenes[k].nodes`` refer to existing root nodes, each once; an empty
    ``nodes`` list (out of spec) is reported."""
    scenes = doc.items("scenes")
    if "scene" in doc.json:
        doc.get("scenes", doc.json["scene"], "'scene'")
    N = len(graph.parent)
    for k in range(len(scenes)):
        roots = doc.get("scenes", k).get("nodes", [])
        if not isinstance(roots, list):
            raise doc.error(f"scenes[{k}].nodes must be a JSON array")
        if not roots and "nodes" in doc.get("scenes", k):
            log(f"scenes[{k}].nodes is empty, which glTF 2.0 forbids (omit it instead): the scene shows nothing; "
                "rigmix reads every node")
        for n in roots:
            if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n < N:
                raise doc.error(f"scenes[{k}].nodes refers to nodes[{n!r}], which does not exist: the file has "
                                f"{N} nodes")
            if graph.parent[n] >= 0:
                raise doc.error(f"scenes[{k}].nodes lists nodes[{n}], a child of nodes[{graph.parent[n]}]: "
                                "a scene lists root nodes only")
        if len(set(roots)) != len(roots):
            raise doc.error(f"scenes[{k}].nodes lists the same node twice")


def _quantized(doc: Document) -> bool:
    used = doc.json.get("extensionsUsed", [])
    return isinstance(used, list) and "KHR_mesh_quantization" in used + doc.items("extensionsRequired")


def _check_attribute_type(doc: Document, index: int, key: str, label: str) -> None:
    """Refuse a vertex attribute stored in a component type glTF 2.0 does not allow for it."""
    semantic = key.split("_")[0] if key.split("_")[-1].isdigit() else key
    allowed = ATTRIBUTE_TYPES.get(semantic)
    if allowed is None:
        return
    acc = doc.get("accessors", index)
    pair = (acc.get("componentType"), bool(acc.get("normalized", False)))
    if pair in allowed or (pair in QUANTIZED_TYPES.get(semantic, ()) and _quantized(doc)):
        return
    ctype = _COMPONENT_NAMES.get(pair[0], repr(pair[0]))
    kind = f"{'normalized ' if pair[1] else ''}{ctype}"
    hint = " without KHR_mesh_quantization" if semantic in QUANTIZED_TYPES and pair in QUANTIZED_TYPES[semantic] else ""
    raise doc.error(f"{label}: {key} is stored as {kind}{hint}, which glTF 2.0 does not allow: re-export it "
                    "(FLOAT, or the normalized integer types the specification lists)")


def _read(doc: Document, log: _Log) -> Character:
    _check_extensions(doc)
    graph = _node_graph(doc, log)
    _check_scenes(doc, graph, log)
    skins = _choose_skin(doc, graph)
    skeleton, joint_of_node = _skeleton(doc, graph, skins, log)
    materials = read_materials(doc, log)
    meshes, props = _meshes(doc, graph, skins, skeleton, joint_of_node, len(materials), log)
    clips = _clips(doc, joint_of_node, skeleton, log)
    for label in doc.bounds_mismatch:
        log(f"{label}: declared min/max differ from the data (out of spec; recomputed when written)")
    return Character(
        name=doc.path.stem, skeleton=skeleton, meshes=meshes, clips=clips, materials=materials,
        props=props, source=str(doc.path), warnings=tuple(log.items),
    )


# --------------------------------------------------------------------------- 1. node graph


class _Graph:
    """Node hierarchy: ``parent`` (N,), ``local`` (N,4,4), ``world`` (N,4,4), ``depth`` (N,)."""

    def __init__(self, parent, local, world, depth, names):
        self.parent, self.local, self.world, self.depth, self.names = parent, local, world, depth, names


def _node_local(doc: Document, i: int, node: dict) -> np.ndarray:
    if "matrix" in node:
        m = np.asarray(node["matrix"], dtype=np.float64)
        if m.shape != (16,) or not np.all(np.isfinite(m)):
            raise doc.error(f"nodes[{i}].matrix must be 16 finite numbers")
        return m.reshape(4, 4).T  # column-major in the file
    t = np.asarray(node.get("translation", [0, 0, 0]), dtype=np.float64)
    r = np.asarray(node.get("rotation", [0, 0, 0, 1]), dtype=np.float64)
    s = np.asarray(node.get("scale", [1, 1, 1]), dtype=np.float64)
    if t.shape != (3,) or r.shape != (4,) or s.shape != (3,) or not all(np.all(np.isfinite(a)) for a in (t, r, s)):
        raise doc.error(f"nodes[{i}] has a malformed translation, rotation or scale")
    return trs_to_matrix(t, r, s)


def _node_locals(doc: Document, nodes: list) -> np.ndarray:
    """Local matrices ``(N, 4, 4)`` of all nodes, in one vectorized pass when every node is
    well-formed (a 100k-joint file in well under a second); else node by node, which names the
    first malformed node."""
    try:
        is_m = np.array(["matrix" in n for n in nodes], dtype=bool)
        t = np.array([n.get("translation", (0, 0, 0)) for n in nodes], dtype=np.float64).reshape(-1, 3)
        r = np.array([n.get("rotation", (0, 0, 0, 1)) for n in nodes], dtype=np.float64).reshape(-1, 4)
        s = np.array([n.get("scale", (1, 1, 1)) for n in nodes], dtype=np.float64).reshape(-1, 3)
        m = np.array([n["matrix"] for n in nodes if "matrix" in n], dtype=np.float64).reshape(-1, 16)
        ok = len(t) == len(r) == len(s) == len(nodes) and all(np.all(np.isfinite(a)) for a in (t, r, s, m))
    except (TypeError, ValueError, AttributeError):
        ok = False
    if not ok:
        return np.stack([_node_local(doc, i, n) for i, n in enumerate(nodes)]) if nodes else np.zeros((0, 4, 4))
    local = trs_to_matrix(t, r, s)
    local[is_m] = m.reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major in the file
    return local


def _unit_rotations(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalize finite quaternions ``(n, 4)`` without overflow.

    Returns
    -------
    unit : (n, 4) float64
        ``q / |q|`` (bit-identical to :func:`rigmix.transforms.quat_normalize` where ``|q|`` is
        finite), scaled by its largest component first where ``|q|`` overflows; identity where
        ``q`` is zero.
    zero : (n,) bool
        Zero quaternions (made identity).
    off : (n,) bool
        Non-zero quaternions whose length was off 1 by more than :data:`UNIT_TOLERANCE`.
    """
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(q, axis=-1)
    huge = ~np.isfinite(norm)
    if huge.any():  # [1e300, 0, 0, 1e300]: |q| is inf, q / |q| would be 0
        q = q.copy()
        q[huge] /= np.abs(q[huge]).max(axis=-1, keepdims=True)
        norm = np.linalg.norm(q, axis=-1)
    unit = quat_normalize(q)
    zero = norm <= 1e-12
    off = ~zero & (huge | (np.abs(norm - 1.0) > UNIT_TOLERANCE))
    return unit, zero, off


def _rest_rotations(doc: Document, nodes: list, log) -> list:
    """``nodes`` with zero, overflowing or non-unit rest rotations made unit (each reported)."""
    index = [i for i, n in enumerate(nodes) if isinstance(n, dict) and "rotation" in n]
    try:
        q = np.array([nodes[i]["rotation"] for i in index], dtype=np.float64).reshape(len(index), 4)
    except (TypeError, ValueError):
        return nodes  # malformed: _node_locals names the node
    if not np.all(np.isfinite(q)):
        return nodes
    unit, zero, off = _unit_rotations(q)
    if not (zero.any() or off.any()):
        return nodes
    nodes = list(nodes)
    for k in np.flatnonzero(zero | off):
        i = index[k]
        label = f"nodes[{i}]" + (f" {nodes[i]['name']!r}" if isinstance(nodes[i].get("name"), str) else "")
        how = "is zero: replaced by the identity" if zero[k] else "is not unit: normalized"
        log(f"{label}: rest rotation quaternion {how}")
        nodes[i] = dict(nodes[i], rotation=unit[k].tolist())
    return nodes


def _node_graph(doc: Document, log) -> _Graph:
    nodes = doc.items("nodes")
    N = len(nodes)
    parent = np.full(N, -1, dtype=np.int64)
    for i in range(N):
        node = doc.get("nodes", i)
        for c in node.get("children", []):
            if not isinstance(c, int) or not 0 <= c < N or c == i:
                raise doc.error(f"nodes[{i}] has an invalid child {c!r} (the file has {N} nodes)")
            if parent[c] >= 0:
                raise doc.error(f"nodes[{c}] is a child of both nodes[{parent[c]}] and nodes[{i}]")
            parent[c] = i
    depth = np.full(N, -1, dtype=np.int64)
    for i in range(N):
        chain, k = [], i
        while k >= 0 and depth[k] < 0:
            chain.append(k)
            if len(chain) > N:
                raise doc.error(f"the node hierarchy has a cycle through nodes[{i}]")
            k = parent[k]
        d = depth[k] if k >= 0 else -1
        for c in reversed(chain):
            d += 1
            depth[c] = d
    _check_node_transforms(doc, nodes, log)
    local = _node_locals(doc, _rest_rotations(doc, nodes, log))
    world = np.empty_like(local)
    for i in np.argsort(depth, kind="stable"):
        world[i] = local[i] if parent[i] < 0 else world[parent[i]] @ local[i]
    for i, n in enumerate(nodes):
        if "name" in n and not isinstance(n["name"], str):
            log(f"nodes[{i}].name is {type(n['name']).__name__} {n['name']!r}, not a string: ignored")
    names = [n.get("name") if isinstance(n.get("name"), str) and n.get("name") else None for n in nodes]
    return _Graph(parent, local, world, depth, names)


def _check_node_transforms(doc: Document, nodes: list, log) -> None:
    """Warn about node transforms glTF 2.0 forbids but that have one reading: a ``matrix``
    beside ``translation``/``rotation``/``scale`` (the matrix is used, as three.js and Blender
    do) and a singular ``matrix`` (its subtree collapses; a joint there is refused later)."""
    for i, n in enumerate(nodes):
        if not isinstance(n, dict) or "matrix" not in n:
            continue
        trs = [k for k in ("translation", "rotation", "scale") if k in n]
        if trs:
            log(f"nodes[{i}] has both a matrix and {', '.join(trs)}, which glTF 2.0 forbids: the matrix is used")
        try:
            m = np.asarray(n["matrix"], np.float64).reshape(4, 4).T
        except (TypeError, ValueError):
            continue  # malformed: refused with its name by _node_local
        with np.errstate(all="ignore"):
            singular = not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:3, :3])) <= 1e-12 * max(
                float(np.abs(m[:3, :3]).max()) ** 3, 1e-300)
        if singular and np.all(np.isfinite(m)):
            log(f"nodes[{i}].matrix is singular (a zero scale): everything under it collapses to a point")


# --------------------------------------------------------------------------- 2. skins


class _Skin:
    """One glTF skin mapped onto the skeleton: ``nodes`` (n,), ``ibm`` (n,4,4), ``bind_map``
    (4,4) taking its bind space to the main skin's (identity for the main skin)."""

    def __init__(self, index, nodes, ibm):
        self.index, self.nodes, self.ibm = index, nodes, ibm
        self.bind_map = np.eye(4)
        self.to_joint = None  # (n,) skeleton joint index of each skin joint, set by _skeleton


def _read_skin(doc: Document, i: int) -> _Skin:
    skin = doc.get("skins", i)
    joints = skin.get("joints")
    N = len(doc.items("nodes"))
    if not isinstance(joints, list) or not joints:
        raise doc.error(f"skins[{i}] has no joints")
    if any(not isinstance(j, int) or not 0 <= j < N for j in joints):
        raise doc.error(f"skins[{i}] refers to a node that does not exist (the file has {N} nodes)")
    if len(set(joints)) != len(joints):
        raise doc.error(f"skins[{i}] lists the same node twice in its joints")
    if "inverseBindMatrices" in skin:
        m = doc.accessor(skin["inverseBindMatrices"], f"skins[{i}] inverseBindMatrices")
        if m.shape[1] != 16 or len(m) < len(joints):
            raise doc.error(f"skins[{i}] inverseBindMatrices must be {len(joints)} MAT4, got {m.shape}")
        ibm = m[: len(joints)].reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
        _check_inverse_binds(doc, i, joints, ibm)
    else:
        ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4)).copy()
    return _Skin(i, np.asarray(joints, dtype=np.int64), ibm)


#: An inverse bind matrix whose determinant is below this fraction of the product of its column
#: lengths (1 for a rotation, whatever the scale) is singular.
SINGULAR_IBM = 1e-12


def _check_inverse_binds(doc: Document, skin: int, joints: list, ibm: np.ndarray) -> None:
    """Refuse inverse bind matrices ``(n, 4, 4)`` that are not finite, affine and invertible."""

    def refuse(k, problem):
        name = doc.get("nodes", joints[k]).get("name")
        joint = f"joint {name!r}" if isinstance(name, str) and name else f"nodes[{joints[k]}]"
        return doc.error(f"skins[{skin}] inverseBindMatrices[{k}] ({joint}) {problem}: re-export the skin "
                         "from its bind pose")

    bad = ~np.all(np.isfinite(ibm), axis=(1, 2))
    if bad.any():
        raise refuse(int(np.argmax(bad)), "holds NaN or infinite values")
    affine = np.all(np.abs(ibm[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])) <= 1e-6, axis=1)
    if not affine.all():
        raise refuse(int(np.argmin(affine)), "is not affine (its last row must be 0, 0, 0, 1)")
    # scale-free test on the 3x3 part, each matrix divided by its largest entry (no overflow)
    a = ibm[:, :3, :3]
    a = a / np.maximum(np.abs(a).max(axis=(1, 2)), 1e-300)[:, None, None]
    singular = ~(np.abs(np.linalg.det(a)) > SINGULAR_IBM * np.prod(np.linalg.norm(a, axis=1), axis=1))
    if singular.any():
        raise refuse(int(np.argmax(singular)), "is not invertible (zero scale or collapsed axes)")


def _choose_skin(doc: Document, graph: _Graph) -> list[_Skin]:
    """All skins, the main one (most joints, first on ties) first; the others must be subsets."""
    skins = [_read_skin(doc, i) for i in range(len(doc.items("skins")))]
    if not skins:
        return []
    main_i = max(range(len(skins)), key=lambda i: (len(skins[i].nodes), -i))
    main = skins[main_i]
    pos = {int(n): k for k, n in enumerate(main.nodes)}
    for s in skins:
        if s is main:
            continue
        if not set(s.nodes.tolist()) <= pos.keys():
            raise UnsupportedError(
                f"{doc.name}: skins[{s.index}] uses joints outside skins[{main.index}]: rigmix reads one "
                "skeleton per file; export the character with a single armature"
            )
        # Bind space of s -> bind space of main: inv(ibm_main[j]) @ ibm_s[j], the same for all j.
        idx = [pos[int(n)] for n in s.nodes]
        maps = np.linalg.inv(main.ibm[idx]) @ s.ibm
        scale = max(1.0, float(np.abs(maps[:, :3, 3]).max()))
        if np.abs(maps - maps[0]).max() > 1e-4 * scale:
            raise UnsupportedError(
                f"{doc.name}: skins[{s.index}] binds the joints of skins[{main.index}] in a different "
                "pose: rigmix reads one bind pose per file; re-export with one skin"
            )
        s.bind_map = maps[0]
    return [main] + [s for s in skins if s is not main]


# --------------------------------------------------------------------------- 3. skeleton


def _unique(names: list[str]) -> tuple[list[str], list[tuple[str, str]]]:
    """Make names unique: later duplicates get ``.1``, ``.2``... (:func:`rigmix.rig.unique_names`);
    returns the new names and the ``(old, new)`` renames."""
    out = unique_names(names, suffix=".{}")
    return out, [(n, new) for n, new in zip(names, out) if new != n]


def _joint_members(graph: _Graph, skin_nodes, log) -> set[int]:
    """The skin's joints plus the non-joint nodes lying on a path between two of them.

    Such a node's transform moves the chain below it, so it becomes a joint (without weight).
    """
    skin = {int(n) for n in skin_nodes}
    members = set(skin)
    below_joint: dict[int, bool] = {}  # non-joint node -> has a skin joint above it (memo: linear time)
    for j in skin:
        chain, k = [], int(graph.parent[j])
        while k >= 0 and k not in skin and k not in below_joint:
            chain.append(k)
            k = int(graph.parent[k])
        above = k >= 0 and (k in skin or below_joint[k])
        below_joint.update(dict.fromkeys(chain, above))
        if above:
            members.update(chain)
    for n in sorted(members - skin):
        log(f"node '{graph.names[n] or n}' lies between joints but is not in the skin: added as a joint")
    return members


def _topological_order(graph: _Graph, members: set[int], skin_nodes, joint_parent) -> list[int]:
    """Parents-first order of the joint nodes, as close to the skin's order as possible.

    Each node is keyed by the smallest skin position in its subtree (added nodes have none of
    their own) and a heap-ordered topological sort emits the forest: a skin already listed
    parents-first keeps its order exactly.
    """
    skin_pos = {int(n): k for k, n in enumerate(skin_nodes)}
    key = {n: skin_pos.get(n, len(skin_pos) + n) for n in members}
    for n in sorted(members, key=lambda n: -graph.depth[n]):  # children before parents
        p = joint_parent(n)
        if p >= 0:
            key[p] = min(key[p], key[n])
    return topological_order(members, joint_parent, key.__getitem__)


def _anchors(graph: _Graph, root_nodes: list[int]) -> tuple[tuple[Anchor, ...], dict[int, int]]:
    """The non-joint ancestors of the root joints as anchors (parents first, then node index);
    returns them and ``{node index: anchor index}``."""
    nodes = set()
    for n in root_nodes:
        k = int(graph.parent[n])
        while k >= 0 and k not in nodes:  # a node already seen has its ancestors in too
            nodes.add(k)
            k = int(graph.parent[k])
    order = sorted(nodes, key=lambda n: (graph.depth[n], n))
    index = {n: a for a, n in enumerate(order)}
    names, _ = _unique([graph.names[n] or f"node_{n}" for n in order])
    anchors = tuple(Anchor(names[a], graph.local[n], index.get(int(graph.parent[n]), -1)) for a, n in enumerate(order))
    return anchors, index


def _check_skeleton_root(doc, graph: _Graph, skin: _Skin, root_nodes: list[int], log) -> None:
    """Report a ``skin.skeleton`` that is not a common root of the joints (it is never used)."""
    sroot = doc.get("skins", skin.index).get("skeleton")
    if sroot is None:
        return
    valid = isinstance(sroot, int) and 0 <= sroot < len(graph.parent)
    if valid and all(_is_ancestor(graph.parent, sroot, n) for n in root_nodes):
        return
    label = f"'{graph.names[sroot] or sroot}'" if valid else repr(sroot)
    log(f"skins[{skin.index}].skeleton ({label}) is not a common root of the joints: ignored")


def _skeleton(doc, graph: _Graph, skins: list[_Skin], log) -> tuple[Skeleton, dict]:
    """Joints in topological order; returns the skeleton and ``{node index: joint index}``."""
    if not skins:
        empty = np.zeros((0, 3))
        return Skeleton((), np.zeros(0), empty, np.zeros((0, 4)), empty, np.zeros((0, 4, 4))), {}
    main = skins[0]
    members = _joint_members(graph, main.nodes, log)

    def joint_parent(n):
        k = graph.parent[n]
        return int(k) if k >= 0 and k in members else -1

    order = _topological_order(graph, members, main.nodes, joint_parent)
    joint_of_node = {n: j for j, n in enumerate(order)}
    for sk in skins:
        sk.to_joint = np.array([joint_of_node[int(n)] for n in sk.nodes], dtype=np.int64)
    names, renamed = _unique([graph.names[n] or f"joint_{n}" for n in order])
    for old, new in renamed:
        log(f"joint name '{old}' is used twice: renamed '{new}'")
    parents = np.array([joint_of_node.get(joint_parent(n), -1) for n in order])
    t, r, s = matrix_to_trs(graph.local[order])
    skin_pos = {int(n): k for k, n in enumerate(main.nodes)}
    ibm = np.stack([main.ibm[skin_pos[n]] if n in skin_pos else np.linalg.inv(graph.world[n]) for n in order])
    root_nodes = [n for n in order if joint_parent(n) < 0]
    _check_skeleton_root(doc, graph, main, root_nodes, log)
    anchors, anchor_index = _anchors(graph, root_nodes)
    root_anchor = np.array(
        [anchor_index.get(int(graph.parent[n]), -1) if joint_parent(n) < 0 else -1 for n in order], dtype=np.int64
    )
    return Skeleton(tuple(names), parents, t, r, s, ibm, anchors, root_anchor), joint_of_node


def _is_ancestor(parent, a: int, n: int) -> bool:
    """Whether node ``a`` is ``n`` or one of its ancestors."""
    while n >= 0:
        if n == a:
            return True
        n = parent[n]
    return False


# --------------------------------------------------------------------------- 4. meshes


def _triangles(doc, mode: int, idx: np.ndarray, label: str, log) -> np.ndarray | None:
    """Triangle list ``(m, 3)`` from the primitive's index list, or None for points/lines."""
    if mode == 4:
        if len(idx) % 3:
            log(f"{label}: {len(idx)} indices is not a multiple of 3: the last {len(idx) % 3} dropped")
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if mode == 5:  # strip: odd triangles swap their first two corners to keep the winding
        i = np.arange(max(len(idx) - 2, 0))
        odd = i % 2
        tri = np.stack([idx[i + odd], idx[i + 1 - odd], idx[i + 2]], axis=1)
    elif mode == 6:  # fan
        i = np.arange(max(len(idx) - 2, 0))
        tri = np.stack([idx[i + 1], idx[i + 2], np.full_like(i, idx[0] if len(idx) else 0)], axis=1)
    elif mode in (0, 1, 2, 3):
        log(f"{label}: points/lines primitive (mode {mode}) skipped")
        return None
    else:
        raise doc.error(f"{label} has an unknown primitive mode {mode!r}")
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    return tri[keep]


def _read_primitive(doc, prim: dict, label: str, njoints: int | None, log) -> dict | None:
    """Arrays of one primitive; ``njoints`` is the skin's joint count (None if not skinned)."""
    attrs = prim.get("attributes", {})
    if "POSITION" not in attrs:
        log(f"{label} has no POSITION: skipped")
        return None
    V = doc.accessor(attrs["POSITION"], f"{label} POSITION")
    _check_declared_bounds(doc, attrs["POSITION"], f"{label} POSITION", log)
    _check_attribute_type(doc, attrs["POSITION"], "POSITION", label)
    n = len(V)
    if V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise doc.error(f"{label}: POSITION must be finite VEC3")

    def attr(key, comps):
        a = doc.accessor(attrs[key], f"{label} {key}")
        _check_attribute_type(doc, attrs[key], key, label)
        if len(a) != n or a.shape[1] not in comps:
            raise doc.error(f"{label}: {key} has {len(a)} x {a.shape[1]} values, expected {n} x {comps}")
        return a

    if "indices" in prim:
        idx = doc.accessor(prim["indices"], f"{label} indices")
        if idx.dtype.kind != "u" or idx.shape[1] != 1:
            raise doc.error(f"{label}: indices must be unsigned integer scalars")
        idx = idx[:, 0].astype(np.int64)
        if len(idx) and idx.max() >= n:
            raise doc.error(f"{label}: index {int(idx.max())} is past the vertex count {n}")
    else:
        idx = np.arange(n, dtype=np.int64)
    F = _triangles(doc, prim.get("mode", 4), idx, label, log)
    if F is None:
        return None
    if prim.get("targets"):
        log(f"{label}: {len(prim['targets'])} morph targets ignored")
    out = {"positions": V, "faces": F, "material": prim.get("material", -1)}
    if "NORMAL" in attrs:
        out["normals"] = attr("NORMAL", (3,))
    uvs, k = [], 0
    while f"TEXCOORD_{k}" in attrs:
        uvs.append(attr(f"TEXCOORD_{k}", (2,)))
        k += 1
    out["uvs"] = tuple(uvs)
    if "COLOR_0" in attrs:
        c = attr("COLOR_0", (3, 4))
        out["colors"] = np.concatenate([c, np.ones((n, 1))], axis=1) if c.shape[1] == 3 else c
    if njoints is not None and "JOINTS_0" in attrs and "WEIGHTS_0" in attrs:
        J, W, k = [], [], 0
        while f"JOINTS_{k}" in attrs and f"WEIGHTS_{k}" in attrs:
            j = attr(f"JOINTS_{k}", (4,))
            if j.dtype.kind != "u":
                raise doc.error(f"{label}: JOINTS_{k} must be unsigned byte or short")
            J.append(j.astype(np.int64))
            W.append(attr(f"WEIGHTS_{k}", (4,)).astype(np.float64))
            k += 1
        J, W = np.concatenate(J, axis=1), np.concatenate(W, axis=1)
        if J.max() >= njoints:
            raise doc.error(f"{label}: JOINTS refer to joint {int(J.max())} but the skin has {njoints} joints")
        out["joints"], out["weights"] = J, W
    return out


def _meshes(doc, graph: _Graph, skins, skeleton: Skeleton, joint_of_node, nmat, log):
    """Skinned primitives -> Mesh, unskinned ones -> Prop (rigid on a joint, or static)."""
    skin_by_index = {s.index: s for s in skins}
    parts, props = [], []
    names_raw = []
    rest_world = {n: graph.world[n] for n in joint_of_node}
    for i, node in enumerate(doc.items("nodes")):
        if "mesh" not in node:
            continue
        mi = node["mesh"]
        mesh = doc.get("meshes", mi, f"nodes[{i}]")
        prims = mesh.get("primitives", [])
        if not prims:
            log(f"meshes[{mi}] has no primitives, which glTF 2.0 forbids: nothing to read from it")
        base = mesh.get("name") or f"mesh_{mi}"
        skin = None
        if "skin" in node:
            doc.get("skins", node["skin"], f"nodes[{i}]")
            skin = skin_by_index[node["skin"]]
        for pi, prim in enumerate(prims):
            extras = prim.get("extras")
            name = extras.get("name") if isinstance(extras, dict) else None
            if not isinstance(name, str) or not name:  # rigmix writes the Mesh name there
                name = base if len(prims) == 1 else f"{base}.{pi}"
            label = f"mesh '{name}'"
            d = _read_primitive(doc, prim, label, None if skin is None else len(skin.nodes), log)
            if d is None:
                continue
            mat = d["material"]
            if not (isinstance(mat, int) and -1 <= mat < nmat):
                raise doc.error(f"{label} refers to materials[{mat!r}], the file has {nmat}")
            if skin is not None and "joints" in d:
                V, N = d["positions"], d.get("normals")
                if not np.allclose(skin.bind_map, np.eye(4)):
                    V = V @ skin.bind_map[:3, :3].T + skin.bind_map[:3, 3]
                    if N is not None:
                        N = N @ np.linalg.inv(skin.bind_map[:3, :3])
                        N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
                d = dict(d, positions=V, normals=N, joints=skin.to_joint[d["joints"]])
                names_raw.append(name)
                parts.append(d)
                continue
            if skin is not None:
                log(f"{label} is on a skinned node but has no JOINTS_0/WEIGHTS_0: read as a static prop")
            # Rigid: follows its nearest joint ancestor, or static in the world.
            k = graph.parent[i]
            while k >= 0 and k not in joint_of_node:
                k = graph.parent[k]
            joint = joint_of_node[k] if k >= 0 else -1
            matrix = graph.world[i] if k < 0 else np.linalg.inv(rest_world[k]) @ graph.world[i]
            props.append((name, d, joint, matrix))

    all_names, _ = _unique(names_raw + [p[0] for p in props])
    for p, nm in zip(parts, all_names):
        p["name"] = nm
    _repair_parts(parts, skeleton, log)

    def build(nm, d, skinned):
        return Mesh(
            name=nm, positions=d["positions"], faces=d["faces"], normals=d.get("normals"),
            uvs=d["uvs"], colors=d.get("colors"), joints=d["joints"] if skinned else None,
            weights=d["weights"] if skinned else None, material=d["material"],
        )

    meshes = tuple(build(p["name"], p, True) for p in parts)
    prop_objs = tuple(
        Prop(build(nm, d, False), joint, matrix)
        for (_, d, joint, matrix), nm in zip(props, all_names[len(parts):])
    )
    return meshes, prop_objs


def _repair_parts(parts: list[dict], skeleton: Skeleton, log) -> None:
    """Apply the weight repairs to every skinned primitive (in place) and report them."""
    for p in parts:
        p["nonfinite"] = ~np.all(np.isfinite(p["weights"]), axis=1)
        p["joints"], p["weights"], p["empty"], counts = repair_weights(p["joints"], p["weights"])
        label = f"mesh '{p['name']}'"
        if counts["duplicate"]:
            log(f"{label}: {counts['duplicate']} vertices with duplicate joint slots: their weights summed")
        if counts["negative"]:
            log(f"{label}: {counts['negative']} vertices with negative weights: clamped to 0")
        if counts["unnormalized"]:
            log(f"{label}: {counts['unnormalized']} vertices with weights not summing to 1: renormalized")
    fill_empty_rows(parts, skeleton, log)


# --------------------------------------------------------------------------- 5. clips


def _clips(doc, joint_of_node, skeleton: Skeleton, log) -> tuple[Clip, ...]:
    clips = []
    raw_names = []
    for ai, anim in enumerate(doc.items("animations")):
        raw_names.append(anim.get("name") or f"clip_{ai}")
    names, renamed = _unique(raw_names)
    for old, new in renamed:
        log(f"animation name '{old}' is used twice: renamed '{new}'")
    for ai, anim in enumerate(doc.items("animations")):
        name = names[ai]
        samplers = anim.get("samplers", [])
        tracks, seen = [], set()
        ignored_nodes, morph = set(), 0
        for ci, ch in enumerate(anim.get("channels", [])):
            target = ch.get("target", {})
            path = target.get("path")
            node = target.get("node")
            if path == "weights":
                morph += 1
                continue
            if node is None or path not in ("translation", "rotation", "scale"):
                if "target" not in ch or path is None:  # required by glTF 2.0; a missing node is legal
                    log(f"animation '{name}' channel {ci} has no target{' path' if 'target' in ch else ''}, "
                        "which glTF 2.0 requires: ignored")
                elif path not in ("translation", "rotation", "scale"):  # an extension's path, or a typo
                    log(f"animation '{name}' channel {ci} animates path {path!r}, not translation, rotation, "
                        "scale or weights: ignored")
                continue
            if node not in joint_of_node:
                ignored_nodes.add(node)
                continue
            j = joint_of_node[node]
            if (j, path) in seen:
                log(f"animation '{name}': second {path} channel on joint '{skeleton.names[j]}' ignored")
                continue
            seen.add((j, path))
            si = ch.get("sampler")
            if not isinstance(si, int) or not 0 <= si < len(samplers):
                raise doc.error(f"animation '{name}' channel {ci} refers to sampler {si!r}, it has {len(samplers)}")
            tracks.append(_track(doc, samplers[si], j, path, f"animation '{name}' sampler {si}", log))
        if morph:
            log(f"animation '{name}': {morph} morph-weight channels ignored")
        if ignored_nodes:
            nn = ", ".join(sorted(f"'{doc.get('nodes', n).get('name', n)}'" for n in ignored_nodes))
            log(f"animation '{name}': channels on non-joint nodes {nn} ignored")
        if not tracks:
            log(f"animation '{name}' animates no joint: dropped")
            continue
        clips.append(Clip(name, tuple(tracks)))
    return tuple(clips)


def _check_declared_bounds(doc, index: int, label: str, log) -> None:
    """Warn when an accessor that glTF 2.0 requires to declare ``min`` and ``max`` (POSITION,
    animation input) declares none: readers that trust the bounds (culling, clip length) get
    them wrong. rigmix computes them from the data, and writes them."""
    acc = doc.get("accessors", index)
    if "min" not in acc or "max" not in acc:
        log(f"{label}: accessors[{index}] declares no min/max, which glTF 2.0 requires here "
            "(computed from the data; written when saved)")


def _track(doc, sampler: dict, joint: int, path: str, label: str, log) -> Track:
    interp = sampler.get("interpolation", "LINEAR")
    if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
        raise doc.error(f"{label} has unknown interpolation {interp!r}")
    times = doc.accessor(sampler.get("input"), f"{label} input")
    ctype = doc.get("accessors", sampler.get("input")).get("componentType")
    if ctype != 5126:  # glTF 2.0 3.11: key times are FLOAT (bytes would read as whole seconds)
        raise doc.error(f"{label}: input (key times) is stored as {_COMPONENT_NAMES.get(ctype, repr(ctype))}, "
                        "which glTF 2.0 does not allow (FLOAT seconds): re-export the clip")
    _check_declared_bounds(doc, sampler.get("input"), f"{label} input", log)
    if times.shape[1] != 1 or not np.all(np.isfinite(times)):
        raise doc.error(f"{label}: input must be finite scalar times")
    times = times[:, 0]
    if len(times) and times.min() < 0:
        raise doc.error(f"{label}: key time {float(times.min())!r} is negative: glTF 2.0 key times start "
                        "at 0 or later (animation.sampler.input, time[0] >= 0); re-export the clip")
    values = doc.accessor(sampler.get("output"), f"{label} output")
    C = 4 if path == "rotation" else 3
    per = 3 if interp == "CUBICSPLINE" else 1
    if values.shape[1] != C or len(values) != per * len(times):
        raise doc.error(
            f"{label}: {path} output has {len(values)} x {values.shape[1]} values for {len(times)} keys, "
            f"expected {per * len(times)} x {C}"
        )
    if not np.all(np.isfinite(values)):
        raise doc.error(f"{label}: {path} output holds NaN or infinite values")
    values = values.reshape(len(times), 3, C) if per == 3 else values
    if np.any(np.diff(times) <= 0):
        times, first = np.unique(times, return_index=True)
        values = values[first]
        log(f"{label}: key times not strictly increasing: sorted, duplicates dropped")
    if path == "rotation" and per == 1:
        values, zero, off = _unit_rotations(values)
        if zero.any():
            log(f"{label}: {int(zero.sum())} zero rotation quaternions replaced by the identity")
        if off.any():
            log(f"{label}: {int(off.sum())} rotation quaternions not unit: normalized")
    elif path == "rotation" and np.abs(values).max() > 1e150:  # tangents: no safe rescaling
        raise doc.error(f"{label}: rotation values as large as {float(np.abs(values).max()):.3g}: re-export the clip")
    return Track(joint, path, times, values, interp)
