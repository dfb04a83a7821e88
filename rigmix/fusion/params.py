"""The ``[fusion]`` options: :class:`FusionParams` (PIPELINE.md section 3).

A module of its own, with no numerical dependency, so that reading and checking a config does not
load the fusion's kernels (libigl, gpytoolbox, scipy)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FusionParams"]


@dataclass(frozen=True)
class FusionParams:
    """Parameters of the fusion (defaults: PIPELINE.md section 3, see each note).

    Attributes
    ----------
    snap, smooth_iterations, smooth_alpha : presence snapping and smoothing (0.02, 10, 0.8).
    preserve_threshold : face presence for a preserved face (prototype 0.999).
    morphology_rounds : opening-closing rounds on the face adjacency (2).
    secondary_variance : presence variance under which a component is secondary (0.04).
    replaced_present : whether the target of a replace keeps the skin of its replaced joint
        itself (:func:`.presence.compute_presence`). True (the default) keeps it, and the
        target's part around the fused joint stays (the built-in centaur's quadruped neck, a
        stump in front of the rider); False takes the whole replaced region away. Measured on
        the corpus matrix with ``WeightParams.cut_joint_reach`` 0.1 (on 260 cases): 9 cases
        pass that failed and 17 fail that passed, so it is not the default;
        ``retry_whole_region`` takes it where it passes more gates.
    retry_whole_region : where True (the default) and ``replaced_present`` is True, a
        composition that fails a fusion gate (:func:`rigmix.gates.mesh_gates`) is fused again
        with the replaced regions taken away whole (``replaced_present`` False), and that surface
        is kept when the gates it fails are some of those the first fails, or the same ones,
        none farther from its bound and one nearer (fewer crossing pairs, grafted parts showing
        more; :func:`rigmix.pipeline.fusion_stage`).
    retry_max_faces : the retry's work budget: it is not tried when the fusion's inputs hold
        more faces than this together (250,000; a second fusion costs as much as the first).
    voxel_factor : voxel = voxel_factor x smallest average edge length (0.8) before refinement.
    min_voxels_across : the voxel is refined until this many span the junction (its second
        largest extent).
    max_voxel_diagonal : if positive, the voxel is also refined until it is at most this
        fraction of the smallest input's bounding-box diagonal (0: off). Marching cubes rounds
        creases off by up to about half a voxel, and low-poly characters get 1.1 to 1.3% of the
        diagonal per voxel from the two rules above (RiggedFigure, Fox). 0.004 brings the
        isosurface within 0.35% on every limb self-composition, but it is off by default: the
        thinner bridge strips it makes cost junction angle quality (on the two-ellipsoid test,
        p05 18.7 degrees with 0.004 against 26.9 without).
    margin_voxels : the grid reaches this many voxels beyond the junction faces (10).
    band_voxels : exact distances within this many voxels of a surface, clamped beyond.
    max_voxels : cap on samples per grid (the voxel grows to respect it).
    cut_voxels : isosurface parts closer than this to a preserved face are cut away.
    attach_conflict_voxels : for attach, faces this close to the other's present part are blended.
    remesh_iterations, target_edge_factor : junction remeshing; target = factor x the smaller
        of the mean preserved boundary edge and the mean edge of the input faces the junction
        replaces. A factor of 0.8 (the prototype's) chords off the creases of low-poly game
        meshes by up to 0.86% of the bounding-box diagonal on CesiumMan self-compositions; 0.5
        keeps them under 0.5%.
    taubin_iterations : smoothing of the remeshed junction interior.
    plain_taubin_iterations : the same for the smoothed plain remeshing, taken where the
        plain junction creases more than ``crease_ratio`` times the replaced input faces and
        the smoothed one creases less, keeps the angles and folds no more (its vertices are
        pulled onto the inputs only where they agree): the built-in centaur's junction creased
        2.13 times as much as its inputs near the fused joint, 1.40 smoothed.
    project_voxels : junction vertices are then pulled at most this many voxels towards the
        presence-weighted closest input points (0 disables).
    fidelity_voxels, fidelity_diagonal : the junction may stray from the isosurface by at
        most the smaller of this many voxels and this fraction of the smallest input's
        bounding-box diagonal (0 disables): remeshing to the neighbouring edge length alone
        chords off corners and thin parts (1 to 3% of the diagonal on self-compositions of
        low-poly characters); see :func:`.stitch.remesh_keeping_features`.
    keep_input_corners : vertices of the replaced input faces that the exact blended field puts
        on the surface (within a tenth of a voxel) but the isosurface misses are inserted into it
        and kept by the remeshing: corners and thin parts of low-poly inputs that marching cubes
        rounds off.
    feature_rounds : rounds that insert, as kept vertices, the reference vertices the refined
        junction still leaves farther than the tolerance.
    refine_rounds, refine_min_edge : the shape-keeping junction is first refined where it strays
        farther than the tolerance (:func:`.remesh.refine_where_stray`), at most this many
        rounds, edges down to twice this many target edges. Pinning those vertices in the
        remeshing instead left them three faces standing as spikes over the coarse triangles:
        junction dihedral p95 149 degrees on RiggedFigure's left arm swapped for its mirrored
        right (90 on the input there; 57 refined).
    fidelity_relax : when the fidelity path misses ``min_angle_p05`` and the plain remeshing
        strays from its reference (the cut isosurface and its bridges) by more than the tolerance
        times one of these, the fidelity path is tried again with that looser tolerance (fewer
        kept features) and kept if it meets ``min_angle_p05`` and loses at most
        ``relax_max_angle_loss`` degrees of p05 against the plain remeshing (keeping less, it
        may cost little); the report's grid gives the ``fidelity_tolerance`` used (0: plain)
        and, after a miss, the plain remeshing's ``plain_deviation`` (same unit as the
        positions). RiggedFigure's right arm: at 4x the shape stays within 0.14% of the
        diagonal at p05 21.6 degrees, where the plain remeshing rounds a box corner off by 2.2%
        (p05 21.3). The Horse + Knight centaur's plain junction strays 0.11 units (1.7% of the
        diagonal) from its reference; at 4x its p05 would be 20.1 against the plain 28.4, with
        visibly jagged, feature-pinned triangles, so it stays plain.
    relax_max_angle_loss : degrees, see ``fidelity_relax``.
    fold_free_deviation : the shape-keeping junction gives way to the plain one where it folds
        (crossing faces, or neighbours turned past 150 degrees) and the plain one does less, as
        long as the plain junction strays from the reference at most this many times as far
        (fox_arm: 3 crossings at 0.85% of the diagonal, against none at 1.3%). Kept features
        pinned closer than the target edge fold the triangles between them.
    crease_ratio : the shape-keeping junction gives way to the plain one where the 95th
        percentile of its dihedral angles exceeds this many times the replaced input faces' (and
        the plain one's is lower; 0 disables). The gate ``junction_dihedral_ratio`` allows 1.5
        against the inputs' faces around the fused joints, kept ones included, which can crease
        less than the replaced ones (the Deer's neck under EnemyLarge's head: 37 degrees against
        49). The Rat's right foreleg, swapped for its mirrored left, keeps features at the
        corners of its low-poly paw that crease the junction to 93 degrees, 1.5 times the
        input's there; plain, 81. Low-poly inputs crease as much as their shape-keeping
        junctions: the limb self-compositions keep theirs.
    min_angle_p05 : degrees; the fidelity path is kept only if the junction's 5th percentile of
        triangle minimum angles stays at least this, or above the plain remeshing's.
    min_seam_wedge : degrees; preserved faces around a seam vertex that leaves the junction a
        thinner wedge than this join the junction (no good triangle fits such a wedge).
    snap_input_vertices : junction vertices move onto the nearby vertices of the replaced input
        faces that lie on the blended surface (within a quarter voxel): corners of low-poly
        inputs survive the remeshing.
    collapse_poor : free junction vertices of triangles under 20 degrees are collapsed into a
        neighbour where that raises the angles and moves the surface less than the fidelity
        tolerance (:func:`.remesh.collapse_to_improve_angles`). A uniform target edge cannot
        meet the long seam edges of low-poly preserved faces (up to 8 target edges). Measured
        on the 37 limb self-compositions: with it, the shape-keeping path falls back to the
        plain one on 3, one of them more than 0.5% of the diagonal off (RiggedFigure's right
        arm); without it, on 13, 11 of them off (up to 2.2%).
    copy_coincident : a junction cluster whose every face both inputs of an action have (the
        same corner positions bit for bit, same orientation) is copied as it is: both surfaces
        pass through those faces, so the blended field vanishes there and remeshing its
        isosurface could only lose them. Each face is kept once, from the input more present on
        it; its vertices get junction weights unless a preserved face keeps the position
        (:attr:`FusedSurface.junction_vertices`). A limb replaced by itself then comes back face
        for face: measured on the 37 limb self-compositions of the shared characters, Hausdorff
        0 and every face kept, where rebuilding from the fields gives a Hausdorff distance of
        at most 0.44% and keeps at least 90% of the faces on 24 of them. A partly shared
        junction is rebuilt from the fields. (Preserved faces both inputs have are kept once
        whatever this says: :func:`.seams.shared_preserved`.)
    bridge_recuts : times the isosurface may be cut back and the seam loops bridged again where
        a bridge strip crosses the isosurface or the fan that closes a hole no seam claims
        (without recuts, 8 bridge triangles of the Horse + Knight centaur, spanning 0.26 to 0.33
        units against a median of 0.076, cross an 87-vertex fan 101 times, and the remeshed
        junction keeps 35 of the crossings); the report's grids give ``bridge_recuts``.
    untangle_move : folds left in a remeshed junction are smoothed open
        (:func:`.remesh.untangle`) only if no vertex of a shape-keeping junction moves farther
        than this many fidelity tolerances (opening five folds of RiggedFigure's arm, replaced
        by itself, without this limit rounds its box corners to 0.9% of the diagonal, against
        0.23% with it).
    min_island_faces : preserved parts bordering a junction with fewer faces join it (specks
        left by the presence pattern have no isosurface hole to meet).
    crossing_rounds : rounds of the repair of junction faces that cross the surface
        (:func:`.crossings.repair_crossings`: smoothing and pushing junction vertices apart, kept
        faces in the way joining the junction; 0 disables it). Where the junction band is
        narrow, the remeshed junction folds through itself or through a kept face (9 pairs on
        the Horse + Knight centaur, 14 on the built-in centaur); the report's
        ``junction_crossings_repaired``, ``junction_faces_released``,
        ``junction_crossings_layered`` and ``junction_repair_largest_move`` say what the repair
        did and what it left.
    shell_clearance_voxels : where crossings are left after the repair and an input keeps closed
        parts whole (a robot's plates, an arm band: secondary components, never blended), the
        junction is made again around them, this many voxels clear, and kept if it crosses less
        with triangles as good (0 disables it, and :func:`.seams.under_kept_shells`, which first
        gives the junction the preserved faces such a part covers next to it). Sunk into the
        surface they cover, such parts are crossed by the isosurface of that surface (a cyberpunk
        figure's arm plates by its own arm, 46 pairs on the Triceratops' tail on it).
    backend : "numpy" (numpy + libigl) or "openvdb".
    keep_fields : keep the blended grids in the result (for ``dump_fields``).
    """

    snap: float = 0.02
    smooth_iterations: int = 10
    smooth_alpha: float = 0.8
    preserve_threshold: float = 0.999
    morphology_rounds: int = 2
    secondary_variance: float = 0.04
    replaced_present: bool = True
    retry_whole_region: bool = True
    retry_max_faces: int = 250_000
    voxel_factor: float = 0.8
    min_voxels_across: int = 32
    max_voxel_diagonal: float = 0.0
    margin_voxels: float = 10.0
    band_voxels: float = 8.0
    max_voxels: int = 4_000_000
    cut_voxels: float = 1.0
    attach_conflict_voxels: float = 2.0
    remesh_iterations: int = 5
    target_edge_factor: float = 0.5
    taubin_iterations: int = 3
    plain_taubin_iterations: int = 8
    project_voxels: float = 1.0
    fidelity_voxels: float = 0.75
    fidelity_diagonal: float = 0.0025
    feature_rounds: int = 2
    refine_rounds: int = 3
    refine_min_edge: float = 0.2
    fidelity_relax: tuple = (4.0,)
    relax_max_angle_loss: float = 5.0
    fold_free_deviation: float = 2.0
    crease_ratio: float = 1.0
    keep_input_corners: bool = True
    min_angle_p05: float = 20.0
    min_seam_wedge: float = 60.0
    min_island_faces: int = 24
    snap_input_vertices: bool = True
    collapse_poor: bool = True
    copy_coincident: bool = True
    bridge_recuts: int = 6
    untangle_move: float = 2.0
    crossing_rounds: int = 6
    shell_clearance_voxels: float = 1.0
    backend: str = "numpy"
    keep_fields: bool = False
