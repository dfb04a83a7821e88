"""Offscreen rendering of a character's clip on the CPU: frames, GIF, MP4, contact sheet.

The pose of every frame comes from rigmix itself (:func:`rigmix.animation.sample_clip` and
:func:`rigmix.skinning.skin_character`, linear blend skinning in numpy); props follow their
joint's world matrix. Two rasterizers draw the posed triangles:

* ``"gl"``: OpenGL through moderngl on a headless EGL context (Mesa's llvmpipe renders on the
  CPU, no display and no GPU needed): depth buffer, 4x multisampling, smooth shading from
  normals recomputed on the posed mesh, base colour textures, vertex colours.
* ``"pil"``: a pure numpy + Pillow fallback (painter's algorithm: faces sorted back to front and
  filled as polygons at 2x resolution, then downsampled), flat shading, base colour factors and
  vertex colours (textures are averaged to one colour). Used when EGL is unavailable.

Both use the same camera (:func:`camera_matrices`): a perspective view looking at the centre of
the bounding box of the posed character over the *whole* clip (so it never leaves the frame and
its motion is visible), from ``azimuth`` degrees around +Y (0 = looking along -Z, i.e. from the
front of a glTF asset) and ``elevation`` degrees above the horizon. Lighting is a headlight
(ambient 0.35 + diffuse 0.65, two-sided: game assets often have inconsistent winding).
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dfd.mesh import vertex_normals

from ..animation.sampling import clip_times, sample_clip
from ..errors import InputError, UnsupportedError
from ..safety import atomic_output
from ..skinning import skin_character
from ..transforms import trs_to_matrix

__all__ = [
    "PosedScene",
    "pose_scene",
    "camera_matrices",
    "project_points",
    "render_frames",
    "contact_sheet",
    "write_gif",
    "write_mp4",
    "write_png",
    "render_clip",
]

logger = logging.getLogger(__name__)

BACKGROUND = (235, 238, 242)
_AMBIENT, _DIFFUSE = 0.35, 0.65


@dataclass(frozen=True)
class PosedScene:
    """The triangles of a character at every frame, in world space.

    Attributes
    ----------
    positions : list of (F, n_i, 3) float64
        Posed vertices of each drawn mesh (skinned meshes, then props).
    faces : list of (m_i, 3) int64
    uvs : list of ((n_i, 2) float64 or None)
        glTF uvs (v down) of the texture set used by the mesh's material.
    colors : list of (n_i, 4) float64
        Linear RGBA per vertex: the material's base colour factor times ``COLOR_0``.
    textures : list of (bytes or None)
        Encoded base colour image of each mesh's material.
    times : (F,) float64
        Seconds.
    joints : (F, J, 3) float64
        Posed joint positions (world), for the skeleton overlay.
    parents : (J,) int64
        Parent joint indices, ``-1`` for roots.
    """

    positions: list
    faces: list
    uvs: list
    colors: list
    textures: list
    times: np.ndarray
    joints: np.ndarray = field(default_factory=lambda: np.zeros((1, 0, 3)))
    parents: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def bounds(self):
        """``(lo, hi)``: the (3,) corners of the box around every vertex at every frame."""
        pts = np.concatenate([P.reshape(-1, 3) for P in self.positions])
        return pts.min(axis=0), pts.max(axis=0)


def pose_scene(character, clip=None, times=None, *, fps=30.0):
    """Pose a character at ``times`` of ``clip`` (the rest pose when ``clip`` is None).

    Parameters
    ----------
    character : rigmix.character.Character
    clip : Clip, str or None
        The clip (or its name).
    times : (F,) float array, optional
        Seconds; default: the clip's frames at ``fps`` (:func:`rigmix.animation.clip_times`),
        or ``[0]`` for the rest pose.
    fps : float

    Returns
    -------
    PosedScene
    """
    sk = character.skeleton
    where = character.label  # the file's name, never its folders
    if isinstance(clip, str):
        try:
            clip = character.clip(clip)
        except KeyError:
            names = [c.name for c in character.clips]
            raise InputError(f"render: {where} has no clip {clip!r}; clips: {names}") from None
    if times is None:
        times = clip_times(clip, fps) if clip is not None else np.zeros(1)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    F = len(times)
    if clip is not None:
        T, R, S = sample_clip(sk, clip, times)
    else:
        T, R, S = (np.broadcast_to(a, (F,) + a.shape) for a in (sk.translations, sk.rotations, sk.scales))
    skinned = skin_character(character, T, R, S) if sk.num_joints else [
        np.broadcast_to(m.positions, (F,) + m.positions.shape) for m in character.meshes]
    worlds = sk.world_matrices(trs_to_matrix(T, R, S)) if sk.num_joints else None  # (F, J, 4, 4)

    meshes, positions = list(character.meshes), list(skinned)
    for prop in character.props:
        M = worlds[:, prop.joint] @ prop.matrix if prop.joint >= 0 and worlds is not None else prop.matrix[None]
        M = np.broadcast_to(M, (F, 4, 4))
        positions.append(np.einsum("fij,nj->fni", M[:, :3, :3], prop.mesh.positions) + M[:, None, :3, 3])
        meshes.append(prop.mesh)
    if not meshes:
        raise UnsupportedError(f"render: {where} has no mesh to draw")

    uvs, colors, textures = [], [], []
    for mesh in meshes:
        mat = character.materials[mesh.material] if 0 <= mesh.material < len(character.materials) else None
        base = mat.base_color if mat is not None else np.array([0.8, 0.8, 0.8, 1.0])
        col = np.broadcast_to(base, (len(mesh.positions), 4)).copy()
        if mesh.colors is not None:
            col *= mesh.colors
        tex = mat.base_color_texture if mat is not None else None
        texcoord = mat.base_color_texcoord if mat is not None else 0
        uv = mesh.uvs[texcoord] if tex is not None and texcoord < len(mesh.uvs) else None
        uvs.append(uv)
        textures.append(tex.data if uv is not None else None)
        colors.append(col)
    joints = worlds[..., :3, 3] if worlds is not None else np.zeros((F, 0, 3))
    return PosedScene(positions, [m.faces for m in meshes], uvs, colors, textures, times, joints,
                      np.asarray(sk.parents, dtype=np.int64))


def camera_matrices(lo, hi, *, width, height, azimuth=30.0, elevation=15.0, fov=35.0):
    """View and projection matrices framing the box ``[lo, hi]``.

    Parameters
    ----------
    lo, hi : (3,) float arrays
        World-space box to keep in view (its bounding sphere fits the narrower field of view).
    width, height : int
        Image size in pixels (sets the aspect ratio).
    azimuth, elevation : float
        Degrees: rotation of the eye around +Y from +Z, and height above the horizon.
    fov : float
        Vertical field of view in degrees.

    Returns
    -------
    view : (4, 4) float64
        World -> camera (column vectors; the camera looks along its -Z).
    proj : (4, 4) float64
        Camera -> clip space (OpenGL convention, depth in [-1, 1]).
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    center = (lo + hi) / 2
    radius = max(np.linalg.norm(hi - lo) / 2, 1e-9)
    aspect = width / height
    half_v = np.radians(fov) / 2
    half_h = np.arctan(np.tan(half_v) * aspect)
    dist = radius / np.sin(min(half_v, half_h)) * 1.05
    az, el = np.radians(azimuth), np.radians(elevation)
    direction = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    eye = center + dist * direction
    fwd = (center - eye) / np.linalg.norm(center - eye)
    up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight down or up
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, true_up, -fwd
    view[:3, 3] = -view[:3, :3] @ eye
    near, far = max(dist - radius * 1.5, dist * 1e-3), dist + radius * 1.5
    f = 1 / np.tan(half_v)
    proj = np.zeros((4, 4))
    proj[0, 0], proj[1, 1] = f / aspect, f
    proj[2, 2], proj[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    proj[3, 2] = -1.0
    return view, proj


def _srgb(c):
    return np.clip(c, 0, 1) ** (1 / 2.2)


def render_frames(scene, *, width=480, height=480, azimuth=30.0, elevation=15.0, fov=35.0,
                  backend="auto", bones=False, progress=None):
    """Rasterize every frame of a posed scene.

    Parameters
    ----------
    scene : PosedScene
        From :func:`pose_scene`.
    width, height : int
        Pixels.
    azimuth, elevation, fov : float
        Camera, see :func:`camera_matrices`.
    backend : {"auto", "gl", "pil"}
        ``auto`` tries OpenGL (EGL) and falls back to Pillow with a warning.
    bones : bool
        Draw the skeleton on top: a line from each joint to its parent, a dot on each joint.
    progress : callable, optional
        ``progress(done, total)`` after each frame.

    Returns
    -------
    (F, height, width, 3) uint8
        sRGB images, row 0 at the top.
    """
    if backend not in ("auto", "gl", "pil"):
        raise InputError(f"render: unknown backend {backend!r}; expected auto, gl or pil")
    if width < 8 or height < 8:
        raise InputError(f"render: image size {width}x{height} is too small (at least 8x8)")
    view, proj = camera_matrices(*scene.bounds(), width=width, height=height, azimuth=azimuth,
                                 elevation=elevation, fov=fov)
    if backend in ("auto", "gl"):
        try:
            ctx = _gl_context()
        except Exception as exc:  # moderngl raises plain Exceptions when EGL is missing
            if backend == "gl":
                raise UnsupportedError(f"render: no OpenGL (EGL) context: {exc}; install Mesa's EGL "
                                       "(Debian: libegl1 libgl1-mesa-dri) or use backend='pil'") from exc
            logger.warning("render: no OpenGL (EGL) context (%s); using the slower Pillow rasterizer", exc)
        else:
            try:
                frames = _render_gl(ctx, scene, view, proj, width, height, progress)
            finally:
                ctx.release()
            return _draw_bones(frames, scene, view, proj) if bones else frames
    frames = _render_pil(scene, view, proj, width, height, progress)
    return _draw_bones(frames, scene, view, proj) if bones else frames


def project_points(P, view, proj, width, height):
    """Pixel coordinates of world points through the camera of :func:`camera_matrices`.

    Parameters
    ----------
    P : (..., 3) float array
        Points in world space (metres).
    view, proj : (4, 4) float arrays
        World -> camera and camera -> clip space matrices (column vectors).
    width, height : int
        Image size in pixels.

    Returns
    -------
    (..., 2) float array
        ``x`` right and ``y`` down in pixels, ``(0, 0)`` the top-left corner of the image.
    """
    clip = P @ (proj @ view)[:, :3].T + (proj @ view)[:, 3]
    ndc = clip[..., :2] / clip[..., 3:]
    return np.stack([(ndc[..., 0] + 1) / 2 * width, (1 - ndc[..., 1]) / 2 * height], axis=-1)


#: Skeleton overlay colours: bones and joints.
BONE_COLOR, JOINT_COLOR = (255, 90, 30), (20, 60, 200)


def _draw_bones(frames, scene, view, proj):
    """The frames with the posed skeleton drawn over them (no depth test: always visible)."""
    from PIL import Image, ImageDraw

    F, H, W, _ = frames.shape
    if scene.joints.shape[1] == 0:
        return frames
    xy = project_points(scene.joints, view, proj, W, H)  # (F, J, 2)
    radius = max(1.0, min(W, H) / 160)
    out = np.empty_like(frames)
    for f in range(F):
        img = Image.fromarray(frames[f])
        draw = ImageDraw.Draw(img)
        for j, p in enumerate(scene.parents):
            if p >= 0:
                draw.line([tuple(xy[f, p]), tuple(xy[f, j])], fill=BONE_COLOR, width=max(1, int(radius)))
        for x, y in xy[f]:
            draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=JOINT_COLOR)
        out[f] = np.asarray(img)
    return out


