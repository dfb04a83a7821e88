"""The junction stretch ratio (:func:`rigmix.quality.junction_stretch_ratio`) compares the seam
with each part it joins: the Wasp's rigid wings attached to the Witch, who has no clip of her own
and moves only as completion animates her with the Wasp's clips; a quadruped's front leg replaced
by its mirrored partner, which must step as the leg it replaces."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset, corpus, corpus_case

from rigmix.gates import MAX_STRETCH_RATIO


@pytest.fixture(scope="module")
def witch_wings(tmp_path_factory):
    from rigmix.pipeline import compose

    cfg = tmp_path_factory.mktemp("wings") / "wings.toml"
    text = (f'[characters.body]\npath = "{corpus("Witch").as_posix()}"\n'
            f'[characters.donor]\npath = "{asset("Wasp").as_posix()}"\nscale = "auto"\n')
    for side in ("L", "R"):
        text += (f'[[actions]]\nop = "attach"\nsource = "donor"\nsource_joint = "Wing.{side}"\n'
                 'target = "body"\ntarget_joint = "Chest"\n')
    cfg.write_text(text)
    return compose(cfg)


def test_a_clip_less_input_is_measured_under_the_clips_it_gets(witch_wings):
    comp = witch_wings
    assert not comp.inputs["body"].clips and comp.inputs["donor"].clips
    q = comp.report["quality"]
    figures = q["source_p95_by_input"]
    assert set(figures) == {"body", "donor"}
    assert all(v > 0 for v in figures.values())


def test_the_ratio_is_over_the_most_supple_part(witch_wings):
    q = witch_wings.report["quality"]
    figures = q["source_p95_by_input"]
    # the wing is rigid: pooled by vertex count, it would make the body's own motion look like a seam
    assert figures["donor"] < figures["body"]
    assert q["source_p95"] == max(figures.values())
    assert q["junction_stretch_ratio"] == pytest.approx(q["output_p95"] / q["source_p95"])
    assert q["junction_stretch_ratio"] <= MAX_STRETCH_RATIO


@pytest.fixture(scope="module")
def mirrored_leg(tmp_path_factory):
    """The corpus's mirror case: the Apatosaurus's left front leg (and its foot) replaced by the
    right ones, mirrored."""
    from rigmix.pipeline import compose

    cfg = tmp_path_factory.mktemp("mirror") / "mirror.toml"
    path = corpus("Apatosaurus").as_posix()
    text = f'[characters.body]\npath = "{path}"\n[characters.mirror]\npath = "{path}"\nmirror = true\nscale = 1.0\n'
    for joint in ("FrontUpLeg.L", "FrontFoot.L"):
        text += (f'[[actions]]\nop = "replace"\nsource = "mirror"\nsource_joint = "{joint}"\n'
                 f'target = "body"\ntarget_joint = "{joint}"\nmode = "blend"\n')
    cfg.write_text(text)
    return compose(cfg)


def test_a_mirrored_leg_steps_as_the_leg_it_replaces(mirrored_leg):
    """Every joint of the leg follows the clip's own left leg (not the reflected right leg of the
    mirrored copy's clip, half a step out of phase with the body), so the seam deforms as the
    artist's own shoulder does."""
    from rigmix.animation import clip_times, sample_clip
    from rigmix.transforms import quat_angle, quat_conjugate, quat_multiply

    comp = mirrored_leg
    S, body = comp.plan.skeleton, comp.inputs["body"]
    leg = [o for o, prov in enumerate(comp.plan.provenance) if any(c == "mirror" for c, _ in prov)]
    same = [body.skeleton.names.index(S.names[o]) for o in leg]
    for clip in comp.clips:
        cid, name = clip.name.split(":", 1)
        if cid != "body":
            continue
        t = clip_times(clip, 30.0)
        _, Ro, _ = sample_clip(S, clip, t)
        _, Rb, _ = sample_clip(body.skeleton, body.clip(name), t)
        got = quat_multiply(quat_conjugate(S.rotations[leg])[None], Ro[:, leg])
        want = quat_multiply(quat_conjugate(body.skeleton.rotations[same])[None], Rb[:, same])
        np.testing.assert_allclose(quat_angle(got, want), 0.0, atol=1e-6, err_msg=name)
    q = comp.report["quality"]
    assert q["junction_stretch_ratio"] <= MAX_STRETCH_RATIO, q


