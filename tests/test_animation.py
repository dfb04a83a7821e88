"""Clip sampling: hand-computed values per interpolation, clamping, real clips at key times."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset
from scipy.spatial.transform import Rotation

from rigmix.animation import clip_times, resample_clip, sample_clip, sample_track
from rigmix.character import Clip, Skeleton, Track
from rigmix.io.gltf import read_gltf
from rigmix.transforms import quat_angle


def _quat_axis_angle(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = np.radians(deg) / 2
    return np.append(np.sin(h) * axis, np.cos(h))


def _same_rotation(a, b, atol=1e-12):
    """Equal as rotations (q and -q are the same rotation)."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    d = np.abs(np.sum(a * b, axis=-1))
    np.testing.assert_allclose(d, 1.0, atol=atol)


def test_linear_translation_by_hand():
    tr = Track(0, "translation", [0.0, 1.0, 3.0], [[0, 0, 0], [1, 2, 3], [3, 2, 1]], "LINEAR")
    out = sample_track(tr, [0.25, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(out, [[0.25, 0.5, 0.75], [1, 2, 3], [2, 2, 2], [3, 2, 1]], atol=1e-15)


def test_slerp_midpoint_is_45_degrees():
    axis = [1.0, 2.0, -0.5]
    q0 = _quat_axis_angle(axis, 0)
    q90 = _quat_axis_angle(axis, 90)
    tr = Track(0, "rotation", [0.0, 2.0], [q0, q90], "LINEAR")
    out = sample_track(tr, [1.0, 0.5])
    _same_rotation(out[0], _quat_axis_angle(axis, 45))
    _same_rotation(out[1], _quat_axis_angle(axis, 22.5))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-15)


def test_slerp_takes_the_shorter_arc():
    # the second key is stored with the opposite sign: same rotation, 90 degrees away
    tr = Track(0, "rotation", [0.0, 1.0], [_quat_axis_angle([0, 0, 1], 0),
                                            -_quat_axis_angle([0, 0, 1], 90)], "LINEAR")
    mid = sample_track(tr, [0.5])[0]
    np.testing.assert_allclose(quat_angle(mid, _quat_axis_angle([0, 0, 1], 0)), np.radians(45), atol=1e-12)
    _same_rotation(mid, _quat_axis_angle([0, 0, 1], 45))


def test_step_holds_the_previous_key():
    tr = Track(0, "scale", [0.0, 1.0, 2.0], [[1, 1, 1], [2, 2, 2], [3, 3, 3]], "STEP")
    out = sample_track(tr, [-1.0, 0.0, 0.99, 1.0, 1.5, 2.0, 7.0])
    np.testing.assert_array_equal(out[:, 0], [1, 1, 1, 2, 2, 3, 3])


def test_cubic_spline_by_hand():
    """glTF Hermite spline: p(u) = h00 v0 + h10 dt b0 + h01 v1 + h11 dt a1.

    Keys t = 0 and 2, values 0 and 1, out-tangent of key 0 = 1, in-tangent of key 1 = 0.5. At
    u = 0.5: 0.5*0 + 0.125*2*1 + 0.5*1 - 0.125*2*0.5 = 0.625.
    """
    values = np.array([[[9.0], [0.0], [1.0]], [[0.5], [1.0], [9.0]]])  # (k, 3, C): a, v, b
    tr = Track(0, "translation", [0.0, 2.0], values, "CUBICSPLINE")
    out = sample_track(tr, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(out[:, 0], [0.0, 0.625, 1.0], atol=1e-15)


def test_cubic_spline_reproduces_a_cubic_with_exact_tangents():
    """With tangents set to the derivative (per second), the spline is any cubic exactly.

    This pins the scaling of the tangents by the (non-uniform) key intervals.
    """
    f = lambda t: np.stack([t**3 - 2 * t**2 + 0.5 * t + 1, -t**2 + 3 * t, 0.25 * t**3], -1)  # noqa: E731
    df = lambda t: np.stack([3 * t**2 - 4 * t + 0.5, -2 * t + 3, 0.75 * t**2], -1)  # noqa: E731
    kt = np.array([0.0, 0.3, 1.0, 1.2, 2.5])
    values = np.stack([df(kt), f(kt), df(kt)], axis=1)
    tr = Track(0, "translation", kt, values, "CUBICSPLINE")
    t = np.linspace(0, 2.5, 101)
    np.testing.assert_allclose(sample_track(tr, t), f(t), atol=1e-12)
    # clamped outside the key range, to the key values (not extrapolated)
    np.testing.assert_allclose(sample_track(tr, [-1.0, 3.0]), f(np.array([0.0, 2.5])), atol=1e-12)


def test_cubic_spline_rotation_is_normalized():
    q0, q1 = _quat_axis_angle([0, 1, 0], 0), _quat_axis_angle([0, 1, 0], 120)
    values = np.stack([np.zeros((2, 4)), np.stack([q0, q1]), np.zeros((2, 4))], axis=1)
    tr = Track(0, "rotation", [0.0, 1.0], values, "CUBICSPLINE")
    out = sample_track(tr, np.linspace(0, 1, 11))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-14)
    # zero tangents and symmetric keys: at the middle the normalized average is the 60 degree pose
    _same_rotation(out[5], _quat_axis_angle([0, 1, 0], 60))


@pytest.mark.parametrize("interp", ["LINEAR", "STEP"])
def test_clamping_outside_the_key_range(interp):
    tr = Track(0, "translation", [1.0, 2.0], [[1, 0, 0], [2, 0, 0]], interp)
    out = sample_track(tr, [-5.0, 0.999, 2.001, 100.0])
    np.testing.assert_array_equal(out[:, 0], [1, 1, 2, 2])


def test_single_key_track_is_constant():
    tr = Track(0, "rotation", [0.5], [[0, 0, 2.0, 0]], "LINEAR")
    np.testing.assert_allclose(sample_track(tr, [0.0, 0.5, 9.0]), [[0, 0, 1.0, 0]] * 3)


def _skeleton():
    return Skeleton(
        ("a", "b", "c"), [-1, 0, 1], [[0, 0, 0], [0, 1, 0], [0, 1, 0]],
        [[0, 0, 0, 1], _quat_axis_angle([1, 0, 0], 30), [0, 0, 0, 1]], np.ones((3, 3)),
        np.eye(4)[None].repeat(3, 0),
    )


def test_sample_clip_keeps_rest_values_without_tracks():
    sk = _skeleton()
    clip = Clip("c", (Track(1, "translation", [0.0, 1.0], [[0, 1, 0], [0, 3, 0]]),
                      Track(2, "scale", [0.0, 1.0], [[1, 1, 1], [2, 2, 2]], "STEP")))
    T, R, S = sample_clip(sk, clip, [0.0, 0.5, 1.0])
    assert T.shape == (3, 3, 3) and R.shape == (3, 3, 4) and S.shape == (3, 3, 3)
    np.testing.assert_allclose(T[:, 1, 1], [1, 2, 3])
    np.testing.assert_array_equal(T[:, 0], np.zeros((3, 3)))
    np.testing.assert_array_equal(T[:, 2], [[0, 1, 0]] * 3)
    np.testing.assert_allclose(R, np.broadcast_to(sk.rotations, (3, 3, 4)))
    np.testing.assert_array_equal(S[:, 2, 0], [1, 1, 2])
    np.testing.assert_array_equal(S[:, :2], np.ones((3, 2, 3)))


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_sample_clip_samples_tracks_that_share_their_keys_as_each_alone(interpolation):
    """Tracks with the same key times are sampled together: every value is the one the track
    gives alone, for each path, a single key, and times outside the keys; a track without keys
    is refused."""
    rng = np.random.default_rng(11)
    sk = _skeleton()
    times = np.array([0.0, 0.4, 1.0])
    tracks = []
    for joint in range(3):
        for path, C in (("translation", 3), ("rotation", 4), ("scale", 3)):
            shape = (3, 3, C) if interpolation == "CUBICSPLINE" else (3, C)
            tracks.append(Track(joint, path, times, rng.normal(size=shape), interpolation))
    tracks.append(Track(0, "translation", [0.5], rng.normal(size=(3, 3) if interpolation == "CUBICSPLINE" else (1, 3)),
                        interpolation))
    tracks.pop(0)  # joint 0's translation: the single key above instead
    clip = Clip("c", tuple(tracks))
    t = np.array([-0.2, 0.0, 0.1, 0.4, 0.55, 0.99, 1.0, 1.3])
    T, R, S = sample_clip(sk, clip, t)
    out = {"translation": T, "rotation": R, "scale": S}
    for track in clip.tracks:  # the same operations; SIMD lanes may round the last bit apart
        np.testing.assert_allclose(out[track.path][:, track.joint], sample_track(track, t), rtol=1e-13, atol=1e-15)
    with pytest.raises(ValueError, match="no keys"):
        sample_track(Track(0, "translation", np.zeros(0), np.zeros((0, 3))), t)


def test_sample_clip_of_real_clips_is_the_tracks_sampled_alone():
    c = read_gltf(asset("Fox"))
    for clip in c.clips:
        t = clip_times(clip)
        out = dict(zip(("translation", "rotation", "scale"), sample_clip(c.skeleton, clip, t)))
        for track in clip.tracks:
            np.testing.assert_allclose(out[track.path][:, track.joint], sample_track(track, t), rtol=1e-13,
                                       atol=1e-15)


def test_clip_times():
    clip = Clip("walk", (Track(0, "translation", [0.0, 17 / 24], np.zeros((2, 3))),))
    t = clip_times(clip)
    np.testing.assert_allclose(t[:-1], np.arange(22) / 30, atol=1e-15)
    assert t[-1] == 17 / 24 and len(t) == 23
    whole = Clip("one", (Track(0, "translation", [0.5, 1.5], np.zeros((2, 3))),))
    t = clip_times(whole, fps=10)
    assert len(t) == 11 and t[0] == 0.5 and t[-1] == 1.5
    np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-12)
    assert len(clip_times(Clip("empty", ()))) == 1


