"""Choosing the source frames and joining them (SkinMixer section 8, the assembly).

* :func:`choose_frames`: one candidate frame per output frame, the best per frame (the paper)
  or a Viterbi path that pays for every jump;
* :func:`blend_seams`, :func:`smooth_seams`: where the chosen frames jump, fade the jump out
  and smooth lightly around it, leaving continuous playback untouched;
* :func:`angular_acceleration`: the smoothness figure of completed clips.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..transforms import quat_angle, quat_conjugate, quat_multiply, quat_normalize, quat_slerp

__all__ = [
    "segments_next",
    "choose_frames",
    "discontinuities",
    "blend_seams",
    "smooth_seams",
    "angular_acceleration",
]

_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def segments_next(segment):
    """``succ[b]``: the next frame of the same clip, -1 at a clip's last frame."""
    segment = np.asarray(segment)
    succ = np.arange(1, len(segment) + 1)
    last = np.ones(len(segment), dtype=bool)
    last[:-1] = segment[1:] != segment[:-1]
    succ[last] = -1
    return succ


def choose_frames(score, segment_b, *, jump_penalty=0.0, fixed=None) -> np.ndarray:
    """Candidate frame per query frame, maximizing the total score (Viterbi over frames).

    Continuing from candidate ``b`` to ``b + 1`` of the same clip is free; any other step
    costs ``jump_penalty``. With ``jump_penalty=0`` this is the best frame per row.

    Parameters
    ----------
    score : (Fa, Fb) float array
    segment_b : (Fb,) int array
        Candidate clip of each column.
    jump_penalty : float
    fixed : mapping of int to int, optional
        Query frame -> pinned candidate frame.

    Returns
    -------
    (Fa,) int64 column per row.
    """
    score = np.asarray(score)
    Fa, Fb = score.shape
    if fixed:
        score = score.copy()
    for a, b in (fixed or {}).items():
        if not (0 <= a < Fa and 0 <= b < Fb):
            raise InputError(f"completion: fixed frame {a} -> {b} outside ({Fa}, {Fb})")
        row = np.full(Fb, -np.inf)
        row[b] = score[a, b]
        score[a] = row
    if jump_penalty <= 0:
        return np.argmax(score, axis=1).astype(np.int64)
    succ = segments_next(segment_b)
    pred = np.full(Fb, Fb, dtype=np.int64)  # index Fb reads the -inf padding: no predecessor
    has = succ >= 0
    pred[succ[has]] = np.flatnonzero(has)
    stayed = np.empty((Fa, Fb), dtype=bool)  # back-pointers: pred[b] if stayed, else best[a]
    best = np.zeros(Fa, dtype=np.int64)
    Vp = np.empty(Fb + 1)
    Vp[Fb] = -np.inf
    Vp[:Fb] = score[0]
    stay = np.empty(Fb)
    for a in range(1, Fa):  # a loop over query frames; each step is vectorized over Fb
        best[a] = np.argmax(Vp[:Fb])
        jump = Vp[best[a]] - jump_penalty
        np.take(Vp, pred, out=stay)
        np.greater_equal(stay, jump, out=stayed[a])
        np.maximum(stay, jump, out=stay)
        np.add(score[a], stay, out=Vp[:Fb])
    path = np.empty(Fa, dtype=np.int64)
    path[-1] = int(np.argmax(Vp[:Fb]))
    for a in range(Fa - 1, 0, -1):
        b = path[a]
        path[a - 1] = pred[b] if stayed[a, b] else best[a]
    return path


def blend_seams(R, T, seams, frames) -> tuple[np.ndarray, np.ndarray]:
    """Remove the jumps at seams with offsets that fade out (inertial blending).

    At a seam ``t -> t + 1`` the pose the old frames were heading to (constant-velocity
    extrapolation of frames ``t - 1, t``) replaces frame ``t + 1``; the offset between the two
    fades to zero over ``frames`` frames with a smoothstep (zero slope at both ends), so the
    new frames take over without a jump. Seams are processed in order, each from the frames
    already corrected.

    Parameters
    ----------
    R : (F, J, 4) float array
        Local rotations, xyzw.
    T : (F, J, 3) float array
        Local translations.
    seams : (s,) int array
        Frames ``t`` such that ``t -> t + 1`` jumps.
    frames : int
        Length of the fade (0: none).

    Returns
    -------
    R : (F, J, 4) float64, T : (F, J, 3) float64
    """
    R = quat_normalize(R).copy()
    T = np.asarray(T, dtype=np.float64).copy()
    F = len(R)
    if frames <= 0:
        return R, T
    for t in np.unique(np.asarray(seams, dtype=np.int64)):
        if not 0 <= t < F - 1:
            continue
        if t >= 1:
            vel = quat_multiply(quat_conjugate(R[t - 1]), R[t])
            r_ext = quat_multiply(R[t], vel)
            t_ext = 2 * T[t] - T[t - 1]
        else:
            r_ext, t_ext = R[t], T[t]
        off_r = quat_multiply(r_ext, quat_conjugate(R[t + 1]))  # (J, 4), left offset
        off_r = np.where(off_r[..., 3:4] < 0, -off_r, off_r)
        off_t = t_ext - T[t + 1]
        n = min(int(frames), F - 1 - t)
        x = np.arange(n) / float(frames)
        fade = 1.0 - (3 * x**2 - 2 * x**3)  # 1 at the seam, 0 after `frames`
        span = slice(t + 1, t + 1 + n)
        off = quat_slerp(np.broadcast_to(_IDENTITY, (n,) + off_r.shape),
                         np.broadcast_to(off_r, (n,) + off_r.shape), fade[:, None])
        R[span] = quat_multiply(off, R[span])
        T[span] += fade[:, None, None] * off_t
    return R, T


