"""The ``dfd`` command line: distill a feature field, compute handle weights, deform a mesh.

    dfd distill MESH -o FIELD.pt [--encoder filterbank|dinov2] [--views 24] [--resolution 224] ...
    dfd weights MESH FIELD --handle VERTEX [VERTEX ...] -o W.npy [--form distance|cosine]
                [--fixed VERTEX ...] [--locality P]
    dfd deform MESH FIELD --handle V --translate X Y Z [--handle V --translate X Y Z ...] -o OUT.obj

Meshes: OBJ, PLY, OFF, STL, glTF, GLB (:func:`dfd.io.read_mesh`). This module is the only place
that configures logging and prints.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from dfd.errors import DfdError, DfdInputError

__all__ = ["main", "build_parser"]

log = logging.getLogger("dfd")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``dfd``."""
    parser = argparse.ArgumentParser(prog="dfd", description="Deep Feature Deformation weights for triangle meshes.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", required=True)

    d = sub.add_parser("distill", help="distill a feature field from renders of a mesh")
    d.add_argument("mesh", help="OBJ, PLY, OFF, STL, glTF or GLB")
    d.add_argument("-o", "--output", required=True, help="field file (.pt)")
    d.add_argument("--encoder", default="filterbank", choices=["filterbank", "dinov2"])
    d.add_argument("--checkpoint", help="DINOv2 state dict (default $DFD_DINOV2_CHECKPOINT)")
    d.add_argument("--views", type=int, default=24)
    d.add_argument("--resolution", type=int, default=224)
    d.add_argument("--layout", default="prototype", choices=["prototype", "sphere"])
    d.add_argument("--face-budget", type=int, default=50_000)
    d.add_argument("--steps", type=int, default=None, help="Adam steps (default dfd.distill.DEFAULT_STEPS)")
    d.add_argument("--batch-size", type=int, default=None)
    d.add_argument("--fourier", type=int, default=0, help="Fourier feature octaves (0: none)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--cache", help="folder of distilled fields to reuse")

    def weight_options(p):
        p.add_argument("mesh")
        p.add_argument("field", help="field file from `dfd distill`")
        p.add_argument("--form", default="distance", choices=["distance", "cosine"])
        p.add_argument("--fixed", type=int, nargs="+", default=[], help="vertices that must not move")
        p.add_argument("--locality", type=float, default=0.0, help="geodesic locality exponent p (0: off)")

    w = sub.add_parser("weights", help="weights of every vertex for handle vertices")
    weight_options(w)
    w.add_argument("--handle", type=int, nargs="+", action="extend", required=True, help="handle vertex indices")
    w.add_argument("-o", "--output", required=True, help="weights (.npy, (n, h) float32)")

    f = sub.add_parser("deform", help="move handles and write the deformed mesh")
    weight_options(f)
    f.add_argument("--handle", type=int, action="append", required=True, help="handle vertex (repeat)")
    f.add_argument(
        "--translate", type=float, nargs=3, action="append", required=True, metavar=("X", "Y", "Z"),
        help="translation of the matching --handle (repeat, same order)",
    )
    f.add_argument("-o", "--output", required=True, help="deformed mesh (.obj, .ply, .off, .stl)")
    return parser


def _distill(args):
    from dfd.distill import DEFAULT_BATCH_SIZE, DEFAULT_STEPS, distill
    from dfd.io import read_mesh

    mesh = read_mesh(args.mesh)
    start = time.perf_counter()
    field = distill(
        mesh.V,
        mesh.F,
        encoder=args.encoder,
        encoder_kwargs={"checkpoint": args.checkpoint} if args.encoder == "dinov2" else None,
        n_views=args.views,
        resolution=args.resolution,
        layout=args.layout,
        face_budget=args.face_budget,
        steps=DEFAULT_STEPS if args.steps is None else args.steps,
        batch_size=DEFAULT_BATCH_SIZE if args.batch_size is None else args.batch_size,
        n_frequencies=args.fourier,
        seed=args.seed,
        vertex_colors=mesh.vertex_colors,
        uvs=mesh.uvs,
        texture=mesh.texture,
        cache=args.cache,
    )
    field.save(args.output)
    print(f"dfd distill: {args.mesh} ({len(mesh.F)} faces) -> {args.output} in {time.perf_counter() - start:.1f} s")


def _weights(args, handles):
    """Mesh, field and the (n, h) weights of the handle vertices."""
    from dfd.field import load_field
    from dfd.io import read_mesh
    from dfd.mesh import mesh_hash
    from dfd.weights import geodesic_distances, handle_weights

    mesh = read_mesh(args.mesh)
    field = load_field(args.field)
    if field.mesh_hash != mesh_hash(mesh.V, mesh.F):
        log.warning("dfd: %s was distilled from another mesh than %s; evaluating it anyway", args.field, args.mesh)
    n = len(mesh.V)
    bad = [h for h in list(handles) + list(args.fixed) if not 0 <= h < n]
    if bad:
        raise DfdInputError(f"dfd: vertex indices {bad} are out of range for {args.mesh} ({n} vertices)")
    features = field.evaluate(mesh.V)
    geodesic = geodesic_distances(mesh.V, mesh.F, handles) if args.locality > 0 else None
    W = handle_weights(
        features,
        features[handles],
        form=args.form,
        fixed=features[args.fixed] if args.fixed else None,
        geodesic=geodesic,
        p=args.locality,
    )
    return mesh, W


def _cmd_weights(args):
    _, W = _weights(args, args.handle)
    np.save(args.output, W)
    print(f"dfd weights: {W.shape[0]} vertices x {W.shape[1]} handles -> {args.output}")


def _cmd_deform(args):
    from dfd.deform import deform, translations
    from dfd.io import write_mesh

    if len(args.handle) != len(args.translate):
        raise DfdInputError(
            f"dfd deform: {len(args.handle)} --handle but {len(args.translate)} --translate; "
            "give one translation per handle"
        )
    mesh, W = _weights(args, args.handle)
    Vd = deform(mesh.V, W, translations(args.translate))
    write_mesh(args.output, Vd, mesh.F)
    print(f"dfd deform: {len(args.handle)} handles moved -> {args.output}")


def main(argv=None) -> int:
    """Run ``dfd``; returns the exit status (0 ok, 2 for a reported error)."""
    args = build_parser().parse_args(argv)
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "distill":
            _distill(args)
        elif args.command == "weights":
            _cmd_weights(args)
        else:
            _cmd_deform(args)
    except DfdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