def test_resample_clip_is_linear_everywhere_and_matches():
    sk = _skeleton()
    rng = np.random.default_rng(0)
    kt = np.array([0.0, 0.4, 0.45, 1.1])
    q = Rotation.random(4, random_state=rng).as_quat()
    clip = Clip("c", (Track(1, "rotation", kt, q, "LINEAR"),
                      Track(0, "translation", kt, rng.normal(size=(4, 3)), "STEP"),
                      Track(2, "scale", kt[:2], np.stack([rng.normal(size=(2, 3))] * 3, axis=1), "CUBICSPLINE")))
    res = resample_clip(sk, clip, fps=30)
    assert len(res.tracks) == 9 and res.name == "c"
    assert {tr.interpolation for tr in res.tracks} == {"LINEAR"}
    t = clip_times(clip)
    a = sample_clip(sk, clip, t)
    b = sample_clip(sk, res, t)
    np.testing.assert_allclose(b[0], a[0], atol=1e-12)
    np.testing.assert_allclose(b[2], a[2], atol=1e-12)
    _same_rotation(b[1].reshape(-1, 4), a[1].reshape(-1, 4))
    r = res.tracks[4].values  # joint 1 rotation: continuous signs
    assert np.all(np.sum(r[1:] * r[:-1], axis=1) >= 0)