# ---------------------------------------------------------------------------------------------
# OpenGL (moderngl, EGL)

_VERTEX_SHADER = """
#version 330
uniform mat4 view;
uniform mat4 proj;
in vec3 in_pos;
in vec3 in_nrm;
in vec2 in_uv;
in vec4 in_col;
out vec3 v_nrm;
out vec2 v_uv;
out vec4 v_col;
void main() {
    v_nrm = mat3(view) * in_nrm;
    v_uv = in_uv;
    v_col = in_col;
    gl_Position = proj * view * vec4(in_pos, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform sampler2D tex;
uniform bool use_tex;
uniform float ambient;
uniform float diffuse;
in vec3 v_nrm;
in vec2 v_uv;
in vec4 v_col;
out vec4 f_color;
void main() {
    vec3 base = pow(clamp(v_col.rgb, 0.0, 1.0), vec3(1.0 / 2.2));  // linear factor -> sRGB
    if (use_tex) base *= texture(tex, v_uv).rgb;
    float lambert = length(v_nrm) > 0.0 ? abs(normalize(v_nrm).z) : 1.0;  // headlight, two-sided
    f_color = vec4(base * (ambient + diffuse * lambert), 1.0);
}
"""


def _gl_context():
    import moderngl

    return moderngl.create_standalone_context(backend="egl")