@pytest.fixture(scope="module")
def ik_foot_swap(tmp_path_factory):
    """The corpus's leg swap of two Quaternius rigs whose feet are IK bones under the armature
    root (detached parts of the leg): the Trex's left leg and foot replaced by the Triceratops's
    front left ones."""
    from rigmix.pipeline import compose

    cfg = tmp_path_factory.mktemp("ikfoot") / "ikfoot.toml"
    text = (f'[characters.body]\npath = "{corpus("Trex").as_posix()}"\n'
            f'[characters.donor]\npath = "{corpus("Triceratops").as_posix()}"\nscale = "auto"\n')
    for source, target in (("FrontUpLeg.L", "BackUpLeg.L"), ("FrontFoot.L", "BackFoot.L")):
        text += (f'[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "{source}"\n'
                 f'target = "body"\ntarget_joint = "{target}"\nmode = "blend"\n')
    cfg.write_text(text)
    return compose(cfg)


def _tip_distance(skeleton, clip, joint, tip):
    """(F,) distance from ``joint`` to ``tip`` in ``clip`` (30 fps), over the rest distance."""
    from rigmix.animation import clip_times, sample_clip
    from rigmix.transforms import trs_to_matrix

    T, R, S = sample_clip(skeleton, clip, clip_times(clip, 30.0))
    P = skeleton.world_matrices(trs_to_matrix(T, R, S))[..., :3, 3]
    rest = skeleton.rest_worlds()[:, :3, 3]
    return np.linalg.norm(P[:, joint] - P[:, tip], axis=-1) / np.linalg.norm(rest[joint] - rest[tip])


def test_a_moved_ik_foot_stays_at_its_leg(ik_foot_swap):
    """The donor's foot hangs from the root, its leg from the body's hip: it follows the leg's tip,
    at its rest distance where the body's clip plays (the leg plays chosen donor frames), as in
    the donor's own clip where that plays; the seam then stretches no more than the sources'."""
    comp = ik_foot_swap
    S, donor = comp.plan.skeleton, comp.inputs["donor"]
    foot, tip = S.names.index("BackFoot.L"), S.names.index("donor_FrontLowLeg.L")
    assert S.parents[foot] != tip  # the foot is a detached part: it does not hang from the leg
    d_foot, d_tip = donor.skeleton.names.index("FrontFoot.L"), donor.skeleton.names.index("FrontLowLeg.L")
    sources = comp.report["animation"]["sources"]
    assert {cid for cid, _ in sources} == {"body", "donor"}
    for clip, (cid, name) in zip(comp.clips, sources, strict=True):
        got = _tip_distance(S, clip, foot, tip)
        if cid == "body":
            np.testing.assert_allclose(got, 1.0, atol=1e-6, err_msg=clip.name)
        else:
            own = _tip_distance(donor.skeleton, donor.clip(name), d_foot, d_tip)
            # the leg and the foot were placed apart (rest offsets differ a little), so the same
            # motion of the foot in its own frame changes the distance a little differently
            np.testing.assert_allclose(got, own, atol=0.15, err_msg=clip.name)
    assert comp.report["quality"]["junction_stretch_ratio"] <= MAX_STRETCH_RATIO


def test_band_stretch_under_given_matrices_equals_sampling_the_clips():
    """The stretch ratio samples each skeleton's clips once and hands the matrices to every band
    under them: the samples are those of sampling the clips for the band itself."""
    from rigmix.io import load_character
    from rigmix.quality import band_stretch, clip_skinning_matrices

    c = load_character(asset("CesiumMan"))
    m = c.meshes[0]
    band = np.flatnonzero(m.positions[:, 2] > np.median(m.positions[:, 2]))
    own = band_stretch(c.skeleton, c.clips, m.positions, m.joints, m.weights, m.faces, band)
    given = band_stretch(c.skeleton, c.clips, m.positions, m.joints, m.weights, m.faces, band,
                         matrices=clip_skinning_matrices(c.skeleton, c.clips))
    assert len(own) > len(band)  # several frames
    assert np.array_equal(own, given) and np.isfinite(own).all() and own.max() > 0


def test_all_clips_through_one_forward_kinematics_pass_are_each_clip_on_its_own():
    """clip_skinning_matrices poses the frames of every clip together: each clip's matrices are
    those of posing its own frames alone, bit for bit, and as many as its stretch frames."""
    from rigmix.animation import sample_clip
    from rigmix.io import load_character
    from rigmix.quality import clip_skinning_matrices
    from rigmix.skinning import skinning_matrices

    c = load_character(asset("Fox"))
    assert len(c.clips) > 1
    together = clip_skinning_matrices(c.skeleton, c.clips, max_frames=7)
    assert len(together) == len(c.clips)
    for clip, M in zip(c.clips, together):
        alone = clip_skinning_matrices(c.skeleton, [clip], max_frames=7)[0]
        assert M.shape == alone.shape == (min(7, len(M)), c.skeleton.num_joints, 4, 4)
        assert np.array_equal(M, alone)
        T, R, S = sample_clip(c.skeleton, clip, np.zeros(1))
        assert np.array_equal(clip_skinning_matrices(c.skeleton, [clip], max_frames=1)[0],
                              skinning_matrices(c.skeleton, T, R, S))  # the first frame is time 0


