"""glTF 2.0 / GLB <-> :class:`rigmix.character.Character`.

:func:`read_gltf` and :func:`write_gltf` are the public API; the work is done in
:mod:`rigmix.io.accessors` (containers, buffers, bounds-checked accessors),
:mod:`rigmix.io.gltf_read` (+ :mod:`rigmix.io.gltf_materials`, :mod:`rigmix.io.repair`) and
:mod:`rigmix.io.gltf_write`.

Reading: glTF -> model
----------------------
* **Skin.** The skin with most joints is the skeleton. Another skin whose joints are a subset is
  merged (its meshes' bind space mapped onto the main skin's when their inverse binds differ by
  one common transform); a skin over other joints raises :class:`UnsupportedError`. A file with
  no skin gives a skeleton of 0 joints and every mesh becomes a static ``Prop``
  (``Character.skinned`` is False).
* **Joint order.** Topological, parents first. Each joint is keyed by the smallest skin
  position in its subtree and the forest is emitted by a heap-ordered topological sort, so a
  skin already listed parents-first keeps its order exactly; JOINTS are remapped. Non-joint
  nodes lying *between* two joints become joints (with a warning; they get no weight and their
  inverse bind is their inverse rest world matrix).
* **Names.** From the nodes; unnamed joints are ``joint_<node index>``; a repeated name gets
  ``.1``, ``.2``... (with a warning). Unnamed clips are ``clip_<index>``.
* **Rest pose.** Local TRS from the node (``matrix`` decomposed). The non-joint ancestors of
  the root joints are ``Skeleton.anchors`` (e.g. CesiumMan's ``Z_UP`` matrix), parents first.
* **Meshes.** Each triangle primitive (strips and fans converted, points and lines skipped with
  a warning) of a skinned node is one ``Mesh`` named ``<mesh>`` or ``<mesh>.<primitive>`` (or
  the name rigmix stored in the primitive's ``extras.name``); all ``JOINTS_n``/``WEIGHTS_n`` sets
  are concatenated (``K = 4 x sets``). Unskinned meshes under a joint are ``Prop`` on that joint
  with their matrix relative to its rest world matrix; other meshes are ``Prop(joint=-1)`` with
  their world matrix. ``COLOR_0`` becomes float RGBA; morph targets are ignored (warning).
* **Animations.** Channels on joints become ``Track`` (interpolation and, for CUBICSPLINE,
  tangents kept as ``(k, 3, C)``; LINEAR/STEP rotations normalized). Channels on non-joint nodes
  and morph weights are ignored with a warning; a clip left with no track is dropped.
* **Materials.** Metallic-roughness factors and the base colour texture (PNG or JPEG bytes from
  a buffer view, a data URI or a file next to the glTF; a missing or non-PNG/JPEG image drops the
  texture with a warning).

Repairs (each logged with ``logger.warning`` and kept in ``Character.warnings`` as
``"<file>: mesh '<name>': <count> vertices ..."``)
--------------------------------------------------------------------------------------------
1. NaN or infinite weights are set to 0; negative weights are clamped to 0.
2. Duplicate joint slots in a row are summed into the first slot.
3. Rows are renormalized to sum 1 (reported when the sum was off by more than 1e-3).
4. Rows left with no positive weight (e.g. the shared Wasp's 6 all-NaN vertices) take the
   weights of a vertex of the same skin at the same bind position (within 1e-6 of the bounding
   box diagonal) when there is one, else weight 1 on the joint whose bind position is nearest.
5. Unused slots are set to joint 0, weight 0.
6. A ``skin.skeleton`` that is not a common root of the joints is ignored (the skeleton never
   depends on it). Key times that are not strictly increasing are sorted and de-duplicated.
7. A zero rotation quaternion (rest or key) becomes identity; a non-unit one (off by more than
   2e-3) is normalized, scaled down first so that an overflowing norm never turns it into identity.

Not repaired (:class:`InputError`, one line naming the file and the object): not a glTF file,
truncated GLB, corrupted JSON chunk, missing external buffer, a buffer shorter than its declared
``byteLength`` (never allocated from the declaration), buffer view or accessor ranges outside
their buffer, sparse indices past the accessor count, triangle indices past the vertex count,
joint indices past the skin's joint count, NaN positions or animation values, a node hierarchy
with cycles; inverse bind matrices that are not finite, not affine or not invertible; attribute
component types the glTF 2.0 attribute table does not allow (POSITION as UNSIGNED_INT, or SHORT
without ``KHR_mesh_quantization``; WEIGHTS as UNSIGNED_INT or BYTE); negative key times; a scene
naming a missing or non-root node; an unknown extension in ``extensionsRequired``
(:class:`UnsupportedError`).

Confinement: the input and every file it names are read only when they are regular files; a URI
resolves (percent-decoded, symlinks resolved) only to a file inside the glTF's own folder, and a
refusal never repeats an outside path. Sizes are checked before reading
(:data:`rigmix.io.accessors.MAX_FILE_BYTES` for the file and its buffers,
:data:`rigmix.io.accessors.MAX_IMAGE_BYTES` per image), and a ``data:`` URI longer than its
declared ``byteLength`` needs is refused before it is decoded.

Writing: model -> glTF
----------------------
One skin with one node per joint (TRS, hierarchy), anchors as nodes above the roots (matrix),
every ``Character.meshes`` entry as one primitive of a single glTF mesh on one skinned node at
the scene root (never under a transformed node), props as mesh nodes under their joint (or at
the root), inverse bind matrices, all clips (CUBICSPLINE with tangents), materials with embedded
PNG/JPEG textures and samplers. Data are float32 with POSITION and animation-input min/max;
normals and rotations are unit; weights keep the 4 largest influences per vertex, renormalized in
float32 so their sum is exactly 1, unused slots joint 0 weight 0 (unsigned byte or short
joints). Files are written to a temporary file in the same folder and renamed over the target.
"""

from __future__ import annotations

from .gltf_read import read_gltf
from .gltf_write import sparsify_weights, write_gltf
from .repair import repair_weights

__all__ = ["read_gltf", "write_gltf", "repair_weights", "sparsify_weights"]