def _gl_texture(ctx, data):
    from PIL import Image

    img = Image.open(io.BytesIO(data)).convert("RGBA")
    tex = ctx.texture(img.size, 4, img.tobytes())  # row 0 = top = glTF v 0: uvs used as they are
    tex.build_mipmaps()
    tex.repeat_x = tex.repeat_y = True
    return tex


def _render_gl(ctx, scene, view, proj, width, height, progress):
    import moderngl

    prog = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
    prog["view"].write(view.T.astype("f4").tobytes())  # GLSL matrices are column-major
    prog["proj"].write(proj.T.astype("f4").tobytes())
    prog["ambient"].value, prog["diffuse"].value = _AMBIENT, _DIFFUSE
    samples = min(4, ctx.max_samples)
    msaa = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), 4, samples=samples)],
                           depth_attachment=ctx.depth_renderbuffer((width, height), samples=samples))
    resolved = ctx.simple_framebuffer((width, height), components=4)
    ctx.enable(moderngl.DEPTH_TEST)  # no face culling: two-sided

    draws = []
    for P, F, uv, col, data in zip(scene.positions, scene.faces, scene.uvs, scene.colors, scene.textures):
        if len(F) == 0:
            continue
        n = P.shape[1]
        pos_buf = ctx.buffer(reserve=n * 12)
        nrm_buf = ctx.buffer(reserve=n * 12)
        uv_buf = ctx.buffer((uv if uv is not None else np.zeros((n, 2))).astype("f4").tobytes())
        col_buf = ctx.buffer(col.astype("f4").tobytes())
        idx_buf = ctx.buffer(np.ascontiguousarray(F, dtype="u4").tobytes())
        vao = ctx.vertex_array(prog, [(pos_buf, "3f", "in_pos"), (nrm_buf, "3f", "in_nrm"),
                                      (uv_buf, "2f", "in_uv"), (col_buf, "4f", "in_col")], idx_buf)
        tex = _gl_texture(ctx, data) if data is not None else None
        draws.append((P, F, pos_buf, nrm_buf, vao, tex))

    total = len(scene.times)
    out = np.empty((total, height, width, 3), dtype=np.uint8)
    bg = tuple(c / 255 for c in BACKGROUND)
    for f in range(total):
        msaa.use()
        msaa.clear(*bg, 1.0)
        for P, F, pos_buf, nrm_buf, vao, tex in draws:
            pos_buf.write(P[f].astype("f4").tobytes())
            nrm_buf.write(vertex_normals(P[f], F).astype("f4").tobytes())
            prog["use_tex"].value = tex is not None
            if tex is not None:
                tex.use(0)
                prog["tex"].value = 0
            vao.render(moderngl.TRIANGLES)
        ctx.copy_framebuffer(resolved, msaa)
        img = np.frombuffer(resolved.read(components=3), dtype=np.uint8).reshape(height, width, 3)
        out[f] = img[::-1]  # OpenGL rows start at the bottom
        if progress is not None:
            progress(f + 1, total)
    return out


