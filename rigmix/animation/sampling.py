"""Clip sampling and resampling (the numpy foundation of section 5, animation completion).

Sampling follows the glTF 2.0 specification, appendix C (animation interpolation):

* ``LINEAR``: linear interpolation; rotations use spherical linear interpolation along the
  shorter arc.
* ``STEP``: the value of the last key at or before the time.
* ``CUBICSPLINE``: cubic Hermite spline with the stored in/out tangents scaled by the key
  interval; rotation results are normalized.

Times before the first key or after the last are clamped to the first/last key value.
Everything is vectorized over frames with :func:`numpy.searchsorted`.
"""

from __future__ import annotations

import logging

import numpy as np

from ..character import Clip, Track
from ..errors import InputError
from ..transforms import quat_normalize, quat_slerp

__all__ = ["sample_track", "sample_clip", "clip_times", "check_clips", "resample_clip", "MAX_CLIP_FRAMES"]

#: Most frames a clip is sampled at (about 9 hours at 30 fps): key times beyond that are a
#: broken file, and sampling them would allocate without bound.
MAX_CLIP_FRAMES = 1_000_000

logger = logging.getLogger(__name__)


def _key_index(times, t):
    """Segment index ``i`` with ``times[i] <= t < times[i+1]`` and the fraction ``u`` in it.

    Returns ``i`` in ``[0, k-2]`` and ``u`` in ``[0, 1]`` (clamped outside the key range).
    """
    k = len(times)
    i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, k - 2)
    t0 = times[i]
    dt = times[i + 1] - t0
    u = np.clip((t - t0) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
    return i, u, dt


def sample_track(track: Track, times) -> np.ndarray:
    """Values of one animation track at the given times.

    Parameters
    ----------
    track : rigmix.character.Track
        ``k`` keys; values ``(k, C)``, or ``(k, 3, C)`` (in-tangent, value, out-tangent) for
        ``CUBICSPLINE``.
    times : (F,) float array
        Query times in seconds, any order.

    Returns
    -------
    (F, C) float64 array
        Sampled values; unit quaternions (xyzw) for rotation tracks.
    """
    _check_keys(track)
    vals = np.asarray(track.values, dtype=np.float64)
    k = len(track.times)
    vals = vals.reshape(k, 3, 1, -1) if track.interpolation == "CUBICSPLINE" else vals.reshape(k, 1, -1)
    return _sample_keys(track.times, vals, track.interpolation, track.path == "rotation", times)[:, 0]


def _check_keys(track: Track) -> None:
    if not len(track.times):
        raise ValueError(f"animation: track of joint {track.joint} ({track.path}) has no keys")


def _sample_keys(kt, vals, interpolation, rotation, times):
    """Values at ``times`` ``(F,)`` of ``T`` tracks that share their key times ``kt`` ``(k,)``
    and interpolation: ``vals`` ``(k, T, C)``, or ``(k, 3, T, C)`` for ``CUBICSPLINE``; returns
    ``(F, T, C)`` (each track's values are those :func:`sample_track` gives it alone)."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    cubic = interpolation == "CUBICSPLINE"
    points = vals[:, 1] if cubic else vals
    k = len(kt)
    if k == 1:
        out = np.broadcast_to(points[0], (len(t),) + points.shape[1:]).copy()
        return quat_normalize(out) if rotation else out

    if interpolation == "STEP":
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, k - 1)
        out = points[i]
        return quat_normalize(out) if rotation else out

    i, u, dt = _key_index(kt, t)
    if interpolation == "LINEAR":
        a, b = points[i], points[i + 1]
        if rotation:
            # slerp flips b into a's hemisphere; at and after a segment's end key return that
            # key as stored, as interior keys are (they start the next segment)
            return np.where((u >= 1.0)[:, None, None], quat_normalize(b), quat_slerp(a, b, u[:, None]))
        return a + u[:, None, None] * (b - a)

    # CUBICSPLINE (glTF 2.0 appendix C): tangents are scaled by the key interval
    u2, u3 = u * u, u * u * u
    h00 = (2 * u3 - 3 * u2 + 1)[:, None, None]
    h10 = (u3 - 2 * u2 + u)[:, None, None]
    h01 = (-2 * u3 + 3 * u2)[:, None, None]
    h11 = (u3 - u2)[:, None, None]
    p0, p1 = points[i], points[i + 1]
    m0 = vals[i, 2] * dt[:, None, None]  # out-tangent of key i
    m1 = vals[i + 1, 0] * dt[:, None, None]  # in-tangent of key i+1
    out = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
    # clamping: outside the key range the spline is held at the end values
    out = np.where((t < kt[0])[:, None, None], points[0], out)
    out = np.where((t > kt[-1])[:, None, None], points[-1], out)
    return quat_normalize(out) if rotation else out


def sample_clip(skeleton, clip: Clip, times):
    """Local joint poses of a clip at the given times.

    Tracks with the same key times, interpolation and path (a glTF clip's channels usually
    share one time accessor) are sampled together.

    Parameters
    ----------
    skeleton : rigmix.character.Skeleton
        J joints; joints and paths without a track keep their rest value.
    clip : rigmix.character.Clip
    times : (F,) float array
        Seconds.

    Returns
    -------
    T : (F, J, 3) float64
        Local translations.
    R : (F, J, 4) float64
        Local rotations, unit quaternions xyzw.
    S : (F, J, 3) float64
        Local scales.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    F, J = len(t), skeleton.num_joints
    out = {
        "translation": np.broadcast_to(skeleton.translations, (F, J, 3)).copy(),
        "rotation": np.broadcast_to(quat_normalize(skeleton.rotations), (F, J, 4)).copy(),
        "scale": np.broadcast_to(skeleton.scales, (F, J, 3)).copy(),
    }
    groups: dict = {}
    for track in clip.tracks:
        if not 0 <= track.joint < J:
            raise ValueError(
                f"animation: clip {clip.name!r} has a track on joint {track.joint}, "
                f"but the skeleton has {J} joints"
            )
        _check_keys(track)
        key = (track.path, track.interpolation, track.times.tobytes(), np.shape(track.values)[1:])
        groups.setdefault(key, []).append(track)
    targets = [(tr.joint, tr.path) for tr in clip.tracks]
    if len(set(targets)) < len(targets):  # a joint's property keyed twice: the last track wins
        for track in clip.tracks:
            out[track.path][:, track.joint] = sample_track(track, t)
        return out["translation"], out["rotation"], out["scale"]
    for (path, interpolation, _, _), tracks in groups.items():
        axis = 2 if interpolation == "CUBICSPLINE" else 1
        k = len(tracks[0].times)
        vals = np.stack([np.asarray(tr.values, np.float64).reshape((k, 3, -1) if axis == 2 else (k, -1))
                         for tr in tracks], axis=axis)
        joints = [tr.joint for tr in tracks]
        out[path][:, joints] = _sample_keys(tracks[0].times, vals, interpolation, path == "rotation", t)
    return out["translation"], out["rotation"], out["scale"]


def clip_times(clip: Clip, fps: float = 30.0) -> np.ndarray:
    """Sample times every ``1/fps`` seconds from ``clip.start`` to ``clip.end``, end included.

    When the duration is not a whole number of frames, the end time is appended, so the last
    interval is shorter than ``1/fps`` (the clip's final pose is always sampled). An end closer
    to the last frame than float32 can tell apart (glTF stores key times as float32) replaces
    that frame instead, so the times stay strictly increasing once written.

    Returns
    -------
    (F,) float64, strictly increasing, also after a cast to float32, ``F >= 1``.
    """
    if fps <= 0:
        raise ValueError(f"animation: fps must be positive, got {fps}")
    start, end = clip.start, clip.end
    n = _whole_frames(clip, fps, where="animation")
    t = start + np.arange(n + 1) / fps
    # a few float32 steps: two times this close may cast to one float32 key
    distinct = max(1e-6 / fps, 8.0 * float(np.spacing(np.float32(max(abs(end), abs(t[-1]))))))
    if end - t[-1] > distinct:
        t = np.append(t, end)
    elif n:
        t[-1] = end  # on the grid up to rounding: sample the end key exactly
    return t


def _whole_frames(clip: Clip, fps: float, *, where: str) -> int:
    """Whole ``1/fps`` steps from the clip's start to its end (the rule :func:`clip_times` and
    :func:`check_clips` share).

    Raises
    ------
    InputError
        ``"{where}: clip 'NAME': ..."`` when that is more than :data:`MAX_CLIP_FRAMES` (or not
        finite).
    """
    start, end = clip.start, clip.end
    frames = (end - start) * fps
    if not np.isfinite(frames) or frames > MAX_CLIP_FRAMES:
        raise InputError(f"{where}: clip {clip.name!r}: runs from {start:g} to {end:g} s, more than "
                         f"{MAX_CLIP_FRAMES} frames at {fps:g} fps: trim its key times")
    return int(np.floor(frames + 1e-6))


def check_clips(character, fps: float) -> None:
    """Refuse a character with a clip too long to sample at ``fps`` (:data:`MAX_CLIP_FRAMES`
    frames), naming its file and the clip.

    Compose applies it to every input file at the config's ``[animation] fps`` before any stage
    runs, and ``rigmix inspect`` at the default fps, so no clip of a file is refused later
    without its file.

    Parameters
    ----------
    character : rigmix.character.Character
    fps : float
        Frames per second, positive.

    Raises
    ------
    InputError
        ``"<file>: clip 'NAME': runs from ... s, more than ... frames at ... fps: trim its key
        times"``.
    """
    for clip in character.clips:
        _whole_frames(clip, fps, where=character.label)


def _hemisphere_continuous(q):
    """Flip quaternions ``(F, J, 4)`` so consecutive frames have non-negative dot products."""
    q = q.copy()
    if len(q) < 2:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=-1)  # (F-1, J)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    q[1:] *= flips[..., None]
    return q


def resample_clip(skeleton, clip: Clip, fps: float = 30.0) -> Clip:
    """The clip resampled as ``LINEAR`` tracks on every joint at a fixed rate.

    Every joint gets a translation, rotation and scale track with keys at
    :func:`clip_times` (``1/fps`` apart, end included); rotations are made continuous (no
    sign flips between consecutive keys).

    Parameters
    ----------
    skeleton : rigmix.character.Skeleton
    clip : rigmix.character.Clip
    fps : float
        Frames per second.

    Returns
    -------
    rigmix.character.Clip
        Same name, ``3 * J`` tracks, joint order.
    """
    t = clip_times(clip, fps)
    T, R, S = sample_clip(skeleton, clip, t)
    R = _hemisphere_continuous(R)
    tracks = []
    for j in range(skeleton.num_joints):
        tracks.append(Track(j, "translation", t, T[:, j], "LINEAR"))
        tracks.append(Track(j, "rotation", t, R[:, j], "LINEAR"))
        tracks.append(Track(j, "scale", t, S[:, j], "LINEAR"))
    return Clip(clip.name, tuple(tracks))