def test_the_meshes_of_an_input_are_sampled_as_one_with_each_samples_own():
    """A modular character's band spans several meshes: sampled as one merged mesh (influences
    padded to the widest), its samples are every mesh's own, the same floats."""
    from rigmix.io import load_character
    from rigmix.quality import band_stretch, clip_skinning_matrices, merged_band
    from rigmix.skinning import linear_blend_skinning, rest_skinning_matrices

    c = load_character(corpus("CyberpunkCharacter"))
    meshes = [m for m in c.meshes if m.skinned and len(m.faces)]
    assert len(meshes) > 2
    M = clip_skinning_matrices(c.skeleton, c.clips[:3])
    M0 = rest_skinning_matrices(c.skeleton)
    parts = []
    for m in meshes:
        rest = linear_blend_skinning(m.positions, m.joints, m.weights, M0)
        band = np.flatnonzero(rest[:, 1] > np.median(rest[:, 1]))
        if len(band):
            parts.append((m, rest, band))
    assert len(parts) > 2
    own = np.concatenate([band_stretch(c.skeleton, c.clips[:3], m.positions, m.joints, m.weights, m.faces, b,
                                       rest=rest, matrices=M) for m, rest, b in parts])
    V0, J, W, F, vertices, rest = merged_band(parts)
    merged = band_stretch(c.skeleton, c.clips[:3], V0, J, W, F, vertices, rest=rest, matrices=M)
    assert len(merged) == len(own) and own.max() > 0
    assert np.array_equal(np.sort(merged), np.sort(own))


def test_band_stretch_is_the_mean_face_stretch_of_the_skinned_band():
    """The band's samples, taken from the posed edge vectors without posing the vertices, are the
    definition: each band vertex's area-weighted mean of the stretch of its faces, skinned by
    every sampled frame of every clip, clip after clip."""
    from rigmix.io import load_character
    from rigmix.quality import band_stretch, clip_skinning_matrices, face_stretch
    from rigmix.skinning import linear_blend_skinning, rest_skinning_matrices

    c = load_character(asset("CesiumMan"))
    m = c.meshes[0]
    band = np.flatnonzero(m.positions[:, 1] > np.median(m.positions[:, 1]))
    got = band_stretch(c.skeleton, c.clips, m.positions, m.joints, m.weights, m.faces, band)
    rest = linear_blend_skinning(m.positions, m.joints, m.weights, rest_skinning_matrices(c.skeleton))
    F = np.asarray(m.faces)
    area = 0.5 * np.linalg.norm(np.cross(rest[F[:, 1]] - rest[F[:, 0]], rest[F[:, 2]] - rest[F[:, 0]]), axis=1)
    want = []
    for M in clip_skinning_matrices(c.skeleton, c.clips):
        s = face_stretch(rest, linear_blend_skinning(m.positions, m.joints, m.weights, M), F)  # (k, m)
        for f in range(len(M)):
            num, den = np.zeros(len(rest)), np.zeros(len(rest))
            for corner in range(3):
                np.add.at(num, F[:, corner], s[f] * area)
                np.add.at(den, F[:, corner], area)
            want.append(num[band] / den[band])
    want = np.concatenate(want)
    assert len(got) == len(want) and want.max() > 0.01
    # near 0 the square root of a difference of eigenvalues turns rounding into ~1e-9
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-8)


def test_an_inputs_band_is_its_vertices_within_reach_of_the_joint(witch_wings):
    """Over all the input's meshes, at least its nearest vertex; a mesh far from the joint (a
    modular character's other parts, a prop) adds none."""
    from rigmix.skinning import linear_blend_skinning, rest_skinning_matrices

    comp = witch_wings
    q = comp.report["quality"]
    donor = comp.inputs["donor"]
    scale = float(comp.plan.scales.get("donor", 1.0))
    M0 = rest_skinning_matrices(donor.skeleton)
    meshes = [m for m in donor.meshes if m.skinned and len(m.faces)]
    assert len(meshes) > 1
    expected = 0
    for p in comp.plan.fused_pairs:
        c = donor.skeleton.rest_worlds()[p.source_joint, :3, 3]
        d = [np.linalg.norm(linear_blend_skinning(m.positions, m.joints, m.weights, M0) - c, axis=1) for m in meshes]
        reach = max(q["band_radius"] / scale, min(x.min() for x in d))
        per_mesh = [int((x <= reach).sum()) for x in d]
        assert 0 in per_mesh  # some part of the Wasp lies beyond the reach of each wing's root
        expected += sum(per_mesh)
    # the Witch has no clip: her band is her own vertices in the output band
    body = comp.fusion_ids.index("body")
    S = comp.surface
    V = np.asarray(S.V)
    P = comp.plan.skeleton.rest_worlds()[[p.output for p in comp.plan.fused_pairs], :3, 3]
    band = np.linalg.norm(V[:, None] - P[None], axis=2).min(axis=1) <= q["band_radius"]
    expected += int((band & (S.origin_input == body) & ~np.asarray(S.junction_vertices)).sum())
    assert q["source_band_vertices"] == expected