# ---------------------------------------------------------------------------------------------
# Pillow fallback (painter's algorithm)


def _texture_mean(data):
    from PIL import Image

    img = Image.open(io.BytesIO(data)).convert("RGB")
    return np.asarray(img, dtype=np.float64).reshape(-1, 3).mean(axis=0) / 255


def _render_pil(scene, view, proj, width, height, progress, supersample=2):
    from PIL import Image, ImageDraw

    W, H = width * supersample, height * supersample
    face_colors, all_faces, offsets = [], [], []
    start = 0
    for P, F, col, data in zip(scene.positions, scene.faces, scene.colors, scene.textures):
        c = _srgb(col[:, :3])
        if data is not None:
            c = c * _texture_mean(data)
        face_colors.append(c[F].mean(axis=1))
        all_faces.append(F + start)
        offsets.append(start)
        start += P.shape[1]
    face_colors = np.concatenate(face_colors)  # (m, 3) sRGB in [0, 1]
    faces = np.concatenate(all_faces)
    total = len(scene.times)
    out = np.empty((total, height, width, 3), dtype=np.uint8)
    for f in range(total):
        P = np.concatenate([Pm[f] for Pm in scene.positions])
        cam = P @ view[:3, :3].T + view[:3, 3]  # (n, 3) camera space
        clip = cam @ proj[:3, :3].T + proj[:3, 3]
        w = cam @ proj[3, :3] + proj[3, 3]
        ndc = clip[:, :2] / w[:, None]
        xy = np.column_stack([(ndc[:, 0] + 1) / 2 * W, (1 - ndc[:, 1]) / 2 * H])
        tri = cam[faces]  # (m, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normal, axis=1)
        lambert = np.abs(normal[:, 2]) / np.maximum(length, 1e-30)
        rgb = face_colors * (_AMBIENT + _DIFFUSE * lambert)[:, None]
        rgb = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
        depth = tri[:, :, 2].mean(axis=1)  # camera looks along -z: most negative is farthest
        visible = (w[faces] > 0).all(axis=1) & (length > 0)
        order = np.flatnonzero(visible)[np.argsort(depth[visible], kind="stable")]
        img = Image.new("RGB", (W, H), BACKGROUND)
        draw = ImageDraw.Draw(img)
        pts = xy[faces]
        for i in order:
            draw.polygon([tuple(p) for p in pts[i]], fill=tuple(rgb[i]))
        out[f] = np.asarray(img.resize((width, height), Image.Resampling.BOX))
        if progress is not None:
            progress(f + 1, total)
    return out


