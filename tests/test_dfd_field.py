"""dfd.field and dfd.distill: save/load, stored normalization, determinism, cache, decimation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dfd.distill import decimate, distill
from dfd.errors import DfdInputError
from dfd.field import FeatureField, load_field
from dfd.mesh import Normalization, mesh_hash
from dfd.shapes import ellipsoids, icosphere

#: Small, quick settings: the tests check behaviour, not feature quality.
QUICK = dict(n_views=12, resolution=48, steps=25, batch_size=512)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def figure():
    V, F = ellipsoids([((0, 0, 0), (0.6, 1.0, 0.5)), ((0.9, 0.3, 0), (0.35, 0.2, 0.2))], subdivisions=2)
    return V * 40.0 + [100.0, 0.0, -20.0], F  # unusual units and offset


@pytest.fixture(scope="module")
def field(figure):
    return distill(*figure, seed=3, **QUICK)


def test_field_architecture():
    f = FeatureField(28)
    linear = [m for m in f.mlp if isinstance(m, torch.nn.Linear)]
    norms = [m for m in f.mlp if isinstance(m, torch.nn.LayerNorm)]
    assert [(m.in_features, m.out_features) for m in linear] == [(3, 256)] + [(256, 256)] * 4 + [(256, 28)]
    assert len(norms) == 5
    g = FeatureField(28, n_frequencies=6)
    assert g.mlp[0].in_features == 3 + 36
    x = torch.randn(10, 3)
    np.testing.assert_allclose(g(x).norm(dim=1).detach().numpy(), 1.0, atol=1e-6)


def test_distilled_field_in_mesh_coordinates(field, figure):
    V, F = figure
    X = field.evaluate(V)
    assert X.shape == (len(V), field.feature_dim) and X.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), 1.0, atol=1e-5)
    assert field.mesh_hash == mesh_hash(V, F)
    # the stored normalization maps the mesh into [-1, 1]^3
    Vn = field.normalization.apply(V)
    np.testing.assert_allclose(np.abs(Vn).max(), 1.0)
    with torch.no_grad():
        np.testing.assert_allclose(field(torch.from_numpy(Vn.astype(np.float32))).numpy(), X, atol=1e-6)
    assert X.std(axis=0).max() > 0.05  # the field varies over the surface


def test_save_load_round_trip(field, figure, tmp_path):
    V, _ = figure
    path = tmp_path / "field.pt"
    field.save(path)
    loaded = load_field(path)
    np.testing.assert_array_equal(loaded.evaluate(V), field.evaluate(V))
    assert loaded.mesh_hash == field.mesh_hash and loaded.settings == field.settings
    assert isinstance(loaded.normalization, Normalization)
    np.testing.assert_array_equal(loaded.normalization.center, field.normalization.center)
    with pytest.raises(DfdInputError, match="no field file"):
        load_field(tmp_path / "missing.pt")


def test_deterministic_under_a_seed(field, figure):
    V, F = figure
    again = distill(V, F, seed=3, **QUICK)
    np.testing.assert_array_equal(again.evaluate(V), field.evaluate(V))
    other = distill(V, F, seed=4, **QUICK)
    assert np.abs(other.evaluate(V) - field.evaluate(V)).max() > 1e-3


def test_cache_reuses_fields(figure, tmp_path):
    V, F = figure
    first = distill(V, F, seed=0, cache=tmp_path, **QUICK)
    files = list(tmp_path.glob("*.pt"))
    assert len(files) == 1
    mtime = files[0].stat().st_mtime_ns
    second = distill(V, F, seed=0, cache=tmp_path, **QUICK)
    assert files[0].stat().st_mtime_ns == mtime  # read back, not trained and written again
    np.testing.assert_array_equal(second.evaluate(V), first.evaluate(V))
    distill(V, F, seed=1, cache=tmp_path, **QUICK)  # other settings: another file
    assert len(list(tmp_path.glob("*.pt"))) == 2


def test_decimation_respects_budget_and_keeps_shape():
    import igl

    V, F = icosphere(4)  # 5,120 faces
    C = (V + 1.0) / 2.0
    Vd, Fd, Cd, _ = decimate(V, F, 1000, vertex_colors=C)
    assert 800 <= len(Fd) <= 1000
    assert np.sqrt(igl.point_mesh_squared_distance(Vd, V, F)[0]).max() < 0.02
    np.testing.assert_allclose(Cd, (Vd + 1.0) / 2.0, atol=0.02)  # colours follow the surface
    Vs, Fs, _, _ = decimate(V, F, 10_000)
    np.testing.assert_array_equal(Fs, F)


def test_distill_decimates_above_budget(figure):
    V, F = figure
    small = distill(V, F, face_budget=500, **QUICK)
    assert small.mesh_hash == mesh_hash(V, F)  # the field belongs to the full mesh
    assert small.settings["face_budget"] == 500
    X = small.evaluate(V)
    np.testing.assert_allclose(np.linalg.norm(X, axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("lr_decay", [True, False])
def test_written_out_adam_is_torchs_bit_for_bit(lr_decay):
    """distill's optimizer and schedule (dfd.distill.Adam, cosine_rates) train exactly the
    weights that torch.optim.Adam with CosineAnnealingLR trains (the stored fields and every
    figure measured with them stay valid)."""
    from dfd.distill import Adam, cosine_rates

    def network():
        torch.manual_seed(0)
        return torch.nn.Sequential(torch.nn.Linear(3, 32), torch.nn.ReLU(), torch.nn.LayerNorm(32),
                                   torch.nn.Linear(32, 5))

    def train(ours):
        net = network()
        X = torch.randn(256, 3, generator=torch.Generator().manual_seed(1))
        Y = torch.randn(256, 5, generator=torch.Generator().manual_seed(2))
        steps, lr = 40, 1e-2
        if ours:
            opt = Adam(net.parameters())
            rates = list(cosine_rates(lr, steps)) if lr_decay else [lr] * steps
        else:
            opt = torch.optim.Adam(net.parameters(), lr=lr)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps) if lr_decay else None
        for step in range(steps):
            idx = torch.randint(256, (64,), generator=torch.Generator().manual_seed(step))
            loss = (net(X[idx]) - Y[idx]).square().sum(dim=1).mean()
            opt.zero_grad()
            loss.backward()
            if ours:
                opt.step(rates[step])
            else:
                opt.step()
                if sched is not None:
                    sched.step()
        return net.state_dict()

    mine, torchs = train(True), train(False)
    assert all(torch.equal(mine[k], torchs[k]) for k in torchs)
    assert not torch.equal(mine["0.weight"], network().state_dict()["0.weight"])  # training moved them


def test_distilling_does_not_import_the_compiler_stack():
    """A field trains without torch._dynamo (seconds of import, which torch.optim pays)."""
    import subprocess
    import sys

    code = ("import sys; from dfd.distill import distill; from dfd.shapes import ellipsoids; "
            "V, F = ellipsoids([((0, 0, 0), (1, 0.6, 0.5))], 1); "
            "distill(V, F, n_views=3, resolution=32, steps=3, batch_size=64); "
            "print('torch._dynamo' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
