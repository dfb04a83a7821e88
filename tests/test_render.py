"""Offscreen rendering (``rigmix render``): camera, posing, both rasterizers, GIF/MP4/sheet."""

from __future__ import annotations

import importlib.util
import os
from dataclasses import replace

import numpy as np
import pytest
from conftest import asset
from PIL import Image
from test_usd import decorated_chain

from rigmix.animation import clip_times, sample_clip
from rigmix.errors import RigmixError
from rigmix.io.gltf import read_gltf
from rigmix.preview.render import BACKGROUND, camera_matrices, contact_sheet, pose_scene, render_clip, render_frames
from rigmix.skinning import rest_pose
from rigmix.transforms import trs_to_matrix

SIZE = 96


def egl_available():
    try:
        import moderngl

        moderngl.create_standalone_context(backend="egl").release()
        return True
    except Exception:
        return False


# Without an EGL context (Mesa, installed by `make env`) the OpenGL cases skip, except under
# CI=true, where they run and fail.
needs_gl = pytest.mark.skipif(not egl_available() and os.environ.get("CI", "").lower() != "true",
                              reason="no OpenGL EGL context (Mesa) on this machine")


def foreground(img):
    """(h, w) bool: pixels that are not the background colour."""
    return np.abs(img.astype(int) - np.array(BACKGROUND)).sum(axis=-1) > 12


@pytest.fixture(scope="module")
def fox():
    return read_gltf(asset("Fox"))


@pytest.fixture(scope="module")
def fox_walk(fox):
    """The Fox's Walk at 12 fps (9 frames), posed once."""
    return pose_scene(fox, "Walk", fps=12.0)


def test_camera_centres_the_box_and_keeps_it_in_view():
    rng = np.random.default_rng(3)
    for _ in range(5):
        lo = rng.normal(size=3) * 10
        hi = lo + rng.random(3) * 50 + 0.1
        w, h = rng.integers(40, 400, size=2)
        view, proj = camera_matrices(lo, hi, width=w, height=h, azimuth=rng.uniform(-180, 180),
                                     elevation=rng.uniform(-60, 60))
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        pts = np.vstack([corners, np.append((lo + hi) / 2, 1)])
        clip = pts @ (proj @ view).T
        ndc = clip[:, :3] / clip[:, 3:]
        np.testing.assert_allclose(ndc[-1, :2], 0, atol=1e-9)  # centre of the box -> image centre
        assert np.all(clip[:, 3] > 0)  # in front of the camera
        assert np.all(np.abs(ndc) < 1)  # inside the image and the depth range
        np.testing.assert_allclose(np.linalg.det(view[:3, :3]), 1)  # a rigid view


def test_pose_scene_follows_skinning_and_props():
    ch = decorated_chain()
    rest = pose_scene(ch)
    np.testing.assert_allclose(rest.positions[0][0], rest_pose(ch)[0], atol=1e-12)
    clip = ch.clips[0]
    scene = pose_scene(ch, clip.name, fps=10)
    times = clip_times(clip, 10)
    np.testing.assert_array_equal(scene.times, times)
    T, R, S = sample_clip(ch.skeleton, clip, times)
    world = ch.skeleton.world_matrices(trs_to_matrix(T, R, S))[:, 2] @ ch.props[0].matrix
    sword = np.einsum("fij,nj->fni", world[:, :3, :3], ch.props[0].mesh.positions) + world[:, None, :3, 3]
    np.testing.assert_allclose(scene.positions[1], sword, atol=1e-12)
    np.testing.assert_allclose(scene.positions[2][3], 2 * ch.props[1].mesh.positions, atol=1e-12)  # static
    assert scene.textures[0] == ch.materials[0].base_color_texture.data and scene.textures[1] is None
    with pytest.raises(RigmixError, match="no clip 'fly'"):
        pose_scene(ch, "fly")


@pytest.mark.parametrize("backend", [pytest.param("gl", marks=needs_gl), "pil"])
def test_frames_show_the_moving_character(fox_walk, backend):
    calls = []
    frames = render_frames(fox_walk, width=SIZE, height=SIZE + 16, backend=backend,
                           progress=lambda done, total: calls.append((done, total)))
    F = len(fox_walk.times)
    assert frames.shape == (F, SIZE + 16, SIZE, 3) and frames.dtype == np.uint8
    assert calls == [(f + 1, F) for f in range(F)]
    for img in frames:  # not blank, not all character, never touching the border (framed)
        covered = foreground(img).mean()
        assert 0.03 < covered < 0.8
        assert not foreground(img)[[0, -1]].any() and not foreground(img)[:, [0, -1]].any()
    # the legs move: consecutive frames differ, by more than antialiasing noise; and the same pose
    # gives the same image (a looping walk: the last frame is the first again)
    diffs = [np.abs(frames[f].astype(int) - frames[f - 1]).mean() for f in range(1, F)]
    assert min(diffs) > 0.2 and max(diffs) > 1.0
    assert np.abs(frames[-1].astype(int) - frames[0]).max() <= 1


