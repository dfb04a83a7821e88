"""Animation completion: fast kernels against slow references, self-composition ground truth
on the shared Fox, and a centaur (two different characters) for coverage and smoothness."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from conftest import asset

from rigmix.animation import clip_times, sample_clip
from rigmix.animation.completion import (
    CompletionOptions,
    FixedFrame,
    angular_acceleration,
    choose_frames,
    complete_clips,
    continuity_scores,
    global_rotations,
    hop_weights,
    keyframe_scores,
    map_pose,
    rotation_features,
    smooth_seams,
)
from rigmix.character import Skeleton
from rigmix.errors import InputError
from rigmix.mapping import BoneMap
from rigmix.transforms import quat_angle, quat_conjugate, quat_multiply, quat_normalize

# --------------------------------------------------------------------------------------------
# helpers (acceleration_figures is also used by benchmarks/completion_bench.py)


def random_quats(rng, shape):
    return quat_normalize(rng.normal(size=shape + (4,)))


def graft(base, base_id, onto, donor, donor_id, root, *, drop=None, extra=()):
    """A hand-made plan: ``donor``'s subtree at ``root`` fused with ``base``'s joint ``onto``.

    S_R holds ``base``'s joints except the subtree ``drop`` (default: the descendants of
    ``onto``), then ``root``'s descendants in ``donor`` (``root`` itself is ``onto``).

    Parameters
    ----------
    extra : iterable of (character id, input joint name, output joint name, confidence)
        Mappings of dropped joints (as the mapping stage would propagate them).

    Returns
    -------
    skeleton : Skeleton, provenance : list of list of (str, int), maps : dict of BoneMap
    """
    bs, ds = base.skeleton, donor.skeleton
    b, a = bs.index(onto), ds.index(root)
    dropped = bs.subtree(bs.index(drop)) if drop else bs.subtree(b) & (np.arange(bs.num_joints) != b)
    keep = np.flatnonzero(~dropped)
    part = np.flatnonzero(ds.subtree(a))[1:]
    bmap = -np.ones(bs.num_joints, dtype=np.int64)
    bmap[keep] = np.arange(len(keep))
    dmap = -np.ones(ds.num_joints, dtype=np.int64)
    dmap[part] = len(keep) + np.arange(len(part))
    dmap[a] = bmap[b]
    names = [bs.names[i] for i in keep] + [f"{donor_id}.{ds.names[i]}" for i in part]
    parents = [bmap[p] if p >= 0 else -1 for p in bs.parents[keep]] + [dmap[p] for p in ds.parents[part]]

    def cat(x, y):
        return np.concatenate([x[keep], y[part]])

    skel = Skeleton(names, parents, cat(bs.translations, ds.translations),
                    cat(bs.rotations, ds.rotations), cat(bs.scales, ds.scales),
                    cat(bs.inverse_binds, ds.inverse_binds), bs.anchors,
                    np.concatenate([bs.root_anchor[keep], -np.ones(len(part), dtype=np.int64)]))
    prov = [[(base_id, int(i))] for i in keep] + [[(donor_id, int(i))] for i in part]
    prov[bmap[b]].append((donor_id, a))
    target = {base_id: bmap, donor_id: dmap}
    conf = {k: (v >= 0).astype(np.float64) for k, v in target.items()}
    chars = {base_id: base, donor_id: donor}
    for cid, jname, oname, c in extra:
        i = chars[cid].skeleton.index(jname)
        target[cid][i] = names.index(oname)
        conf[cid][i] = c
    maps = {k: BoneMap(k, target[k], conf[k]) for k in target}
    return skel, prov, maps


#: Mean angular acceleration (rad/s^2) below which joints count as not animated.
STATIC = 0.05


def acceleration_figures(skeleton, inputs, maps, provenance, clips, keys):
    """Mean angular acceleration of the completed joints, output over source, per input.

    For the clips completed for input ``x``, the completed joints are those whose provenance
    does not list ``x``; the reference is the same joints driven by the other input's own
    clips (mapped onto S_R).
    """
    out = {}
    for x in inputs:
        comp = np.array([x not in [cid for cid, _ in prov] for prov in provenance])
        if not comp.any():
            continue
        acc_out = []
        for clip, (cid, _) in zip(clips, keys):
            if cid == x:
                _, R, _ = sample_clip(skeleton, clip, clip_times(clip))
                acc_out.append(angular_acceleration(R[:, comp]).ravel())
        acc_src = []
        for y, ch in inputs.items():
            if y == x:
                continue
            for clip in ch.clips:
                T, R, S = sample_clip(ch.skeleton, clip, clip_times(clip))
                _, Ro, _, _ = map_pose(skeleton, ch.skeleton, maps[y], T, R, S)
                acc_src.append(angular_acceleration(Ro[:, comp]).ravel())
        a, b = np.concatenate(acc_out), np.concatenate(acc_src)
        if b.mean() < STATIC:  # the source barely moves these joints: no meaningful ratio
            out[x] = {"mean_ratio": None, "p95_ratio": None, "max_ratio": None,
                      "mean_output": float(a.mean()), "mean_source": float(b.mean())}
            continue
        out[x] = {"mean_ratio": float(a.mean() / b.mean()),
                  "p95_ratio": float(np.percentile(a, 95) / np.percentile(b, 95)),
                  "max_ratio": float(a.max() / b.max()),
                  "mean_output": float(a.mean()), "mean_source": float(b.mean())}
    return out


def _angles_to_source(skeleton_out, clip, source, source_clip, joints_out, joints_in):
    t = clip_times(source_clip)
    _, R0, _ = sample_clip(source.skeleton, source_clip, t)
    _, R1, _ = sample_clip(skeleton_out, clip, t)
    return quat_angle(R0[:, joints_in], R1[:, joints_out])


# --------------------------------------------------------------------------------------------
# kernels against slow references


def _scores_reference(Ga, Pa, Gb, Pb, w, rw, tw, length, metric):
    """Obviously correct double loop over pairs of frames."""
    out = np.zeros((len(Ga), len(Gb)))
    for a in range(len(Ga)):
        for b in range(len(Gb)):
            r = d = 0.0
            for j in range(len(w)):
                dot = float(np.dot(Ga[a, j], Gb[b, j]))
                r += w[j] * (dot * dot if metric == "squared" else abs(dot))
                d += w[j] * float(np.sum((Pa[a, j] - Pb[b, j]) ** 2))
            out[a, b] = rw * r / w.sum() + tw * np.exp(-d / (w.sum() * length**2))
    return out


@pytest.mark.parametrize("metric", ["squared", "abs"])
def test_keyframe_scores_match_slow_reference(metric):
    rng = np.random.default_rng(7)
    J, Fa, Fb = 6, 9, 13
    Ga, Gb = random_quats(rng, (Fa, J)), random_quats(rng, (Fb, J))
    Pa, Pb = rng.normal(size=(Fa, J, 3)), rng.normal(size=(Fb, J, 3))
    w = rng.uniform(0, 1, J)
    w[2] = 0.0
    fast = keyframe_scores(Ga, Pa, Gb, Pb, w, rotation_weight=0.8, translation_weight=0.2,
                           length=2.5, metric=metric)
    slow = _scores_reference(Ga, Pa, Gb, Pb, w, 0.8, 0.2, 2.5, metric)
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    # sign of quaternions is irrelevant
    flip = keyframe_scores(-Ga, Pa, Gb, Pb, w, length=2.5, metric=metric)
    np.testing.assert_allclose(flip, fast, atol=1e-12)
    # single precision (centred features): close to the reference
    f32 = keyframe_scores(Ga, Pa, Gb, Pb, w, length=2.5, metric=metric, dtype=np.float32)
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, slow, atol=2e-6)


def test_rotation_features_give_squared_dots():
    rng = np.random.default_rng(1)
    Qa, Qb = random_quats(rng, (5, 3)), random_quats(rng, (4, 3))
    w = np.array([0.5, 1.0, 2.0])
    got = rotation_features(Qa, w) @ rotation_features(Qb, w).T
    want = np.einsum("j,abj->ab", w, np.einsum("ajk,bjk->abj", Qa, Qb) ** 2)
    np.testing.assert_allclose(got, want, atol=1e-13)


def _continuity_reference(S, seg, weights):
    Fa, Fb = S.shape
    out = np.zeros_like(S)
    for a in range(Fa):
        for b in range(Fb):
            num, den = S[a, b], 1.0
            for step, wk in enumerate(weights, start=1):
                for k in (-step, step):
                    if 0 <= a + k < Fa and 0 <= b + k < Fb and seg[b + k] == seg[b]:
                        num += wk * S[a + k, b + k]
                        den += wk
            out[a, b] = num / den
    return out


@pytest.mark.parametrize("Fa, lengths, weights", [(7, [3, 2, 4, 2], (0.2, 0.1)),
                                                  (20, [6, 1, 9, 2, 12], (0.2, 0.1)),
                                                  (3, [5, 5], (0.3, 0.0, 0.05)),
                                                  (1, [2, 3], (0.2, 0.1))])
def test_continuity_matches_slow_reference(Fa, lengths, weights):
    rng = np.random.default_rng(3)
    seg = np.repeat(np.arange(len(lengths)), lengths)
    S = rng.normal(size=(Fa, len(seg)))
    want = _continuity_reference(S, seg, weights)
    np.testing.assert_allclose(continuity_scores(S, seg, weights), want, atol=1e-13)
    got32 = continuity_scores(S.astype(np.float32), seg, weights)
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, want, atol=1e-5)


def test_choose_frames_viterbi_matches_brute_force():
    rng = np.random.default_rng(5)
    seg = np.array([0, 0, 0, 1, 1])
    for _ in range(20):
        S = rng.uniform(size=(4, 5))
        lam = 0.3
        path = choose_frames(S, seg, jump_penalty=lam)

        def total(p):
            cost = sum(S[a, b] for a, b in enumerate(p))
            cost -= lam * sum(not (q == p_ + 1 and seg[q] == seg[p_]) for p_, q in zip(p, p[1:]))
            return cost

        best = max(itertools.product(range(5), repeat=4), key=total)
        assert total(tuple(path)) == pytest.approx(total(best), abs=1e-12)
    np.testing.assert_array_equal(choose_frames(S, seg, jump_penalty=0.0), S.argmax(axis=1))
    pinned = choose_frames(S, seg, jump_penalty=lam, fixed={2: 4})
    assert pinned[2] == 4


def test_hop_weights_on_a_chain():
    parents = np.array([-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 2])
    w = hop_weights(parents, [1])
    d = np.array([1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 2])
    want = np.where(d <= 2, 1.0, 2.0 ** -(d - 2.0))
    want[d > 8] = 0.0
    np.testing.assert_allclose(w, want)


def test_angular_acceleration_of_constant_and_accelerating_spin():
    t = np.arange(20) / 30.0
    for alpha in (0.0, 3.0):
        angle = 2.0 * t + 0.5 * alpha * t**2
        q = np.stack([np.zeros_like(t), np.sin(angle / 2), np.zeros_like(t), np.cos(angle / 2)], -1)
        acc = angular_acceleration(q[:, None], fps=30.0)
        np.testing.assert_allclose(acc, alpha, atol=1e-6)


def test_blend_seams_removes_the_jump_and_fades_out():
    from rigmix.animation.transitions import blend_seams

    t = np.arange(40) / 30.0
    angle = 1.5 * t
    angle[20:] -= 0.6  # a jump of -0.6 rad between frames 19 and 20
    q = np.stack([np.zeros_like(t), np.sin(angle / 2), np.zeros_like(t), np.cos(angle / 2)], -1)[:, None]
    T = np.zeros((40, 1, 3))
    T[20:, 0, 0] = 1.0
    Rb, Tb = blend_seams(q, T, [19], 8)
    step = quat_angle(Rb[1:], Rb[:-1])[:, 0]
    assert step[19] == pytest.approx(1.5 / 30, abs=1e-9)  # the seam continues the motion
    assert step.max() <= 1.5 / 30 + 0.6 * 1.5 / 8 + 1e-9  # the offset fades at most 1.5/8 per frame
    np.testing.assert_allclose(quat_angle(Rb[28:], q[28:]), 0.0, atol=1e-12)  # faded out
    np.testing.assert_allclose(Rb[:20], q[:20])
    assert abs(Tb[20, 0, 0]) < 1e-12 and Tb[28, 0, 0] == 1.0


def test_smooth_seams_leaves_frames_far_from_seams_untouched():
    rng = np.random.default_rng(2)
    R = random_quats(rng, (60, 2))
    T = rng.normal(size=(60, 2, 3))
    Rs, Ts = smooth_seams(R, T, [30], 1.5)
    far = np.r_[0:15, 46:60]
    assert quat_angle(Rs[far], R[far]).max() < 1e-3
    assert quat_angle(Rs[28:33], R[28:33]).max() > 1e-2  # the seam itself is smoothed


# --------------------------------------------------------------------------------------------
# mapping keyframes onto S_R


def _chain(n, rots=None):
    rots = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)) if rots is None else rots
    return Skeleton([f"j{i}" for i in range(n)], np.arange(n) - 1, np.tile([0.0, 1.0, 0.0], (n, 1)),
                    rots, np.ones((n, 3)), np.tile(np.eye(4), (n, 1, 1)))


def test_map_pose_accumulates_chains_and_blends_confidence():
    rng = np.random.default_rng(4)
    src = _chain(4, random_quats(rng, (4,)))
    r = src.rotations
    # S_R: the source chain with joints 1 and 2 merged (rest = their product)
    out = _chain(3, np.stack([r[0], quat_multiply(r[1], r[2]), r[3]]))
    F = 5
    R = random_quats(rng, (F, 4))
    T = np.broadcast_to(src.translations, (F, 4, 3))
    S = np.ones((F, 4, 3))
    m = BoneMap("x", np.array([0, 1, 1, 2]), np.ones(4))
    _, Ro, _, mass = map_pose(out, src, m, T, R, S)
    np.testing.assert_allclose(mass, 1.0)
    # accumulated rotations: global rotations of S_R equal the source's at the chain ends
    Gs, Go = global_rotations(src.parents, R), global_rotations(out.parents, Ro)
    np.testing.assert_allclose(quat_angle(Go, Gs[:, [0, 2, 3]]), 0.0, atol=1e-6)
    # confidence 0.5 halves the local delta angle; confidence 0 leaves the rest pose
    half = BoneMap("x", np.array([0, 1, -1, 2]), np.array([1.0, 0.5, 0.0, 0.0]))
    _, Rh, _, mass = map_pose(out, src, half, T, R, S)
    np.testing.assert_allclose(mass, [1.0, 0.5, 0.0])
    full_delta = quat_angle(src.rotations[1], R[:, 1])
    np.testing.assert_allclose(quat_angle(out.rotations[1], Rh[:, 1]), full_delta / 2, atol=1e-9)
    np.testing.assert_allclose(quat_angle(out.rotations[2], Rh[:, 2]), 0.0, atol=1e-7)


# --------------------------------------------------------------------------------------------
# self-composition: the exact answer is known


@pytest.fixture(scope="module")
def fox():
    from rigmix.io import load_character

    return load_character(asset("Fox"))


def _self_compose(fox, part_root, options, selection=None):
    sk = fox.skeleton
    J = sk.num_joints
    part = sk.subtree(part_root)
    prov = [[("B", j)] if part[j] else [("A", j)] for j in range(J)]
    prov[part_root] = [("A", part_root), ("B", part_root)]
    maps = {k: BoneMap(k, np.arange(J), np.ones(J)) for k in "AB"}
    clips = complete_clips(sk, {"A": fox, "B": fox}, maps, options=options, provenance=prov, selection=selection)
    return clips, part


@pytest.mark.parametrize("part_name, options", [
    ("b_Tail01_012", CompletionOptions()),
    ("b_Spine02_03", CompletionOptions()),
    ("b_Spine02_03", CompletionOptions(metric="abs", jump_penalty=0.0)),  # the paper's rule
])
def test_self_composition_reproduces_every_clip(fox, part_name, options):
    names = [c.name for c in fox.clips]
    # by default a file listed twice gives its clips once, under their own names
    clips, part = _self_compose(fox, fox.skeleton.index(part_name), options)
    assert [c.name for c in clips] == names
    # each id's clips, when both are asked for, are completed from the other's part
    clips_both, _ = _self_compose(fox, fox.skeleton.index(part_name), options,
                                  selection=[(k, n) for k in "AB" for n in names])
    assert [c.name for c in clips_both] == [f"{k}:{n}" for k in "AB" for n in names]
    J = np.arange(fox.skeleton.num_joints)
    for clip in clips + clips_both:
        src = fox.clip(clip.name.split(":", 1)[-1])
        err = _angles_to_source(fox.skeleton, clip, fox, src, J, J)  # (F, J) radians
        assert err.max() < 1e-3, (clip.name, float(err.max()))
        assert len(clip.tracks) == 3 * len(J)


def test_self_composition_without_provenance_uses_confidence(fox):
    """No provenance: ownership from confidence-1 reach; a half-confident tail is completed."""
    sk = fox.skeleton
    J = sk.num_joints
    tail = sk.subtree(sk.index("b_Tail01_012"))
    ca = np.where(tail & (np.arange(J) != sk.index("b_Tail01_012")), 0.9, 1.0)
    cb = np.where(tail, 1.0, 0.9)
    maps = {"A": BoneMap("A", np.arange(J), ca), "B": BoneMap("B", np.arange(J), cb)}
    clips = complete_clips(sk, {"A": fox, "B": fox}, maps, selection=[("A", "Survey"), ("A", "Run")])
    assert [c.name for c in clips] == ["Survey", "Run"]
    for clip in clips:
        err = _angles_to_source(sk, clip, fox, fox.clip(clip.name), np.arange(J), np.arange(J))
        assert err.max() < 1e-3


def test_fixed_frames_and_sources_are_honoured(fox):
    sk = fox.skeleton
    J = sk.num_joints
    tail = sk.index("b_Tail01_012")
    opts = CompletionOptions(
        clips={"A": ["Survey"]}, sources={"B": ["Walk"]}, smoothing=0.0, blend_frames=0,
        fixed_frames=(FixedFrame("A", "Survey", 10, "B", "Walk", 3),))
    clips, part = _self_compose(fox, tail, opts)
    (clip,) = clips
    assert clip.name == "Survey"
    t = clip_times(fox.clip("Survey"))
    _, R, _ = sample_clip(sk, clip, t)
    _, Rw, _ = sample_clip(sk, fox.clip("Walk"), clip_times(fox.clip("Walk")))
    kids = np.flatnonzero(part & (np.arange(J) != tail))
    # frame 10 pinned to Walk frame 3
    assert quat_angle(R[10, kids], Rw[3, kids]).max() < 1e-6
    # every completed frame comes from Walk: each tail pose is one of Walk's tail poses
    d = quat_angle(R[:, None, kids], Rw[None, :, kids]).max(axis=2).min(axis=1)
    assert d.max() < 1e-6


@pytest.mark.parametrize("fixed, sources, match", [
    (FixedFrame("A", "Survey", 10, "B", "Swim", 3), None, r"Fox\.glb \(character 'B'\): no clip 'Swim'"),
    (FixedFrame("A", "Swim", 10, "B", "Walk", 3), None, r"Fox\.glb \(character 'A'\): no clip 'Swim'"),
    (FixedFrame("A", "Survey", 10, "C", "Walk", 3), None, "a fixed frame names character 'C'"),
    (FixedFrame("A", "Survey", 10**6, "B", "Walk", 3), None,
     r"Fox\.glb \(character 'A'\): clip 'Survey': fixed frame 1000000 is outside the clip \(\d+ frames"),
    (FixedFrame("A", "Survey", 10, "B", "Walk", 10**6), None,
     r"Fox\.glb \(character 'B'\): clip 'Walk': fixed frame source_frame 1000000 is outside the clip"),
    (FixedFrame("A", "Survey", 10, "B", "Run", 3), {"B": ["Walk"]},
     r"Fox\.glb \(character 'B'\): clip 'Run': .*sources leaves it out"),
])
def test_bad_fixed_frame_names_the_file_and_the_clip(fox, fixed, sources, match):
    """A fixed frame out of its clip, or naming a clip or input that does not exist, is refused
    naming the file and the clip (an unknown name was silently ignored)."""
    opts = CompletionOptions(clips={"A": ["Survey"]}, sources=sources, fixed_frames=(fixed,))
    with pytest.raises(InputError, match=match):
        _self_compose(fox, fox.skeleton.index("b_Tail01_012"), opts)


def test_bad_selection_is_a_clear_error(fox):
    J = fox.skeleton.num_joints
    maps = {"A": BoneMap("A", np.arange(J), np.ones(J))}
    with pytest.raises(InputError, match=r"Fox\.glb \(character 'A'\): no clip 'Swim' to complete; its clips: "
                                         "'Survey', 'Walk', 'Run'"):
        complete_clips(fox.skeleton, {"A": fox}, maps, selection=[("A", "Swim")])
    with pytest.raises(InputError, match="bone map"):
        complete_clips(fox.skeleton, {"A": fox, "B": fox}, maps)


# --------------------------------------------------------------------------------------------
# two different characters


def _check_centaur(skel, inputs, maps, prov, clips):
    """Every clip of both inputs completed, the completed part moving; acceleration figures."""
    keys = [(cid, c.name) for cid, ch in inputs.items() for c in ch.clips]
    assert len(clips) == len(keys)
    assert len({c.name for c in clips}) == len(clips)
    rest = quat_normalize(skel.rotations)
    for clip, (cid, _) in zip(clips, keys):
        comp = np.array([cid not in [k for k, _ in p] for p in prov])
        _, R, _ = sample_clip(skel, clip, clip_times(clip))
        Rc = R[:, comp]
        # the completed part moves: away from rest and changing over time
        assert quat_angle(Rc, rest[comp]).max() > 0.05, clip.name
        assert quat_angle(Rc[1:], Rc[:-1]).max() > 1e-3, clip.name
    return acceleration_figures(skel, inputs, maps, prov, clips, keys)


@pytest.fixture(scope="module")
def builtin_centaur():
    """examples/centaur.toml through the operations and mapping stages (built-in characters)."""
    import rigmix

    return rigmix.compose(Path(__file__).parent.parent / "examples" / "centaur.toml", until="mapping")


def test_centaur_from_examples_completes_everything_smoothly(builtin_centaur):
    quad, human = builtin_centaur.inputs["body"], builtin_centaur.inputs["rider"]
    extra = [("human", "Hips", "Hips", 0.5), ("human", "Spine", "Spine", 0.6),
             ("quad", "Head", "human.Head", 0.7)]
    skel, prov, maps = graft(quad, "quad", "Neck", human, "human", "Chest", extra=extra)
    inputs = {"quad": quad, "human": human}
    clips = complete_clips(skel, inputs, maps, provenance=prov)
    # both inputs have a 'walk' and an 'idle': prefixed with the character id
    assert [c.name for c in clips] == ["quad:walk", "trot", "quad:idle", "human:walk", "human:idle"]
    figs = _check_centaur(skel, inputs, maps, prov, clips)
    for x, f in figs.items():
        assert f["mean_ratio"] is None or f["mean_ratio"] <= 2.0, (x, f)


@pytest.fixture(scope="module")
def centaur():
    from rigmix.io import load_character

    horse, knight = load_character(asset("Horse")), load_character(asset("Knight"))
    extra = [("knight", "Body", "Body", 0.5), ("knight", "Hips", "Torso", 0.6),
             ("knight", "Abdomen", "Torso2", 0.7), ("horse", "Neck1", "knight.Neck", 0.6),
             ("horse", "Neck2", "knight.Neck", 0.6), ("horse", "Neck3", "knight.Neck", 0.6),
             ("horse", "Head", "knight.Head", 0.7)]
    skel, prov, maps = graft(horse, "horse", "Torso3", knight, "knight", "Torso", drop="Neck1", extra=extra)
    return skel, prov, maps, {"horse": horse, "knight": knight}


def test_centaur_horse_knight(centaur):
    skel, prov, maps, inputs = centaur
    clips = complete_clips(skel, inputs, maps, provenance=prov)
    assert [c.name for c in clips] == [c.name for ch in inputs.values() for c in ch.clips]
    figs = _check_centaur(skel, inputs, maps, prov, clips)
    for x, f in figs.items():
        assert f["mean_ratio"] is None or f["mean_ratio"] <= 2.0, (x, f)


def test_global_positions_match_matrix_forward_kinematics(fox):
    from rigmix.animation.keyframes import global_positions as _global_positions
    from rigmix.transforms import trs_to_matrix

    clip = fox.clip("Run")
    T, R, S = sample_clip(fox.skeleton, clip, clip_times(clip)[:10])
    want = fox.skeleton.world_matrices(trs_to_matrix(T, R, S))[..., :3, 3]
    got = _global_positions(fox.skeleton, T, R, S)
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())


# --------------------------------------------------------------------------------------------
# through the real pipeline: operations and mapping stages, then completion


def _compose_until_mapping(config, *assets):
    import rigmix

    for name in assets:
        asset(name)  # skip (or fail under CI) when an asset is missing
    return rigmix.compose(Path(__file__).parent / "configs" / config, until="mapping")


def test_pipeline_self_composition_reproduces_the_clip():
    comp = _compose_until_mapping("self_composition.toml", "CesiumMan")
    plan = comp.plan
    keys = [(cid, c.name) for cid, ch in comp.inputs.items() for c in ch.clips]
    assert len(keys) == 2  # one file under two ids
    assert len(complete_clips(plan.skeleton, comp.inputs, comp.maps, provenance=plan.provenance)) == 1
    clips = complete_clips(plan.skeleton, comp.inputs, comp.maps, provenance=plan.provenance, selection=keys)
    assert len(clips) == 2
    for clip, (cid, name) in zip(clips, keys):
        src = comp.inputs[cid]
        target = np.asarray(comp.maps[cid].target)
        ok = np.flatnonzero(target >= 0)
        assert ok.size == src.skeleton.num_joints  # every joint has its copy in S_R
        err = _angles_to_source(plan.skeleton, clip, src, src.clip(name), target[ok], ok)
        assert err.max() < 1e-3, (cid, name, float(err.max()))


@pytest.mark.parametrize("config, assets", [("centaur.toml", ("Horse", "Knight")),
                                            ("tail_graft.toml", ("CesiumMan", "Velociraptor"))])
def test_pipeline_centaur_and_tail_graft(config, assets):
    comp = _compose_until_mapping(config, *assets)
    plan = comp.plan
    clips = complete_clips(plan.skeleton, comp.inputs, comp.maps, provenance=plan.provenance)
    figs = _check_centaur(plan.skeleton, comp.inputs, comp.maps, plan.provenance, clips)
    assert any(f["mean_ratio"] is not None for f in figs.values())
    for x, f in figs.items():
        assert f["mean_ratio"] is None or f["mean_ratio"] <= 2.0, (config, x, f)


def test_completion_stage_on_the_builtin_centaur(builtin_centaur):
    """The stage as the pipeline runs it, on examples/centaur.toml (built-in characters)."""
    import dataclasses

    from rigmix.config import AnimationOptions
    from rigmix.pipeline import completion_stage

    comp = builtin_centaur
    out = completion_stage(comp)
    clips = out.clips
    assert [c.name for c in clips] == ["body:walk", "trot", "body:idle", "rider:walk", "rider:idle"]
    assert out.report["animation"]["clips"] == [c.name for c in clips]
    figs = _check_centaur(comp.plan.skeleton, comp.inputs, comp.maps, comp.plan.provenance, clips)
    for x, f in figs.items():
        assert f["mean_ratio"] is None or f["mean_ratio"] <= 2.0, (x, f)
    # options from a config section
    opts = AnimationOptions.model_validate({"jump_penalty": 0.1, "fixed_frames": [
        {"character": "body", "clip": "walk", "frame": 0, "source": "rider", "source_clip": "idle",
         "source_frame": 0}]}).to_params()
    assert opts.jump_penalty == 0.1 and isinstance(opts.fixed_frames[0], FixedFrame)
    with pytest.raises(InputError, match=r"animation\.jump: unknown key"):  # at load, before any stage
        comp.config.with_options(animation={"jump": 1})
    assert dataclasses.asdict(AnimationOptions().to_params()) == dataclasses.asdict(CompletionOptions())


def test_a_static_input_leaves_the_clips_own_mapped_pose(fox, caplog):
    import dataclasses

    sk = fox.skeleton
    J = sk.num_joints
    tail = sk.index("b_Tail01_012")
    part = sk.subtree(tail)
    prov = [[("B", j)] if part[j] else [("A", j)] for j in range(J)]
    prov[tail] = [("A", tail), ("B", tail)]
    maps = {k: BoneMap(k, np.arange(J), np.ones(J)) for k in "AB"}
    static = dataclasses.replace(fox, clips=())
    with caplog.at_level("WARNING", logger="rigmix.animation.completion"):
        (clip,) = complete_clips(sk, {"A": fox, "B": static}, maps, provenance=prov,
                                 selection=[("A", "Walk")])
    assert "no clip to complete" in caplog.text
    # A maps its own tail onto those joints: the tail keeps A's animation
    err = _angles_to_source(sk, clip, fox, fox.clip("Walk"), np.arange(J), np.arange(J))
    assert err.max() < 1e-6
    # a tail A does not map stays at rest
    cut = np.where(part & (np.arange(J) != tail), -1, np.arange(J))
    maps["A"] = BoneMap("A", cut, np.ones(J))
    (clip,) = complete_clips(sk, {"A": fox, "B": static}, maps, provenance=prov, selection=[("A", "Walk")])
    _, R, _ = sample_clip(sk, clip, clip_times(clip))
    kids = np.flatnonzero(cut < 0)
    np.testing.assert_allclose(quat_angle(R[:, kids], sk.rotations[kids]), 0.0, atol=1e-7)


def test_replaced_limb_root_is_completed_when_the_rest_bones_disagree():
    """examples/beast_arms.toml: the humanoid's T-pose arms replaced by a quadruped's hanging
    front legs. The human's walk lowers its arms by about 72 degrees from rest; that delta used
    to swing the legs 72 degrees out of place. The fused arm roots (and the neck) are now
    completed from the quadruped's frames in the human's clips, and stay near the legs' own
    range of motion; an attach (the tail graft's hips) and a disabled threshold change nothing."""
    import dataclasses

    import rigmix
    from rigmix.animation.completion import limb_roots_to_complete
    from rigmix.pipeline import completion_stage

    examples = Path(__file__).parent.parent / "examples"
    comp = rigmix.compose(examples / "beast_arms.toml", until="mapping")
    S = comp.plan.skeleton
    found = limb_roots_to_complete(comp.plan)
    assert sorted(S.names[o] for o, _ in found) == ["Neck", "UpperArm.L", "UpperArm.R"]
    assert {t for _, t in found} == {"human"}
    assert limb_roots_to_complete(comp.plan, 180.0) == []
    tailed = rigmix.compose(examples / "tailed_humanoid.toml", until="mapping")
    assert limb_roots_to_complete(tailed.plan) == []  # the hips keep the human's children

    def arm_swing(c):
        clip = next(k for k in c.clips if k.name == "human:walk")
        t = clip_times(clip, 30.0)
        _, R, _ = sample_clip(S, clip, t)
        j = S.index("UpperArm.L")
        rest = np.broadcast_to(quat_normalize(S.rotations[j]), R[:, j].shape)
        return np.degrees(quat_angle(rest, R[:, j]))  # off the rest rotation, per frame

    new = arm_swing(completion_stage(comp))
    old_cfg = comp.config.with_options(animation={"rest_mismatch": 180.0})
    old = arm_swing(completion_stage(dataclasses.replace(comp, config=old_cfg)))
    assert old.min() > 60.0, old.min()  # the human's lowered T-pose arm on the hanging leg
    assert new.max() < 45.0, new.max()  # the quadruped's own walk swing


# --------------------------------------------------------------------------------------------
# clip fidelity (issue 25): the joints an input keeps replay its own clips


def test_map_pose_replays_kept_joints_exactly():
    """A joint kept from the input (confidence 1) takes its own rotation, not accumulated with a
    dropped joint the propagation also put there (a removed thumb on the palm), and translation
    keys keep their size (without maps: the bone-length ratio, 1 here)."""
    rng = np.random.default_rng(7)
    src = _chain(4, random_quats(rng, (4,)))
    out = _chain(3, src.rotations[:3])
    F = 6
    R = random_quats(rng, (F, 4))
    T = src.translations + rng.normal(scale=0.1, size=(F, 4, 3))
    S = np.ones((F, 4, 3))
    m = BoneMap("x", np.array([0, 1, 2, 2]), np.array([1.0, 1.0, 1.0, 0.6]))
    To, Ro, _, _ = map_pose(out, src, m, T, R, S)
    np.testing.assert_allclose(quat_angle(Ro, R[:, :3]), 0.0, atol=1e-6)
    np.testing.assert_allclose(To, T[:, :3], atol=1e-12)
    # with maps: each key goes through its joint's linear map
    L = np.stack([np.eye(3) * (k + 1) for k in range(4)])
    To, _, _, _ = map_pose(out, src, m, T, R, S, translation_maps=L)
    np.testing.assert_allclose(To - out.translations, (T[:, :3] - src.translations[:3]) * [[[1.0], [2.0], [3.0]]],
                               atol=1e-12)


def _completed(config_path):
    import rigmix
    from rigmix.pipeline import completion_stage

    return completion_stage(rigmix.compose(config_path, until="mapping"))


def test_body_clips_replay_after_a_cross_rig_graft():
    """three_characters: the Knight (armature x100) keeps its body and gets the Fox's head and
    CesiumMan's arm. Its own clips must move its own joints as in the file: translation keys of
    its feet and hips once came out 14 times too large and the palm was twisted by the removed
    thumb (fidelity 9 and 0.07 diagonals)."""
    for name in ("Knight", "Fox", "CesiumMan"):
        asset(name)
    comp = _completed(Path(__file__).parent / "configs" / "three_characters.toml")
    a = comp.report["animation"]
    assert set(a["fidelity_max"]) == {"knight", "fox", "cesium"}
    assert max(a["fidelity_max"].values()) <= 1e-4, (a["fidelity_max"], a["fidelity_worst"])


def test_fidelity_sees_a_moved_joint():
    """The measure itself: moving the body's root by 1 cm in one frame of its clip shows as
    1 cm over the diagonal; the grafted arm, measured from its fused ancestor, does not move."""
    import dataclasses

    from rigmix.animation.completion import completion_provenance, selected_clips
    from rigmix.animation.fidelity import clip_fidelity
    from rigmix.character import Track

    for name in ("Knight", "CesiumMan"):
        asset(name)
    comp = _completed(Path(__file__).parent / "configs" / "knight_arm.toml")
    plan = comp.plan
    clips = list(comp.clips)
    keys = selected_clips(comp.inputs, CompletionOptions())
    k = keys.index(("man", "clip_0"))
    tracks = list(clips[k].tracks)
    i = next(n for n, t in enumerate(tracks) if t.joint == 0 and t.path == "translation")
    values = np.array(tracks[i].values)
    values[3] += [0.01, 0.0, 0.0]
    tracks[i] = Track(0, "translation", tracks[i].times, values, "LINEAR")
    clips[k] = dataclasses.replace(clips[k], tracks=tuple(tracks))
    prov = completion_provenance(plan)
    before = clip_fidelity(plan.skeleton, comp.clips, keys, comp.inputs, plan.positioned, plan.transforms, prov,
                           comp.maps, diagonal=2.0)
    after = clip_fidelity(plan.skeleton, clips, keys, comp.inputs, plan.positioned, plan.transforms, prov,
                          comp.maps, diagonal=2.0)
    # the root's anchor turns the offset, lengths stay
    assert before["man"].max < 1e-9 and after["man"].max == pytest.approx(0.005, rel=1e-6)
    assert after["man"].frame == 3 and after["man"].clip == "clip_0"
    assert after["knight"].max == before["knight"].max < 1e-6
    assert after["knight"].measured_joints == 7  # the arm from UpperArm.L down, the fused joint included


def _rest_relative(rest, R):
    """``rest^-1 R``: local rotations ``(F, k, 4)`` xyzw as deltas from the rest rotations ``(k, 4)``."""
    return quat_multiply(quat_conjugate(quat_normalize(rest))[None], quat_normalize(R))


def test_a_mirrored_copy_follows_the_joints_it_replaces():
    """A mirrored arm swap (the humanoid's right arm, mirrored, on its left): in the body's walk
    the new arm swings as the body's own left arm does, not as the mirrored character's walk
    swings it (the right arm's swing reflected, half a step out of phase); in the mirrored
    character's walk the body follows that walk's own joints (the walk reflected, whole)."""
    import rigmix
    from rigmix.config import Config
    from rigmix.pipeline import completion_stage

    cfg = Config(name="mirrored_arm", characters={"body": {"path": "builtin:humanoid"},
                                                  "donor": {"path": "builtin:humanoid", "mirror": True}},
                 actions=[{"op": "replace", "source": "donor", "source_joint": "UpperArm.L",
                           "target": "body", "target_joint": "UpperArm.L"}])
    comp = completion_stage(rigmix.compose(cfg, until="mapping"))
    S = comp.plan.skeleton
    by_name = {c.name: c for c in comp.clips}
    for owner, driver in (("donor", "body"), ("body", "donor")):
        joints = [o for o, prov in enumerate(comp.plan.provenance) if [c for c, _ in prov] == [owner]]
        assert len(joints) >= 2  # LowerArm.L, Hand.L (UpperArm.L is fused); the body's many
        src = comp.inputs[driver]
        same = [src.skeleton.names.index(S.names[o]) for o in joints]
        for clip in ("walk", "idle"):
            out = by_name[f"{driver}:{clip}"]
            t = clip_times(out, 30.0)
            _, Ro, _ = sample_clip(S, out, t)
            _, Ri, _ = sample_clip(src.skeleton, src.clip(clip), t)
            got = _rest_relative(S.rotations[joints], Ro[:, joints])
            want = _rest_relative(src.skeleton.rotations[same], Ri[:, same])
            np.testing.assert_allclose(quat_angle(got, want), 0.0, atol=1e-7)


def test_a_detached_part_follows_its_tip_at_the_offset_it_is_given():
    """A root, a two-bone leg under it, and a foot hanging from the root beside the leg's tip
    (an IK foot): placed by :func:`follow_tips`, the foot's world transform is the tip's times the
    rest offset (no input offset), or times the input's offset carried through ``B``; the leg is
    left as it was, and the foot's own rest offset (``D = I``) gives the rest placement back."""
    from rigmix.animation.detached import Follower, follow_tips
    from rigmix.transforms import quat_normalize, quat_to_matrix, trs_to_matrix

    rng = np.random.default_rng(7)
    names = ["root", "hip", "knee", "foot"]
    parents = np.array([-1, 0, 1, 0])
    t = np.array([[0.0, 0.0, 0.0], [0.2, 1.0, 0.0], [0.0, -0.5, 0.1], [0.2, 0.5, 0.1]])
    r = quat_normalize(rng.normal(size=(4, 4)) * [0.2, 0.2, 0.2, 1.0])
    sk = Skeleton(names, parents, t, r, np.ones((4, 3)), np.tile(np.eye(4), (4, 1, 1)))
    F = 5
    T = np.broadcast_to(t, (F, 4, 3)).copy()
    R = quat_normalize(rng.normal(size=(F, 4, 4)) * [0.3, 0.3, 0.3, 1.0])
    S = np.ones((F, 4, 3))
    rest = sk.rest_worlds()
    B = np.eye(4)
    B[:3, :3] = 2.0 * quat_to_matrix(quat_normalize(np.array([0.1, -0.2, 0.3, 1.0])))  # input frame: twice as large
    O_rest = np.linalg.solve(rest[2], rest[3]) @ np.diag([0.5, 0.5, 0.5, 1.0])  # any rest offset in the input
    f = Follower("donor", 3, 2, 3, 2, O_rest, B, ("body",))
    D = trs_to_matrix(rng.normal(size=(F, 3)) * 0.1, quat_normalize(rng.normal(size=(F, 4))), np.ones((F, 3)))
    for off, want_rel in ((None, np.linalg.solve(rest[2], rest[3])[None]),
                          (np.broadcast_to(O_rest, (F, 4, 4)), np.linalg.solve(rest[2], rest[3])[None]),
                          (O_rest @ D, np.linalg.solve(rest[2], rest[3]) @ np.linalg.solve(B, D) @ B)):
        T2, R2, S2 = follow_tips(sk, T, R, S, [f], [off])
        W = sk.world_matrices(trs_to_matrix(T2, R2, S2))
        np.testing.assert_allclose(W[:, 3], W[:, 2] @ want_rel, atol=1e-12)
        for a, b in ((T2, T), (R2, R), (S2, S)):
            np.testing.assert_array_equal(a[:, :3], b[:, :3])


def test_a_kept_wing_joint_flaps_as_in_its_own_clip(tmp_path):
    """The Wasp's wings attached at the Rat's body with ``keep_joint`` (the corpus matrix's wings
    case): each wing is one joint, so fused with the Rat's joint it could never move. Kept, it
    turns in the Wasp's own clips as it turns there (the same rotation away from rest, at every
    frame), and the Rat's clips move it too (completed from the Wasp's frames)."""
    from conftest import corpus_case

    from rigmix.pipeline import compose

    comp = compose(corpus_case("wings__Rat__Wasp", tmp_path), until="completion")
    wasp = comp.inputs["donor"]
    sk, src = comp.skeleton, wasp.skeleton
    for name in ("Wing.L", "Wing.R"):
        o, j = sk.index(name), src.index(name)
        swings = []
        for clip in comp.clips:
            times = clip_times(clip, fps=30.0)
            R = sample_clip(sk, clip, times)[1][:, o]
            delta_out = quat_angle(np.broadcast_to(sk.rotations[o], R.shape), R)
            swings.append(float(delta_out.max()))
            theirs = [c for c in wasp.clips if c.name == clip.name]
            if theirs:
                R0 = sample_clip(src, theirs[0], times)[1][:, j]
                delta_in = quat_angle(np.broadcast_to(src.rotations[j], R0.shape), R0)
                assert np.allclose(delta_out, delta_in, atol=1e-5), (name, clip.name)
        assert len(swings) == len(comp.clips) > len(wasp.clips)
        assert min(swings) > np.radians(10.0), (name, swings)  # it flaps in every clip, the Rat's too


def test_a_detached_foot_stays_at_the_end_of_its_leg_in_every_clip(tmp_path):
    """Leela's leg and IK foot on EnemyLarge: the foot rests at her heel and follows it in every
    clip, EnemyLarge's (completed) and Leela's own (within 1% of the output's size); fused at
    EnemyLarge's foot it hung a tenth of the size away from the leg."""
    from conftest import corpus_case

    from rigmix.animation.keyframes import forward_kinematics
    from rigmix.pipeline import compose

    comp = compose(corpus_case("leg_swap__EnemyLarge__Leela", tmp_path), until="completion")
    sk = comp.skeleton
    size = float(np.linalg.norm(np.ptp(comp.surface.V, axis=0)))
    foot, heel = sk.index("Foot.L"), sk.index("FootBack.L")
    assert len(comp.clips) > len(comp.inputs["donor"].clips)
    for clip in comp.clips:
        T, R, S = sample_clip(sk, clip, clip_times(clip, fps=30.0))
        P = forward_kinematics(sk, T, R, S)[1]
        assert np.linalg.norm(P[:, foot] - P[:, heel], axis=1).max() < 0.01 * size, clip.name