def smooth_seams(R, T, seams, sigma) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing of rotation and translation tracks near seams only.

    Each frame is blended toward its Gaussian-smoothed value with weight
    ``exp(-d^2 / (2 (2 sigma)^2))``, ``d`` its distance to the nearest seam: far from seams
    the tracks are unchanged.

    Parameters
    ----------
    R : (F, J, 4) float array
        Local rotations, xyzw.
    T : (F, J, 3) float array
        Local translations.
    seams : (s,) int array
        Frames ``t`` such that ``t -> t + 1`` jumps.
    sigma : float
        Standard deviation in frames (0: no smoothing).

    Returns
    -------
    R : (F, J, 4) float64, T : (F, J, 3) float64
    """
    from scipy.ndimage import gaussian_filter1d

    R = quat_normalize(R)
    T = np.asarray(T, dtype=np.float64).copy()
    seams = np.asarray(seams, dtype=np.float64).reshape(-1)
    F = len(R)
    if sigma <= 0 or seams.size == 0 or F < 3:
        return R, T
    dots = np.sum(R[1:] * R[:-1], axis=-1)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    R = R.copy()
    R[1:] *= flips[..., None]  # hemisphere-continuous before averaging
    Rs = quat_normalize(gaussian_filter1d(R, sigma, axis=0, mode="nearest"))
    Ts = gaussian_filter1d(T, sigma, axis=0, mode="nearest")
    d = np.min(np.abs(np.arange(F)[:, None] - (seams[None, :] + 0.5)), axis=1) - 0.5
    alpha = np.exp(-0.5 * (d / (2.0 * sigma)) ** 2)[:, None, None]
    R = quat_normalize((1 - alpha) * R + alpha * Rs)
    T = (1 - alpha) * T + alpha * Ts
    return R, T


def angular_acceleration(R, fps=30.0) -> np.ndarray:
    """Magnitude of the angular acceleration of local rotation tracks.

    Angular velocity between consecutive frames is the rotation vector of
    ``q_t^-1 q_{t+1}`` times ``fps``; acceleration is its finite difference times ``fps``.

    Parameters
    ----------
    R : (F, J, 4) float array
        Rotations at a fixed rate, xyzw.
    fps : float

    Returns
    -------
    (F - 2, J) float64, radians per second squared.
    """
    R = quat_normalize(R)
    rel = quat_multiply(quat_conjugate(R[:-1]), R[1:])  # (F-1, J, 4)
    rel = np.where(rel[..., 3:4] < 0, -rel, rel)
    s = np.linalg.norm(rel[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, rel[..., 3:4])
    omega = np.where(s > 1e-12, rel[..., :3] / np.where(s > 1e-12, s, 1.0) * angle, 2 * rel[..., :3])
    omega = omega * fps
    return np.linalg.norm(np.diff(omega, axis=0), axis=-1) * fps


def discontinuities(R, jumps, *, ratio=2.0, floor=1e-3):
    """The jumps that are real discontinuities of the rotation tracks ``R (F, J, 4)``.

    A jump ``t -> t + 1`` between non-consecutive source frames (e.g. the end of a looping
    clip back to its start) is a seam only if its largest joint rotation step exceeds
    ``floor`` radians and ``ratio`` times the steps just before and after it.
    """
    if len(jumps) == 0 or len(R) < 2:
        return np.asarray(jumps, dtype=np.int64)
    step = np.max(quat_angle(R[:-1], R[1:]), axis=1)  # (F - 1,)
    before = np.where(jumps > 0, step[np.maximum(jumps - 1, 0)], 0.0)
    after = np.where(jumps + 1 < len(step), step[np.minimum(jumps + 1, len(step) - 1)], 0.0)
    real = step[jumps] > np.maximum(floor, ratio * np.maximum(before, after))
    return np.asarray(jumps, dtype=np.int64)[real]
