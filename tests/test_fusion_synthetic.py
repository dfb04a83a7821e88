"""fuse_surfaces end to end on shapes made in code: closed, manifold, no gaps, good triangles."""

import numpy as np
import pytest
from fusion_shapes import ellipsoid, split_faces, two_joint_weights

from rigmix.fusion import FusionAction, FusionInput, FusionParams, fuse_surfaces
from rigmix.geometry import weld


def closed_volume(V, F):
    Vw, _, Fw = weld(V, F)
    P = Vw[Fw]
    return np.einsum("ij,ij->i", P[:, 0], np.cross(P[:, 1], P[:, 2])).sum() / 6


def hausdorff(Va, Fa, Vb, Fb):
    import igl

    d1 = np.sqrt(igl.point_mesh_squared_distance(Va, Vb, Fb)[0]).max()
    d2 = np.sqrt(igl.point_mesh_squared_distance(Vb, Va, Fa)[0]).max()
    return max(d1, d2)


def assert_clean(out, *, min_angle=20.0):
    m = out.report["mesh"]
    assert m["junction_faces"] > 0
    assert m["junction_boundary_edges"] == 0
    assert m["boundary_edges"] == 0
    assert m["non_manifold_edges"] == 0
    assert m["junction_min_angle_p05"] >= min_angle
    assert out.report["fields"]["voxels"] > 0
    assert out.report["timings"]["total"] > 0


@pytest.fixture(scope="module")
def capsule():
    V, F = ellipsoid((1.5, 0.4, 0.4))
    return V, F, two_joint_weights(V)


# a shape composed with itself has its junction copied by default; these rebuild it from the
# fields, as between two different shapes
REMESHED = FusionParams(copy_coincident=False)


def test_self_replace_reproduces_the_shape(capsule):
    V, F, W = capsule
    out = fuse_surfaces([FusionInput(V, F, W, np.array([True, False])), FusionInput(V, F, W, np.array([False, True]))],
                        [FusionAction("replace", 0, 1)], params=REMESHED)
    assert_clean(out)
    diag = np.linalg.norm(V.max(0) - V.min(0))
    assert hausdorff(out.V, out.F, V, F) < 0.005 * diag
    assert np.isclose(closed_volume(out.V, out.F), closed_volume(V, F), rtol=0.01)
    # preserved faces are copies of input faces: same positions, bit for bit
    keep = out.face_origin_input >= 0
    src = out.face_origin_face[keep]
    inp = out.face_origin_input[keep]
    assert np.array_equal(out.V[out.F[keep]], V[F[src]])
    assert set(inp.tolist()) == {0, 1}
    assert np.all(out.origin_vertex[out.origin_input >= 0] >= 0)


def test_split_vertices_give_the_same_surface(capsule):
    V, F, W = capsule
    Vs, Fs = split_faces(V, F)
    Ws = W[F.ravel()]
    uv = np.random.default_rng(0).random((len(Vs), 2))
    out = fuse_surfaces([FusionInput(Vs, Fs, Ws, np.array([True, False]), uvs=uv),
                         FusionInput(Vs, Fs, Ws, np.array([False, True]), uvs=uv)],
                        [FusionAction("replace", 0, 1)], params=REMESHED)
    assert_clean(out)
    keep = out.origin_input >= 0
    assert np.array_equal(out.uvs[keep], uv[out.origin_vertex[keep]])
    assert np.array_equal(out.V[keep], Vs[out.origin_vertex[keep]])


def test_replace_between_different_shapes_is_closed():
    Va, Fa = ellipsoid((1.5, 0.45, 0.45))
    Vb, Fb = ellipsoid((1.4, 0.3, 0.35), center=(0.05, 0.02, 0.0), subdivisions=4)
    col_a = np.tile([1.0, 0.0, 0.0, 1.0], (len(Va), 1))
    col_b = np.tile([0.0, 0.0, 1.0, 1.0], (len(Vb), 1))
    out = fuse_surfaces([FusionInput(Va, Fa, two_joint_weights(Va, 0.0, 0.1), np.array([True, False]), colors=col_a),
                         FusionInput(Vb, Fb, two_joint_weights(Vb, 0.1, 0.1), np.array([False, True]), colors=col_b)],
                        [FusionAction("replace", 0, 1)])
    assert_clean(out)
    # junction colours blend red into blue along x
    jv = out.origin_input < 0
    c = out.colors[jv]
    x = out.V[jv, 0]
    assert np.all(c >= -1e-9) and np.all(c <= 1 + 1e-9)
    assert np.corrcoef(x, c[:, 2])[0, 1] > 0.5