# ---------------------------------------------------------------------------------------------
# outputs


def contact_sheet(frames, *, count=12, columns=4, labels=None):
    """A grid of ``count`` frames evenly spread over the clip, ``(rows*h, columns*w, 3)`` uint8.

    Parameters
    ----------
    frames : (F, h, w, 3) uint8
    count : int
        Frames shown (at most F), first and last included.
    columns : int
    labels : sequence of str, optional
        One per frame of ``frames`` (e.g. times), drawn in the corner of each tile.
    """
    from PIL import Image, ImageDraw

    F, h, w, _ = frames.shape
    pick = np.unique(np.linspace(0, F - 1, min(count, F)).round().astype(int))
    columns = max(1, min(columns, len(pick)))
    rows = -(-len(pick) // columns)
    sheet = Image.new("RGB", (columns * w, rows * h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, f in enumerate(pick):
        x, y = (k % columns) * w, (k // columns) * h
        sheet.paste(Image.fromarray(frames[f]), (x, y))
        if labels is not None:
            draw.text((x + 4, y + 4), str(labels[f]), fill=(20, 20, 20))
    return np.asarray(sheet)


def _atomic(path, write):
    """Call ``write(tmp_path)`` on a temporary file beside ``path``, then rename it over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, suffix=path.suffix) as tmp:  # imageio picks the format by suffix
        write(str(tmp))
    return path


def write_gif(frames, path, *, fps=30.0):
    """An looping animated GIF, one image per frame, ``1/fps`` apart (rounded to 10 ms by GIF).

    Identical consecutive frames (a character standing still) are merged by Pillow into one
    longer frame, so the timing, not the frame count, is kept in that case.
    """
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    duration = max(20, int(round(1000 / fps / 10)) * 10)

    def write(tmp):
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration,
                       loop=0, optimize=False, disposal=1)

    return _atomic(path, write)


def write_mp4(frames, path, *, fps=30.0):
    """An H.264 MP4 (needs ``imageio-ffmpeg``, which ships an ffmpeg binary)."""
    import importlib.util

    if importlib.util.find_spec("imageio_ffmpeg") is None:
        raise UnsupportedError("render: MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); "
                               "or write a GIF")
    import imageio.v2 as imageio

    frames = np.asarray(frames)
    # yuv420p (what players accept) needs even sizes: pad by one row/column of background
    h, w = frames.shape[1:3]
    pad = ((0, 0), (0, h % 2), (0, w % 2), (0, 0))
    frames = np.pad(frames, pad, mode="edge") if h % 2 or w % 2 else frames

    def write(tmp):
        with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                pixelformat="yuv420p", macro_block_size=1) as writer:
            for f in frames:
                writer.append_data(f)

    return _atomic(path, write)


def write_png(image, path):
    """One image as PNG (e.g. a contact sheet)."""
    from PIL import Image

    return _atomic(path, lambda tmp: Image.fromarray(image).save(tmp, format="PNG"))


def render_clip(character, clip=None, *, gif=None, mp4=None, sheet=None, fps=30.0, width=480, height=480,
                azimuth=30.0, elevation=15.0, backend="auto", bones=False, sheet_frames=12, progress=None):
    """Render a clip once and write any of a GIF, an MP4 and a contact sheet PNG.

    Parameters
    ----------
    character : rigmix.character.Character
    clip : Clip, str or None
        Default: the first clip (the rest pose for a character without clips).
    gif, mp4, sheet : str or Path, optional
        Output files; at least one is needed. Each is written atomically.
    fps : float
        Frames per second of the rendering (the clip is sampled every ``1/fps`` s, end included).
    width, height, azimuth, elevation, backend, bones, progress
        See :func:`render_frames`.
    sheet_frames : int
        Frames shown on the contact sheet.

    Returns
    -------
    (F, height, width, 3) uint8
        The rendered frames.
    """
    if gif is None and mp4 is None and sheet is None:
        raise InputError("render: nothing to write; give a GIF, an MP4 or a contact sheet path")
    if clip is None and character.clips:
        clip = character.clips[0]
    scene = pose_scene(character, clip, fps=fps)
    frames = render_frames(scene, width=width, height=height, azimuth=azimuth, elevation=elevation,
                           backend=backend, bones=bones, progress=progress)
    if gif is not None:
        write_gif(frames, gif, fps=fps)
    if mp4 is not None:
        write_mp4(frames, mp4, fps=fps)
    if sheet is not None:
        write_png(contact_sheet(frames, count=sheet_frames, labels=[f"{t:.2f} s" for t in scene.times]), sheet)
    return frames