# ---------------------------------------------------------------------------------------------
# real clips: sampling at the key times gives the key values back


@pytest.mark.parametrize("name", ["Fox", "CesiumMan", "Horse", "SimpleSkin"])
def test_real_clips_reproduce_key_values(name):
    ch = read_gltf(asset(name))
    assert ch.clips
    for clip in ch.clips:
        for tr in clip.tracks:
            out = sample_track(tr, tr.times)
            keys = tr.values[:, 1] if tr.interpolation == "CUBICSPLINE" else tr.values
            if tr.path == "rotation":
                keys = keys / np.linalg.norm(keys, axis=1, keepdims=True)
                np.testing.assert_allclose(out, keys, atol=1e-12)
            else:
                np.testing.assert_array_equal(out, keys) if tr.interpolation == "STEP" else \
                    np.testing.assert_allclose(out, keys, rtol=1e-12, atol=1e-12)
        T, R, S = sample_clip(ch.skeleton, clip, clip_times(clip))
        assert np.isfinite(T).all() and np.isfinite(R).all() and np.isfinite(S).all()
        np.testing.assert_allclose(np.linalg.norm(R, axis=-1), 1.0, atol=1e-12)


@pytest.mark.parametrize("fps", [24.0, 30.0, 60.0])
def test_clip_times_stay_strictly_increasing_in_float32(fps):
    """glTF stores key times as float32: an end a few float32 steps past the last frame
    (``..., 1.2, 1.2000000476837158``) must not become a repeated key once written."""
    q = np.array([[0.0, 0.0, 0.0, 1.0]] * 2)
    for frames in (1, 7, 36, 113):
        grid_end = frames / fps
        step = float(np.spacing(np.float32(grid_end)))
        for gap in (0.0, 0.3 * step, step, 2 * step, 1e-3 / fps, 0.5 / fps):
            end = grid_end + gap
            clip = Clip("c", (Track(0, "rotation", np.array([0.0, end]), q),))
            t = clip_times(clip, fps)
            t32 = t.astype(np.float32)
            assert np.all(np.diff(t32) > 0), (fps, frames, gap, t[-3:])
            assert t[0] == 0.0 and t[-1] == end  # the final pose is always sampled
            assert np.all(np.diff(t) <= 1.0 / fps + 16 * step)  # a snapped end moves a few float32 steps


def test_clip_times_refuse_a_clip_too_long_to_sample():
    """Key times of 1e30 s (a hostile file) gave "Maximum allowed size exceeded" (exit 1)."""
    from rigmix.animation.sampling import MAX_CLIP_FRAMES
    from rigmix.errors import InputError

    q = np.array([[0.0, 0.0, 0.0, 1.0]] * 2)
    for end in (1e30, np.inf, (MAX_CLIP_FRAMES + 1) / 30.0):
        with pytest.raises(InputError, match="clip 'long'.*trim its key times"):
            clip_times(Clip("long", (Track(0, "rotation", np.array([0.0, end]), q),)), 30.0)
    assert len(clip_times(Clip("ok", (Track(0, "rotation", np.array([0.0, 60.0]), q),)), 30.0)) == 1801