def test_voxel_cap_relative_to_the_diagonal():
    """``max_voxel_diagonal`` refines the grid below the edge-length rule (off by default) and
    the junction stays closed."""
    from rigmix.fusion import FusionParams
    from rigmix.geometry import bounding_box_diagonal

    Va, Fa = ellipsoid((1.5, 0.45, 0.45))
    Vb, Fb = ellipsoid((1.4, 0.3, 0.35), center=(0.05, 0.02, 0.0), subdivisions=4)
    inputs = [FusionInput(Va, Fa, two_joint_weights(Va, 0.0, 0.1), np.array([True, False])),
              FusionInput(Vb, Fb, two_joint_weights(Vb, 0.1, 0.1), np.array([False, True]))]
    diag = min(bounding_box_diagonal(Va), bounding_box_diagonal(Vb))
    plain = fuse_surfaces(inputs, [FusionAction("replace", 0, 1)])
    cap = 0.9 * plain.report["fields"]["voxel_size"] / diag  # just below the edge-length rule
    capped = fuse_surfaces(inputs, [FusionAction("replace", 0, 1)], params=FusionParams(max_voxel_diagonal=cap))
    assert capped.report["fields"]["voxel_size"] <= cap * diag * (1 + 1e-9)
    assert capped.report["fields"]["voxels"] > plain.report["fields"]["voxels"]
    m = capped.report["mesh"]
    assert m["junction_boundary_edges"] == 0 and m["boundary_edges"] == 0 and m["non_manifold_edges"] == 0


def test_attach_is_the_union():
    Vb, Fb = ellipsoid((1, 1, 1))
    Va, Fa = ellipsoid((0.9, 0.25, 0.25), center=(1.5, 0, 0))
    Wa = two_joint_weights(Va, 0.9, 0.05)
    out = fuse_surfaces([FusionInput(Vb, Fb, np.ones((len(Vb), 1)), np.array([True])),
                         FusionInput(Va, Fa, Wa, np.array([False, True]))],
                        [FusionAction("attach", 0, 1)])
    assert_clean(out)
    # the arm's part outside the sphere is added: between the sphere and sphere + whole arm
    vol = closed_volume(out.V, out.F)
    assert closed_volume(Vb, Fb) < vol < closed_volume(Vb, Fb) + closed_volume(Va, Fa)
    # nothing of the union lies inside the sphere or the arm by more than a voxel
    import igl

    h = out.report["fields"]["voxel_size"]
    w = igl.fast_winding_number(Vb, Fb, out.V) + igl.fast_winding_number(Va, Fa, out.V)
    d = np.minimum(np.sqrt(igl.point_mesh_squared_distance(out.V, Vb, Fb)[0]),
                   np.sqrt(igl.point_mesh_squared_distance(out.V, Va, Fa)[0]))
    assert np.all((w < 0.5) | (d < 1.5 * h))


def test_removed_subtree_is_capped():
    V, F = ellipsoid((1.5, 0.4, 0.4))
    W = two_joint_weights(V, 0.3, 0.08)
    out = fuse_surfaces([FusionInput(V, F, W, np.array([True, False]))], [])
    assert_clean(out)
    assert out.V[:, 0].max() < 0.5
    assert closed_volume(out.V, out.F) > 0


def test_bad_inputs_are_reported():
    from rigmix.errors import InputError

    V, F = ellipsoid((1, 1, 1), subdivisions=1)
    W = np.ones((len(V), 1))
    with pytest.raises(InputError, match="fusion"):
        fuse_surfaces([FusionInput(V, F + 1000, W, np.array([True]))], [])
    with pytest.raises(InputError, match="two different inputs"):
        fuse_surfaces([FusionInput(V, F, W, np.array([True]))], [FusionAction("replace", 0, 0)])


def test_a_seam_that_runs_into_a_hole_of_the_mesh_closes_it():
    """A sphere with a face missing where the seam of a replace runs: the seam of each input is
    a chain from the hole's edge round to it. Closed along the hole's edge, it is bridged like
    any seam loop, and the output is closed (open, it left 39 boundary edges)."""
    from fusion_shapes import sphere

    V, F = sphere(3)
    W = two_joint_weights(V, 0.0, 0.15)
    params = FusionParams(copy_coincident=False)

    def fuse(faces):
        return fuse_surfaces([FusionInput(V, faces, W, np.array([True, False])),
                              FusionInput(V, faces, W, np.array([False, True]))],
                             [FusionAction("replace", 0, 1)], params=params)

    whole = fuse(F)
    # the seam runs along the kept faces of input 0 that touch the junction: take one away
    Vw, _, Fw = weld(whole.V, whole.F)[:3]
    on_junction = np.zeros(len(Vw), bool)
    on_junction[Fw[whole.junction_faces].ravel()] = True
    beside = np.flatnonzero(~whole.junction_faces & (whole.face_origin_input == 0) & on_junction[Fw].any(axis=1))
    holed = np.delete(F, whole.face_origin_face[beside[0]], axis=0)
    m = fuse(holed).report["mesh"]
    for key in ("boundary_edges", "junction_boundary_edges", "open_seam_edges", "new_non_manifold_edges"):
        assert m[key] == 0, key
    assert m["junction_faces"] > 0 and m["junction_min_angle_p05"] >= 20.0