@needs_gl
def test_backends_agree_on_the_silhouette(fox_walk):
    gl = render_frames(fox_walk, width=SIZE, height=SIZE, backend="gl")
    pil = render_frames(fox_walk, width=SIZE, height=SIZE, backend="pil")
    for a, b in zip(foreground(gl), foreground(pil)):
        iou = (a & b).sum() / (a | b).sum()
        assert iou > 0.85, iou


@needs_gl
def test_gl_samples_the_texture():
    """CesiumMan's texture has saturated blue and green stripes; its base colour factor is white."""
    ch = read_gltf(asset("CesiumMan"))
    scene = pose_scene(ch, ch.clips[0], times=[0.5])
    (gl,) = render_frames(scene, width=128, height=128, backend="gl")
    (pil,) = render_frames(scene, width=128, height=128, backend="pil")

    def blue(img):
        img = img.astype(int)
        return ((img[..., 2] - img[..., 0] > 60) & foreground(img)).mean()

    assert blue(gl) > 0.003 and blue(pil) == 0  # the fallback draws the texture's mean colour


def test_skeleton_overlay(fox_walk):
    """Bones drawn over the frames: the overlay colour appears only with bones=True, at the joints."""
    from rigmix.preview.render import BONE_COLOR, JOINT_COLOR, project_points

    scene = replace(fox_walk, times=fox_walk.times[:2], positions=[p[:2] for p in fox_walk.positions],
                    joints=fox_walk.joints[:2])
    plain = render_frames(scene, width=SIZE, height=SIZE, backend="pil")
    boned = render_frames(scene, width=SIZE, height=SIZE, backend="pil", bones=True)

    def has(img, color):
        return (np.abs(img.astype(int) - np.array(color)).sum(axis=-1) < 30)

    assert not has(plain, BONE_COLOR).any() and has(boned, BONE_COLOR).sum() > 20
    assert scene.joints.shape == (2, 24, 3) and list(scene.parents[:2]) == [-1, 0]
    view, proj = camera_matrices(*scene.bounds(), width=SIZE, height=SIZE)
    xy = np.floor(project_points(scene.joints[0], view, proj, SIZE, SIZE)).astype(int)  # (J, 2)
    inside = (xy >= 0).all(axis=1) & (xy < SIZE).all(axis=1)
    assert inside.all()
    hits = has(boned[0], JOINT_COLOR)[xy[:, 1], xy[:, 0]]
    assert hits.mean() > 0.9  # a dot on (nearly) every joint, drawn last


def test_gif_mp4_and_sheet(tmp_path, fox):
    clip = fox.clip("Run")
    F = len(clip_times(clip, 15))
    frames = render_clip(fox, "Run", gif=tmp_path / "run.gif", sheet=tmp_path / "run.png", fps=15,
                         width=64, height=48, backend="pil", sheet_frames=6)
    assert len(frames) == F
    gif = Image.open(tmp_path / "run.gif")
    assert gif.n_frames == F and gif.size == (64, 48) and gif.info["loop"] == 0
    assert gif.info["duration"] == 70  # 1/15 s rounded to GIF's 10 ms
    sheet = Image.open(tmp_path / "run.png")
    assert sheet.size == (4 * 64, 2 * 48)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.gif", "run.png"]  # no temporaries
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        import imageio.v2 as imageio

        render_clip(fox, "Run", mp4=tmp_path / "run.mp4", fps=15, width=63, height=47, backend="pil")
        reader = imageio.get_reader(tmp_path / "run.mp4")
        assert reader.count_frames() == F and reader.get_meta_data()["size"] == (64, 48)  # padded even
    with pytest.raises(RigmixError, match="nothing to write"):
        render_clip(fox, "Run")


def test_contact_sheet_picks_first_and_last():
    frames = np.stack([np.full((4, 5, 3), 10 * i, dtype=np.uint8) for i in range(10)])
    sheet = contact_sheet(frames, count=4, columns=2)
    assert sheet.shape == (8, 10, 3)
    assert sheet[0, 0, 0] == 0 and sheet[-1, -1, 0] == 90  # frames 0 ... 9


def test_cli_render(tmp_path, capsys):
    from rigmix.cli import main

    gif, sheet = tmp_path / "walk.gif", tmp_path / "walk.png"
    args = ["render", str(asset("Fox")), "--clip", "Walk", "--gif", str(gif), "--sheet", str(sheet),
            "--size", "64", "48", "--fps", "12", "--backend", "pil"]
    assert main(args) == 0
    F = len(clip_times(read_gltf(asset("Fox")).clip("Walk"), 12))
    assert Image.open(gif).n_frames == F and Image.open(gif).size == (64, 48)
    assert Image.open(sheet).size == (4 * 64, 3 * 48)  # 12 tiles asked, F = 10 available: 4 x 3 grid
    assert f"{F} frames" in capsys.readouterr().out
    assert main(["render", str(asset("Fox")), "--clip", "Fly", "--gif", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("rigmix: error: render:") and "'Walk'" in err[-1]
    assert main(["render", str(asset("Fox"))]) == 2
    assert "nothing to write" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.gif", "walk.png"]