def _split_faces(V0, W, F, split):
    """``F`` with the faces ``split`` (bool, (m,)) each cut into four at their edge midpoints;
    the new vertices take the mean of their edge's bind positions and dense weights ``W``."""
    E = np.sort(F[split][:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    edges, inverse = np.unique(E, axis=0, return_inverse=True)
    mid = len(V0) + inverse.reshape(-1, 3)
    V1 = np.concatenate([V0, V0[edges].mean(axis=1)])
    W1 = np.concatenate([W, W[edges].mean(axis=1)])
    a, b, c = F[split].T
    ab, bc, ca = mid.T
    quads = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return V1, W1, np.concatenate([F[~split], quads])


def test_the_band_figure_weighs_each_vertex_by_its_area():
    """Refining the band where it barely stretches (CesiumMan's upper body, its faces cut in four)
    puts many more vertices there and no more surface: the percentile over the surface stays
    what it was, the percentile over vertices falls."""
    from rigmix.io import load_character
    from rigmix.quality import band_stretch, vertex_areas, weighted_percentile

    c = load_character(asset("CesiumMan"))
    m = c.meshes[0]
    V0, F = np.asarray(m.positions, np.float64), np.asarray(m.faces, np.int64)
    J = c.skeleton.num_joints
    W = np.zeros((len(V0), J))
    np.put_along_axis(W, np.asarray(m.joints, np.int64), np.asarray(m.weights, np.float64), axis=1)

    def figures(V, W, F):
        band = np.arange(len(V))
        s = band_stretch(c.skeleton, c.clips, V, np.tile(np.arange(J), (len(V), 1)), W, F, band)
        a = np.tile(vertex_areas(V, F, band), len(s) // len(band))
        return weighted_percentile(s, a, 95.0), float(np.percentile(s, 95.0))

    base_area, base_count = figures(V0, W, F)
    # the faces whose corners stretch least over the clips
    s = band_stretch(c.skeleton, c.clips, V0, np.tile(np.arange(J), (len(V0), 1)), W, F,
                     np.arange(len(V0))).reshape(-1, len(V0)).max(axis=0)
    calm = s[F].max(axis=1) < np.percentile(s, 50.0)
    V1, W1, F1 = _split_faces(V0, W, F, calm)
    new = 4 * int(calm.sum())  # _split_faces puts the cut faces last: cut them again
    V2, W2, F2 = _split_faces(V1, W1, F1, np.r_[np.zeros(len(F1) - new, bool), np.ones(new, bool)])
    assert len(V2) > 2 * len(V0)
    refined_area, refined_count = figures(V2, W2, F2)
    assert refined_area == pytest.approx(base_area, rel=0.05)
    assert refined_count < 0.9 * base_count


def test_weighted_percentile_counts_each_sample_by_its_weight():
    from rigmix.quality import weighted_percentile

    x = np.array([4.0, 1.0, 3.0, 2.0])
    assert weighted_percentile(x, np.ones(4), 50.0) == np.percentile(x, 50.0, method="inverted_cdf")
    assert weighted_percentile(x, np.array([5.0, 1.0, 1.0, 1.0]), 50.0) == 4.0
    assert weighted_percentile(x, np.zeros(4), 95.0) == np.percentile(x, 95.0)  # no weight: unweighted


def test_a_head_replaced_by_a_coarser_one_stretches_as_its_sources(tmp_path):
    """The Wasp's head (about 2,900 band vertices, rigid) replaced by the Witch's (642, scaled to
    it): counted by vertex, the Wasp's band percentile was diluted by its dense head and the seam
    read 1.56 times the sources'; over the surface it is within the bound."""
    from rigmix.pipeline import compose

    comp = compose(corpus_case("head_swap__Wasp__Witch", tmp_path))
    q = comp.report["quality"]
    assert q["junction_stretch_ratio"] <= MAX_STRETCH_RATIO, q
