"""The dfd command line: distill, weights, deform on files."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import asset

from dfd.cli import main
from dfd.field import load_field
from dfd.io import read_mesh, write_mesh
from dfd.shapes import ellipsoids

QUICK = ["--views", "6", "--resolution", "40", "--steps", "10", "--batch-size", "256"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("dfd_cli")
    V, F = ellipsoids([((0, 0, 0), (0.6, 1.0, 0.5)), ((0.9, 0.3, 0), (0.35, 0.2, 0.2))], subdivisions=2)
    mesh = root / "figure.obj"
    write_mesh(mesh, V, F)
    field = root / "figure.pt"
    assert main(["distill", str(mesh), "-o", str(field), *QUICK]) == 0
    return root, mesh, field


def test_distill_writes_a_field(files):
    _, mesh, field = files
    m = read_mesh(mesh)
    f = load_field(field)
    assert f.settings["resolution"] == 40 and f.settings["steps"] == 10
    np.testing.assert_allclose(np.linalg.norm(f.evaluate(m.V), axis=1), 1.0, atol=1e-5)


def test_weights_command(files, capsys):
    root, mesh, field = files
    out = root / "w.npy"
    assert main(["weights", str(mesh), str(field), "--handle", "0", "200", "--locality", "1", "-o", str(out)]) == 0
    W = np.load(out)
    n = len(read_mesh(mesh).V)
    assert W.shape == (n, 2) and W.dtype == np.float32
    assert (W >= 0).all() and (W <= 1).all()
    assert W[0, 0] == pytest.approx(1.0, abs=1e-3) and W[200, 1] == pytest.approx(1.0, abs=1e-3)
    assert "2 handles" in capsys.readouterr().out


def test_deform_command(files):
    root, mesh, field = files
    m = read_mesh(mesh)
    still = root / "still.ply"
    assert main(["deform", str(mesh), str(field), "--handle", "0", "--translate", "0", "0", "0", "-o", str(still)]) == 0
    np.testing.assert_allclose(read_mesh(still).V, m.V, atol=1e-5)  # zero motion: the same mesh (PLY stores float32)
    moved = root / "moved.obj"
    args = ["deform", str(mesh), str(field), "--handle", "0", "--translate", "0", "0.5", "0",
            "--handle", "200", "--translate", "0", "0", "0", "-o", str(moved)]
    assert main(args) == 0
    out = read_mesh(moved)
    np.testing.assert_array_equal(out.F, m.F)
    np.testing.assert_allclose(out.V[0], m.V[0] + [0, 0.5, 0], atol=1e-3)  # the handle follows its map
    shift = out.V - m.V
    assert (np.abs(shift[:, [0, 2]]) < 1e-6).all() and (shift[:, 1] >= -1e-6).all()


def test_errors_are_one_line_and_exit_2(files, capsys):
    root, mesh, field = files
    assert main(["weights", str(mesh), str(field), "--handle", "999999", "-o", str(root / "x.npy")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "out of range" in err and err.count("\n") == 1
    assert main(["deform", str(mesh), str(field), "--handle", "0", "--handle", "1",
                 "--translate", "0", "0", "0", "-o", str(root / "y.obj")]) == 2
    assert main(["weights", str(root / "nope.obj"), str(field), "--handle", "0", "-o", str(root / "z.npy")]) == 2


def test_reads_gltf_characters():
    m = read_mesh(asset("Horse"))
    assert m.V.shape == (4400, 3) and m.F.shape == (2182, 3)
    assert m.vertex_colors is not None  # 8 flat-coloured materials
    assert len(np.unique(np.round(m.vertex_colors, 4), axis=0)) > 1
    c = read_mesh(asset("CesiumMan"))
    assert c.F.shape == (4672, 3) and c.texture is not None and c.uvs.shape == (3273, 2)
    # the Z-up to Y-up node above the mesh is applied: the man stands along +Y, about 1.5 tall
    extent = c.V.max(axis=0) - c.V.min(axis=0)
    assert extent[1] == pytest.approx(1.507, abs=0.01)


def test_dfd_never_imports_rigmix():
    import subprocess
    import sys

    code = (
        "import sys, dfd.cli, dfd.render, dfd.encoders, dfd.dinov2, dfd.field, dfd.distill, dfd.weights, "
        "dfd.symmetry, dfd.deform, dfd.io, dfd.shapes; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'rigmix'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
