"""Weight fill benchmark (issue 9): hide the artist's transition bands and fill them back.

Protocol, per character (all its skinned meshes concatenated into one ``(V, F, W)``):

1. weld vertices by position (the truth of a welded vertex is the mean of its split rows);
2. for every joint ``j``, the band is the set of welded vertices whose weight on ``j`` lies
   strictly between 0.05 and 0.95 (joints with an empty band are skipped);
3. hide all weights of the band (every split vertex of a band vertex is unknown) and fill them
   from the rest with :func:`rigmix.weights.fill_weights` (which clamps, keeps the 4 largest
   and renormalizes);
4. error = half the L1 distance to the artist's weights per band vertex (0 identical,
   1 disjoint), averaged over the band, then over the joints.

Methods: ``nearest``, ``harmonic``, ``inpaint`` (the paper's post-smoothing, 10 iterations),
``inpaint-anchor`` (no post-smoothing: the protocol of the issue's anchor figures) and ``dfd``
(with the character's distilled DFD feature field, cached on disk, and its bind-pose joint
positions, names and parents for the joint mirror and the bone prior). Nothing of the hidden
band reaches any method: the weights passed for band vertices are zeros, and every method
reads known rows only.

Issue 27's protocols, on the shared characters and the corpus (``--protocols``: all three in one
run, each character's fields made once; ``--both-hidden``: protocol 1; ``--similar-ambient``: 2 and 3).
Protocol 1, both sides hidden (:func:`mirror_pair_cases`): a limb's transition bands hidden together
with its mirror partner's (joint pairs from the limb classifier, :func:`mirror_joint_pairs`), so the
mirror prior has nothing to copy. Protocol 2, similar-part borrowing (:func:`similar_part_cases`): a
limb pair's bands hidden while the character's other arm or leg pairs stay painted, a wing's outer
joint pair, a tail's middle joint. Protocol 3, ambient handles (:func:`ambient_cases`): a tail chain,
or a wing pair, whose whole painted region is hidden; ``+ambient`` methods give its joints handles
sampled along their bones (:mod:`rigmix.weights.ambient`). Each is filled back by ``nearest``,
``inpaint``, ``dfd_no_field``, the pipeline's default and ``dfd`` with the field of each encoder of
:data:`FIELD_ENCODERS` and :data:`DIRECT_ENCODERS`, and reports the weight error and the skinned error
under the character's clips (:func:`skinned_error`).

Writes ``benchmarks/results/band_fill.json`` and ``band_fill.md``; ``band_fill_both_hidden.*``,
``band_fill_similar.*`` and ``band_fill_ambient.*`` for the protocols of issue 27.
Usage: ``python -m benchmarks.band_fill [--protocols | --both-hidden | --similar-ambient
[--direct-only] [--update]] [CHARACTER ...]``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
sys.path.insert(0, str(ROOT / "tests"))

from rigmix.geometry import weld  # noqa: E402
from rigmix.weights import feature_field, fill_weights  # noqa: E402

#: method label -> (fill_weights method, options)
METHODS = {
    "nearest": ("nearest", {}),
    "harmonic": ("harmonic", {}),
    "inpaint": ("inpaint", {}),
    "inpaint-anchor": ("inpaint", {"iterations": 0}),
    "dfd": ("dfd", {}),
    "dfd-geometry": ("dfd", {"field": False}),
}

#: distillation settings of the benchmark's fields: lighter than dfd's defaults (300 steps of
#: 4,096 pixels) so that the eight fields distil in minutes on a shared two-core machine; the
#: field enters the fill only through the mirror feature-agreement confidence
DISTILL = {"steps": 100, "batch_size": 2048}

#: the issue's anchor figures (nearest, harmonic, inpaint), measured without post-smoothing
ANCHORS = {
    "CesiumMan": (0.427, 0.341, 0.299),
    "Fox": (0.449, 0.397, 0.393),
    "Horse": (0.428, 0.362, 0.308),
    "Knight": (0.357, 0.291, 0.243),
    "Velociraptor": (0.320, 0.292, 0.247),
    "Wasp": (0.355, 0.241, 0.213),
    "RiggedFigure": (0.622, 0.516, 0.469),
}

LOW, HIGH = 0.05, 0.95


def character_arrays(character):
    """All skinned meshes of a character as one mesh.

    Returns
    -------
    V : (n, 3) float64, F : (m, 3) int64, W : (n, J) float64 dense weights,
    names : list of str (J,), joint_positions : (J, 3) bind-pose joint positions (mesh space).
    """
    J = character.skeleton.num_joints
    meshes = [m for m in character.meshes if m.skinned]
    offsets = np.cumsum([0] + [len(m.positions) for m in meshes])
    V = np.vstack([m.positions for m in meshes])
    F = np.vstack([m.faces + o for m, o in zip(meshes, offsets)])
    W = np.vstack([m.dense_weights(J) for m in meshes])
    positions = np.linalg.inv(character.skeleton.inverse_binds)[:, :3, 3]
    return V, F, W, list(character.skeleton.names), positions


def welded_truth(V, F, W):
    """Welded index and the artist's weights per welded vertex (mean of its split rows)."""
    Vw, index = weld(V)
    k = len(Vw)
    Wt = np.zeros((k, W.shape[1]))
    np.add.at(Wt, index, W)
    Wt /= np.bincount(index, minlength=k)[:, None]
    return index, Wt


def band_errors(V, F, W, method, *, names=None, low=LOW, high=HIGH, **options):
    """Error of one fill method on every transition band of a character.

    Parameters
    ----------
    V, F, W : the character's combined mesh and dense weights (split vertices).
    method : str
        ``fill_weights`` method.
    names : list of str, optional
        Joint names for the result keys (default ``"0"``, ``"1"``...).
    **options
        Passed to :func:`fill_weights`.

    Returns
    -------
    errors : dict
        joint name -> mean half-L1 error over its band (joints with an empty band omitted).
    """
    index, Wt = welded_truth(V, F, W)
    out = {}
    for j in range(W.shape[1]):
        band = (Wt[:, j] > low) & (Wt[:, j] < high)
        if not np.any(band):
            continue
        unknown = band[index]
        hidden = np.where(unknown[:, None], 0.0, W)  # the band's weights never reach the fill
        filled = fill_weights(V, F, hidden, unknown, method=method, **options)
        rows = np.zeros(len(Wt), dtype=np.int64)
        rows[index] = np.arange(len(V))  # one split vertex per welded vertex
        err = 0.5 * np.abs(filled[rows[band]] - Wt[band]).sum(axis=1)
        out[names[j] if names else str(j)] = float(err.mean())
    return out


def field_cache() -> Path:
    """Where distilled fields are kept between runs (``$RIGMIX_CACHE/dfd_fields``)."""
    base = Path(os.environ.get("RIGMIX_CACHE", Path.home() / ".cache" / "rigmix"))
    return base / "dfd_fields"


def run_character(name, path, methods=METHODS):
    """Every method on one character: per-joint errors, means and timings."""
    from rigmix.io import load_character

    character = load_character(path)
    V, F, W, names, positions = character_arrays(character)
    parents = character.skeleton.parents
    result = {"vertices": len(V), "welded": int(len(weld(V)[0])), "joints": len(names), "methods": {}}
    for label, (method, options) in methods.items():
        options = dict(options)
        if method == "dfd" and options.get("field") is not False:
            t0 = time.perf_counter()
            try:
                options["field"] = feature_field(V, F, cache=field_cache(), **DISTILL)
            except Exception as exc:  # e.g. a flat fixture that cannot be rendered
                result["field_error"] = f"{type(exc).__name__}: {exc}"
                options["field"] = False
            result["field_seconds"] = round(time.perf_counter() - t0, 2)
        if method == "dfd":
            options.update(joint_positions=positions, joint_names=names, joint_parents=parents)
        t0 = time.perf_counter()
        errors = band_errors(V, F, W, method, names=names, **options)
        seconds = time.perf_counter() - t0
        result["bands"] = len(errors)
        result["methods"][label] = {
            "mean_error": float(np.mean(list(errors.values()))) if errors else float("nan"),
            "seconds": round(seconds, 3),
            "per_joint": {k: round(v, 4) for k, v in errors.items()},
        }
    return result


def summarize(results):
    """Mean over the seven anchor characters per method, and the dfd goal."""
    seven = [n for n in ANCHORS if n in results]
    means = {m: float(np.mean([results[n]["methods"][m]["mean_error"] for n in seven]))
             for m in METHODS if seven}
    base = means.get("inpaint-anchor", float("nan"))
    wins = sum(results[n]["methods"]["dfd"]["mean_error"] < results[n]["methods"]["inpaint-anchor"]["mean_error"]
               for n in seven)
    return {
        "characters": seven,
        "mean_of_seven": means,
        "anchor_means": {"nearest": 0.423, "inpaint": 0.310},
        "dfd_vs_inpaint_anchor": {
            "relative_reduction": 1.0 - means.get("dfd", float("nan")) / base if seven else None,
            "characters_lower": int(wins),
        },
    }


def markdown(results, summary):
    labels = list(METHODS)
    lines = [
        "Band fill: mean half-L1 error over each joint's transition band (weights strictly in "
        f"({LOW}, {HIGH}) hidden and filled back), averaged over joints. Lower is better.",
        "`inpaint` applies the paper's 10 post-smoothing iterations; `inpaint-anchor` does not "
        "(the protocol of the issue's anchor figures, which it reproduces).",
        "",
        "| character | bands | " + " | ".join(labels) + " | anchor n / h / i | dfd s | field s |",
        "|---|---:|" + "---:|" * len(labels) + "---|---:|---:|",
    ]
    for n, r in results.items():
        a = ANCHORS.get(n)
        anchor = " / ".join(f"{x:.3f}" for x in a) if a else "-"
        cells = " | ".join(f"{r['methods'][m]['mean_error']:.3f}" for m in labels)
        lines.append(f"| {n} | {r['bands']} | {cells} | {anchor} | "
                     f"{r['methods']['dfd']['seconds']:.2f} | {r.get('field_seconds', 0):.1f} |")
    means = summary["mean_of_seven"]
    if means:
        cells = " | ".join(f"**{means[m]:.3f}**" for m in labels)
        lines.append(f"| mean of the seven | | {cells} | 0.423 / - / 0.310 | | |")
        d = summary["dfd_vs_inpaint_anchor"]
        lines += ["", f"`dfd` vs `inpaint-anchor`: {100 * d['relative_reduction']:.1f}% lower mean error, "
                  f"lower on {d['characters_lower']} of {len(summary['characters'])} characters."]
    lines += ["", "`dfd-geometry` is the ablation without the feature field (mirror prior from geometry "
              "and the skeleton only). SimpleSkin is not in the mean (no anchor).",
              "", "Timings: seconds to fill all bands of a character (the DFD field is distilled once "
              f"per character with {DISTILL} and cached; `field s` is loading or distilling it)."]
    return "\n".join(lines) + "\n"


# --- protocol 1 (issue 27): a limb's bands hidden together with its mirror partner's -------------

#: protocol 1's methods without a field: label -> (fill method, options)
BOTH_HIDDEN_METHODS = {
    "nearest": ("nearest", {}),
    "inpaint": ("inpaint", {}),
    "dfd_no_field": ("dfd", {"field": False}),
}

#: the encoders protocol 1 measures ``dfd`` with, one distilled field each (``dfd[<encoder>]``)
FIELD_ENCODERS = ("filterbank", "skeleton", "skeleton+filterbank", "hks")
#: encoders whose features are a function of the surface point, also used as fields without
#: distillation (``dfd[<encoder>-direct]``, :func:`dfd.encoders.point_field`)
DIRECT_ENCODERS = ("skeleton", "skeleton-relative", "hks")
#: the largest confidence of the prior borrowed from feature-similar parts (``...+borrow``
#: labels; ``fill_weights``' ``borrow``); without it the field only judges the mirror prior
BORROW = 0.5


def mirror_joint_pairs(character):
    """Joint pairs ``(j, k)`` of every mirrored limb pair that :func:`rigmix.limbs.classify_limbs` finds.

    The limb classifier pairs the limbs (geometry first, names only as a tie-breaker). Within a
    limb pair, joints pair in the classifier's order (parents first) when both limbs have as many;
    otherwise each joint of the first limb pairs with the partner joint nearest to its reflection
    across the classifier's symmetry plane (the axis ``symmetry_axis``, through the midpoint of the
    two limb roots).

    Returns
    -------
    pairs : list of (int, int)
        Joint indices into ``character.skeleton.names``; each limb pair listed once.
    limbs : list of (str, str)
        The root joints ``(limb, partner)`` of each pair, in the same order as their joints.
    """
    from rigmix.limbs import classify_limbs

    plan = classify_limbs(character)
    names = list(character.skeleton.names)
    index = {n: i for i, n in enumerate(names)}
    positions = np.linalg.inv(character.skeleton.inverse_binds)[:, :3, 3]
    axis = plan.symmetry_axis
    pairs, limbs, seen = [], [], set()
    for limb in plan.limbs:
        if limb.partner is None or limb.partner in seen:
            continue
        seen.add(limb.root)
        other = plan.limb(limb.partner)
        a = [index[n] for n in limb.joints]
        b = [index[n] for n in other.joints]
        if len(a) != len(b):
            offset = 0.5 * (positions[a[0], axis] + positions[b[0], axis])
            R = positions[a].copy()
            R[:, axis] = 2.0 * offset - R[:, axis]
            b = [b[int(np.argmin(np.linalg.norm(positions[b] - r, axis=1)))] for r in R]
        pairs += list(zip(a, b))
        limbs.append((limb.root, other.root))
    return pairs, limbs


def pair_band(Wt, j, k, *, low=LOW, high=HIGH):
    """``(n,) bool``: welded vertices in joint ``j``'s transition band or in joint ``k``'s
    (weights strictly in ``(low, high)``), hidden together by protocol 1."""
    return ((Wt[:, j] > low) & (Wt[:, j] < high)) | ((Wt[:, k] > low) & (Wt[:, k] < high))


def mirror_pair_cases(character):
    """Protocol 1's cases: every joint pair of :func:`mirror_joint_pairs`.

    Returns
    -------
    cases : list of dict
        ``name`` (``"j|k"``, the joint names), ``kind`` (``"joint pair"``) and ``joints`` ((2,) int64).
        :func:`case_mask` hides a pair only where both joints have a band (one side hidden alone is
        the single-band protocol of :func:`band_errors`).
    """
    pairs, _ = mirror_joint_pairs(character)
    names = list(character.skeleton.names)
    return [{"name": f"{names[j]}|{names[k]}", "kind": "joint pair", "joints": np.array([j, k], dtype=np.int64)}
            for j, k in pairs]


def make_encoder(name, V, F, positions, parents):
    """The encoder ``name`` of :data:`FIELD_ENCODERS` for one character (mesh, bind-pose skeleton).

    ``skeleton`` gets the bones as segments (:func:`dfd.encoders.bone_segments`; ``skeleton-relative``:
    without the channels that tell the bones apart), ``hks`` the mesh;
    ``a+b`` combines two encoders with equal weights."""
    from dfd.encoders import CombinedEncoder, bone_segments, get_encoder

    if "+" in name:
        return CombinedEncoder([make_encoder(part, V, F, positions, parents) for part in name.split("+")])
    if name in ("skeleton", "skeleton-relative"):
        heads, tails = bone_segments(positions, parents)
        return get_encoder("skeleton", heads=heads, tails=tails, describe=name == "skeleton")
    if name == "hks":
        return get_encoder(name, V=V, F=F)
    return get_encoder(name)


#: the decision rule of issue 27: a field is worth its cost where it lowers the mean junction
#: weight error by at least this fraction against ``dfd_no_field`` ...
RULE_REDUCTION = 0.10
#: ... and costs at most this many seconds per character
RULE_SECONDS = 3.0


def decision_rule(done, means):
    """Per field label ``dfd[E]...`` of ``means`` (label -> mean error over the characters that
    have it): its mean error against ``dfd_no_field``'s on the same characters of ``done`` (per
    character results), its field's cost there, and whether it passes the decision rule
    (:data:`RULE_REDUCTION`, :data:`RULE_SECONDS`)."""
    rule = {}
    for label in means:
        if not label.startswith("dfd["):
            continue
        enc = label[4:label.index("]")]
        have = [r for r in done if label in r["methods"]]
        b = float(np.mean([r["methods"]["dfd_no_field"]["mean_error"] for r in have]))
        seconds = [r["field_seconds"][enc] for r in have]
        reduction = 1.0 - means[label] / b if b > 0 else 0.0
        rule[label] = {"characters": len(have), "relative_reduction": reduction,
                       "field_seconds_max": float(max(seconds)), "field_seconds_mean": float(np.mean(seconds)),
                       "passes": bool(reduction >= RULE_REDUCTION and max(seconds) <= RULE_SECONDS)}
    return rule


# --- protocols 1 to 3 (issue 27): both sides hidden, similar parts painted, ambient handles -------

#: limb kinds that protocol 2 treats as similar parts of one another: a quadruped's front legs and
#: back legs, a dinosaur's arms and legs, an insect's three leg pairs; wings only with wings
SIMILAR_KINDS = {"arm": "limb", "leg": "limb", "wing": "wing"}
#: the largest confidence of the prior from handles sampled along the bones of joints nowhere
#: known (``...+ambient`` labels, protocol 3; ``fill_weights``' ``ambient``)
AMBIENT = 0.5
#: output file stem of each protocol
PROTOCOL_FILES = {"both_hidden": "band_fill_both_hidden", "similar": "band_fill_similar",
                  "ambient": "band_fill_ambient"}
#: issue 27's protocols, in order: 1 both sides hidden, 2 similar parts painted, 3 ambient handles
PROTOCOLS = tuple(PROTOCOL_FILES)
#: frames sampled per clip for the skinned error, and clips used at most (in file order)
SKIN_FRAMES, SKIN_CLIPS = 8, 6


def limb_joint_indices(character, limb):
    """``(m,) int64``: the limb's deforming joints and its detached ones (IK feet carrying the foot's skin)."""
    index = {n: i for i, n in enumerate(character.skeleton.names)}
    return np.array([index[n] for n in (*limb.joints, *limb.detached)], dtype=np.int64)


def similar_part_cases(character):
    """Protocol 2's cases: a part hidden while parts of the same kind stay painted.

    From :func:`rigmix.limbs.classify_limbs` (no joint names read here):

    * every mirrored limb pair of kind arm or leg (:data:`SIMILAR_KINDS`), when another arm or leg
      pair stays painted: the limb's joints and its partner's (detached ones included) are hidden
      together, so the mirror has nothing to copy and only the other pairs are alike;
    * every wing pair: its outermost joint pair when the wing has several joints (the inner ones
      stay painted), else the whole pair (nothing alike stays painted: the Wasp's single-bone wings);
    * every tail: its middle joint alone (the other tail joints stay painted).

    Returns
    -------
    cases : list of dict
        ``name`` (the hidden roots, ``|``-joined), ``kind``, ``joints`` ((m,) int64 hidden
        joints) and ``painted`` (roots, or joint names for a tail or wing chain, of the similar
        parts that stay painted).
    """
    from rigmix.limbs import classify_limbs

    plan = classify_limbs(character)
    names = list(character.skeleton.names)
    cases, seen = [], set()
    for limb in plan.limbs:
        if limb.partner is None or limb.root in seen or limb.kind not in SIMILAR_KINDS:
            continue
        other = plan.limb(limb.partner)
        seen |= {limb.root, other.root}
        alike = [x.root for x in plan.limbs if x.partner is not None and x.root not in (limb.root, other.root)
                 and SIMILAR_KINDS.get(x.kind) == SIMILAR_KINDS[limb.kind]]
        if limb.kind == "wing" and len(limb.joints) > 1 and len(limb.joints) == len(other.joints):
            hidden = [names.index(limb.joints[-1]), names.index(other.joints[-1])]
            inner = [n for n in (*limb.joints[:-1], *other.joints[:-1])]
            cases.append({"name": f"{limb.joints[-1]}|{other.joints[-1]}", "kind": "wing segment",
                          "joints": np.array(hidden, dtype=np.int64), "painted": alike + inner})
            continue
        if not alike and limb.kind != "wing":
            continue
        cases.append({"name": f"{limb.root}|{other.root}", "kind": limb.kind,
                      "joints": np.r_[limb_joint_indices(character, limb), limb_joint_indices(character, other)],
                      "painted": alike})
    for limb in plan.of_kind("tail"):
        if len(limb.joints) < 2:
            continue
        middle = limb.joints[len(limb.joints) // 2]
        cases.append({"name": middle, "kind": "tail segment", "joints": np.array([names.index(middle)]),
                      "painted": [n for n in limb.joints if n != middle]})
    return cases


def ambient_cases(character):
    """Protocol 3's cases: a tail chain, or a wing with its partner, whose painting is nowhere known.

    Returns
    -------
    cases : list of dict
        ``name``, ``kind`` ("tail" or "wing") and ``joints`` ((m,) int64): every deforming joint
        of the chain (both wings of a pair, or the mirror would copy one from the other).
    """
    from rigmix.limbs import classify_limbs

    plan = classify_limbs(character)
    cases, seen = [], set()
    for limb in plan.limbs:
        if limb.kind not in ("tail", "wing") or limb.root in seen:
            continue
        joints = limb_joint_indices(character, limb)
        name = limb.root
        if limb.partner is not None:
            other = plan.limb(limb.partner)
            seen.add(other.root)
            joints = np.r_[joints, limb_joint_indices(character, other)]
            name = f"{limb.root}|{other.root}"
        cases.append({"name": name, "kind": limb.kind, "joints": joints})
    return cases


def band_mask(Wt, joints, *, low=LOW, high=HIGH):
    """``(k,) bool``: welded vertices in the transition band (weight strictly in ``(low, high)``)
    of any of ``joints``: what protocols 1 and 2 hide."""
    B = Wt[:, joints]
    return ((B > low) & (B < high)).any(axis=1)


def region_mask(Wt, joints):
    """``(k,) bool``: welded vertices carrying any weight on ``joints`` (their whole painted region,
    what protocol 3 hides: afterwards no known vertex carries these joints)."""
    return (Wt[:, joints] > 0.0).any(axis=1)


def clip_matrices(character, *, frames=SKIN_FRAMES, clips=SKIN_CLIPS, rest=False):
    """Skinning matrices ``(f, J, 3, 4)`` at ``frames`` evenly spaced times of each of the
    character's first ``clips`` clips; ``None`` for a character without clips.

    They map bind-space points to world space (``world @ inverse_bind``), or with ``rest`` points
    of the skeleton's rest-pose world space, where a composition's fused surface lies
    (``world @ rest_world^-1``)."""
    from rigmix.animation.sampling import sample_clip
    from rigmix.skinning import skinning_matrices
    from rigmix.transforms import trs_to_matrix

    sk = character.skeleton
    out = []
    for clip in character.clips[:clips]:
        T, R, S = sample_clip(sk, clip, np.linspace(clip.start, clip.end, frames))
        if rest:
            M = sk.world_matrices(trs_to_matrix(T, R, S)) @ np.linalg.inv(sk.rest_worlds())
        else:
            M = skinning_matrices(sk, T, R, S)
        out.append(M[..., :3, :])
    return np.concatenate(out) if out else None


def rest_diagonal(skeleton, V, W):
    """Bounding-box diagonal of the mesh skinned in rest pose (the clips' space: an armature's scale,
    a Fox's centimetres, are applied), for ``V`` (n, 3) bind positions and ``W`` (n, J) weights."""
    from rigmix.skinning import rest_skinning_matrices

    M = rest_skinning_matrices(skeleton)[:, :3, :]
    A = np.einsum("nj,jab->nab", W, M)
    X = np.einsum("nab,nb->na", A[..., :3], V) + A[..., 3]
    return float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))


def skinned_error(V, W_true, W_filled, M, diagonal):
    """Vertex error under the clips, skinned with the filled weights against the artist's.

    Parameters
    ----------
    V : (h, 3) bind-space positions of the hidden vertices.
    W_true, W_filled : (h, J) dense weights.
    M : (f, J, 3, 4) skinning matrices (:func:`clip_matrices`).
    diagonal : float
        The character's bounding-box diagonal.

    Returns
    -------
    mean, max : float
        Of ``|| LBS(W_filled) - LBS(W_true) ||`` over hidden vertices and frames, as a fraction of
        ``diagonal`` (linear blend skinning is linear in the weights: the difference is skinned).
    """
    D = np.einsum("nj,fjab->fnab", W_filled - W_true, M, optimize=True)  # (f, h, 3, 4)
    d = np.linalg.norm(np.einsum("fnab,nb->fna", D[..., :3], V) + D[..., 3], axis=2) / diagonal
    return float(d.mean()), float(d.max())


def mask_errors(V, F, W, masks, method, *, skin=None, diagonal=1.0, **options):
    """Hide each welded mask's rows, fill them back with one method, and measure.

    Parameters
    ----------
    V, F, W : the character's combined mesh and dense weights (split vertices).
    masks : dict
        Case name -> ``(k,) bool`` over the welded vertices (:func:`welded_truth`'s order).
    method : str
        ``fill_weights`` method.
    skin : (f, J, 3, 4) float array, optional
        Skinning matrices (:func:`clip_matrices`) for the skinned error.
    diagonal : float
        The unit of the skinned error (:func:`rest_diagonal`).
    **options
        Passed to :func:`fill_weights`.

    Returns
    -------
    errors : dict
        Case name -> ``{"mean", "max", "rows"}``: half-L1 weight error over the hidden welded
        vertices (0 identical, 1 disjoint) and how many; with ``skin``, ``skinned`` and
        ``skinned_max`` (:func:`skinned_error`).
    """
    index, Wt = welded_truth(V, F, W)
    rows = np.zeros(len(Wt), dtype=np.int64)
    rows[index] = np.arange(len(V))  # one split vertex per welded vertex
    out = {}
    for key, mask in masks.items():
        unknown = mask[index]
        hidden = np.where(unknown[:, None], 0.0, W)  # the hidden weights never reach the fill
        filled = fill_weights(V, F, hidden, unknown, method=method, **options)
        err = 0.5 * np.abs(filled[rows[mask]] - Wt[mask]).sum(axis=1)
        out[key] = {"mean": float(err.mean()), "max": float(err.max()), "rows": int(mask.sum())}
        if skin is not None:
            r = rows[mask]
            out[key]["skinned"], out[key]["skinned_max"] = skinned_error(V[r], W[r], filled[r], skin, diagonal)
    return out


#: each protocol's cases (:func:`protocol_cases`)
CASES = {"both_hidden": mirror_pair_cases, "similar": similar_part_cases, "ambient": ambient_cases}


def protocol_cases(character, protocol):
    """The cases of ``protocol`` (a key of :data:`PROTOCOL_FILES`) on one character: a list of dicts
    with ``name``, ``kind`` and ``joints`` ((m,) int64 indices into the character's skeleton)."""
    return CASES[protocol](character)


def case_mask(Wt, joints, protocol, *, low=LOW, high=HIGH):
    """``(k,) bool``: the welded vertices one case of ``protocol`` hides, for ``Wt`` (k, J) weights
    and the case's ``joints`` (indices into ``Wt``'s columns).

    ``"ambient"``: the joints' whole painted region (:func:`region_mask`); ``"similar"``: their
    transition bands (:func:`band_mask`); ``"both_hidden"``: their bands, and nothing unless every
    joint has one (a pair whose one side has no band has nothing the mirror could have copied).
    """
    if protocol == "ambient":
        return region_mask(Wt, joints)
    if protocol == "both_hidden" and not all(band_mask(Wt, [j], low=low, high=high).any() for j in joints):
        return np.zeros(len(Wt), dtype=bool)
    return band_mask(Wt, joints, low=low, high=high)


def protocol_masks(character, Wt, protocol):
    """Case name -> ``(k,) bool`` hidden welded vertices (:func:`case_mask`) of each case of
    :func:`protocol_cases`; empty masks dropped."""
    masks = {c["name"]: case_mask(Wt, c["joints"], protocol) for c in protocol_cases(character, protocol)}
    return {k: m for k, m in masks.items() if m.any()}


def encoder_fields(V, F, positions, parents, *, encoders=FIELD_ENCODERS, direct=DIRECT_ENCODERS):
    """Every encoder's field for one character: distilled (``encoders``) and direct (``direct``).

    Returns
    -------
    fields : dict
        Label (``E`` or ``E-direct``) -> field (``evaluate``-able or callable).
    seconds : dict
        Label -> seconds to distil (no cache: the cost the decision rule reads) or build it.
    errors : dict
        Label -> the exception's text, for a field that could not be made.
    """
    from dfd.encoders import point_field

    fields, seconds, errors = {}, {}, {}
    for enc, is_direct in [(e, False) for e in encoders] + [(e, True) for e in direct]:
        label = f"{enc}-direct" if is_direct else enc
        t0 = time.perf_counter()
        try:
            encoder = make_encoder(enc, V, F, positions, parents)
            fields[label] = point_field(encoder, V) if is_direct else feature_field(V, F, encoder=encoder, **DISTILL)
        except Exception as exc:  # recorded, the other encoders still run
            errors[label] = f"{type(exc).__name__}: {exc}"
            continue
        seconds[label] = round(time.perf_counter() - t0, 2)
    return fields, seconds, errors


def protocol_methods(fields, protocol):
    """Label -> ``(fill method, options)``: the baselines, the pipeline's default (``dfd_default``),
    and, per field, ``dfd`` with it alone, with the borrow prior, and (protocol 3) with ambient handles."""
    methods = {label: (m, dict(o)) for label, (m, o) in BOTH_HIDDEN_METHODS.items()}
    # the pipeline's default since protocol 3's decision: no distilled field, borrowing with the
    # skeleton-relative field only next to joints nowhere known (rigmix.weights.ambient)
    methods["dfd_default"] = ("dfd", {"field": False, "ambient_borrow": BORROW})
    for label, field in fields.items():
        methods[f"dfd[{label}]"] = ("dfd", {"field": field})
        methods[f"dfd[{label}]+borrow"] = ("dfd", {"field": field, "borrow": BORROW})
        if protocol == "ambient":
            methods[f"dfd[{label}]+ambient"] = ("dfd", {"field": field, "ambient": AMBIENT})
    return methods


def run_protocols(path, *, protocols=PROTOCOLS, encoders=FIELD_ENCODERS, direct=DIRECT_ENCODERS):
    """Protocols 1 to 3 (``protocols``: keys of :data:`PROTOCOL_FILES`) on one character, sharing its fields.

    Returns
    -------
    results : dict
        Protocol -> a dict with the mesh sizes, ``cases`` (name -> hidden welded rows), and per
        method label ``mean_error`` (mean over cases), ``max_error`` (largest over all hidden
        vertices), ``skinned_error`` / ``skinned_max`` (mean over cases of the mean, and largest, skinned error
        as a fraction of the diagonal; absent without clips), ``seconds`` and ``per_case``; and the
        encoders' ``field_seconds`` and ``field_errors``.
    """
    from rigmix.io import load_character

    character = load_character(path)
    V, F, W, names, positions = character_arrays(character)
    parents = character.skeleton.parents
    index, Wt = welded_truth(V, F, W)
    masks = {p: protocol_masks(character, Wt, p) for p in protocols}
    base = {"vertices": len(V), "joints": len(names), "clips": len(character.clips)}
    results = {p: {**base, "cases": {k: int(m.sum()) for k, m in masks[p].items()}, "methods": {}}
               for p in protocols}
    if not any(masks.values()):
        return results
    fields, seconds, errors = encoder_fields(V, F, positions, parents, encoders=encoders, direct=direct)
    skin = clip_matrices(character)
    diagonal = rest_diagonal(character.skeleton, V, W)
    skeleton = {"joint_positions": positions, "joint_names": names, "joint_parents": parents,
                "deforming_joints": W.sum(axis=0) > 0}
    for p in protocols:
        results[p].update(field_seconds=seconds, field_errors=errors)
        if not masks[p]:
            continue
        for label, (method, options) in protocol_methods(fields, p).items():
            if method == "dfd":
                options = {**options, **skeleton}
            t0 = time.perf_counter()
            errs = mask_errors(V, F, W, masks[p], method, skin=skin, diagonal=diagonal, **options)
            results[p]["methods"][label] = method_summary(errs, time.perf_counter() - t0)
    return results


def method_summary(errors, seconds):
    """One method's figures on one character from :func:`mask_errors`' per-case errors."""
    e = list(errors.values())
    out = {"mean_error": float(np.mean([x["mean"] for x in e])), "max_error": float(max(x["max"] for x in e)),
           "seconds": round(seconds, 3),
           "per_case": {k: {m: (round(v, 4) if isinstance(v, float) else v) for m, v in x.items()}
                        for k, x in errors.items()}}
    if "skinned" in e[0]:
        out["skinned_error"] = float(np.mean([x["skinned"] for x in e]))
        out["skinned_max"] = float(max(x["skinned_max"] for x in e))
    return out


def summarize_protocol(results):
    """Mean over characters of each method's mean, max and skinned error, and the decision rule per
    field (against ``dfd_no_field`` on the same characters, with the field's largest cost there)."""
    done = [r for r in results.values() if r.get("methods")]
    labels = list(dict.fromkeys(label for r in done for label in r["methods"]))
    means, maxes, skinned = {}, {}, {}
    for label in labels:
        have = [r["methods"][label] for r in done if label in r["methods"]]
        means[label] = float(np.mean([m["mean_error"] for m in have]))
        maxes[label] = float(np.mean([m["max_error"] for m in have]))
        sk = [m["skinned_error"] for m in have if "skinned_error" in m]
        skinned[label] = float(np.mean(sk)) if sk else float("nan")
    skin_chars = sum(1 for r in done if "skinned_error" in r["methods"].get("nearest", {}))
    return {"characters": len(done), "skinned_characters": skin_chars, "mean_error": means,
            "mean_of_max_error": maxes, "skinned_error": skinned, "dfd_no_field": means.get("dfd_no_field"),
            "rule": decision_rule(done, means)}


#: what each protocol hides, for its table's header
PROTOCOL_TEXT = {
    "both_hidden": (
        "Band fill, protocol 1 (issue 27), both sides hidden: for each mirrored joint pair of each limb pair "
        "found by the limb classifier (`mirror_pair_cases`), both joints' transition bands (weights strictly "
        "in ({low}, {high})) are hidden together and filled back, so the mirror prior has nothing to copy; a "
        "case per joint pair where both joints have a band."),
    "similar": (
        "Band fill, protocol 2 (issue 27), similar-part borrowing: per case from the limb classifier "
        "(`similar_part_cases`), the transition bands (weights strictly in ({low}, {high})) of a limb and its "
        "mirror partner (detached IK feet included) are hidden together while the other arm or leg pairs stay "
        "painted (front against back legs, a dinosaur's arms against its legs, one of the Wasp's three leg "
        "pairs against the other two); the outer joint pair of a wing of several joints (the inner stays "
        "painted; the Wasp's one-bone wings: the whole pair, nothing alike painted); a tail's middle joint "
        "(the other tail joints painted)."),
    "ambient": (
        "Band fill, protocol 3 (issue 27), ambient handles: per tail chain, and per wing with its partner "
        "(`ambient_cases`), every welded vertex carrying any weight on the chain's joints is hidden, so no "
        "known vertex carries them: nearest and inpaint cannot bring them back; `+ambient` evaluates the "
        "field at points sampled along each such joint's bones in rest pose and gives the hidden vertices "
        "weights Gaussian in feature distance, `exp(-(||f(v) - f(h)|| / 0.1)^2)` normalized (DFD's own "
        "`clamp(1 - d)` is nearly flat over unit features), over those handles and the region's border joints "
        "(`rigmix/weights/ambient.py`, confidence {ambient})."),
}


def markdown_protocol(results, summary, protocol, distilled, *, header=None):
    """The protocol's table: means over characters with the decision rule, then per character.

    ``header``: what the protocol hides, opening the text (default :data:`PROTOCOL_TEXT`'s)."""
    labels = list(summary["mean_error"])
    rule = summary["rule"]
    fmt = {"low": LOW, "high": HIGH, "ambient": AMBIENT}
    lines = [
        (header or PROTOCOL_TEXT[protocol].format(**fmt))
        + " Error: half-L1 over the hidden welded vertices (0 identical, 1 disjoint); per character `mean` is the "
        "mean over cases, `max` the largest over every hidden vertex. "
        "Skinned error: the hidden vertices skinned (LBS) with the filled weights against the artist's at "
        f"{SKIN_FRAMES} evenly spaced frames of each of the first {SKIN_CLIPS} clips, distance as % of the "
        f"bounding-box diagonal, mean over vertices and frames then over cases ({summary['skinned_characters']} "
        "of the characters have clips). Lower is better.",
        "",
        "`dfd[E]`: the dfd fill with encoder `E`'s field distilled "
        f"({DISTILL}, 24 views at 224 px, no cache: `field s` is the distillation); `E-direct`: the encoder's "
        f"features evaluated at the points, no distillation; `+borrow`: the borrow prior (confidence {BORROW}). "
        "`dfd_default`: the pipeline's default since protocol 3's decision, no distilled field and the borrow "
        "prior with the skeleton-relative direct field only next to a chain nowhere known (`ambient_borrow`, "
        "`rigmix/weights/ambient.py`).",
        "",
        f"**Distilled encoders were run on {len(distilled)} of the {summary['characters']} characters** "
        f"({', '.join(distilled) or 'none'}); the direct variants and the baselines on all of them. Each rule "
        "row compares with `dfd_no_field` on the characters that row was measured on.",
        "",
        f"Mean over characters, and the decision rule (a field is a default only where it lowers the mean error "
        f"by at least {100 * RULE_REDUCTION:.0f}% against `dfd_no_field` and costs at most {RULE_SECONDS:.0f} s "
        "per character):",
        "",
        "| method | characters | mean error | mean of max error | skinned error % | vs dfd_no_field | "
        "field s (mean / max) | rule |",
        "|---|---:|---:|---:|---:|---:|---|---|",
    ]
    for m in labels:
        d = rule.get(m)
        n = d["characters"] if d else summary["characters"]
        vs = f"{-100 * d['relative_reduction']:+.1f}%" if d else "-"
        fs = f"{d['field_seconds_mean']:.2f} / {d['field_seconds_max']:.2f}" if d else "-"
        verdict = ("passes" if d["passes"] else "fails") if d else "-"
        lines.append(f"| {m} | {n} | {summary['mean_error'][m]:.3f} | {summary['mean_of_max_error'][m]:.2f} | "
                     f"{100 * summary['skinned_error'][m]:.2f} | {vs} | {fs} | {verdict} |")
    lines += ["", "Per character, mean / max weight error (cases: hidden welded vertices):", "",
              "| character | cases | " + " | ".join(labels) + " |",
              "|---|---|" + "---:|" * len(labels)]
    for name, r in results.items():
        if not r.get("methods"):
            continue
        cases = ", ".join(f"{k.replace('|', ' & ')} ({v})" for k, v in r["cases"].items())  # '|' splits a cell
        cells = " | ".join(
            f"{r['methods'][m]['mean_error']:.3f} / {r['methods'][m]['max_error']:.2f}" if m in r["methods"] else "-"
            for m in labels)
        lines.append(f"| {name} | {cases} | {cells} |")
    return "\n".join(lines) + "\n"


def write_protocol(results, protocol, *, stem=None, header=None):
    """Write ``benchmarks/results/<stem>.{json,md}`` for one protocol of :data:`PROTOCOL_FILES`
    (``stem``: default its band-fill file; ``header``: :func:`markdown_protocol`'s)."""
    summary = summarize_protocol(results)
    distilled = [n for n, r in results.items() if r.get("methods") and any(
        not k.endswith("-direct") for k in r.get("field_seconds", {}))]
    payload = {"protocol": {"name": protocol, "low": LOW, "high": HIGH, "max_influences": 4, "distill": DISTILL,
                            "encoders": list(FIELD_ENCODERS), "direct_encoders": list(DIRECT_ENCODERS),
                            "borrow": BORROW, "ambient": AMBIENT, "skin_frames": SKIN_FRAMES,
                            "skin_clips": SKIN_CLIPS, "distilled_on": distilled},
               "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
               "characters": results, "summary": summary}
    stem = stem or PROTOCOL_FILES[protocol]
    (RESULTS / f"{stem}.json").write_text(json.dumps(payload, indent=2) + "\n")
    (RESULTS / f"{stem}.md").write_text(markdown_protocol(results, summary, protocol, distilled, header=header))
    return payload


def protocol_characters():
    """Name -> path of every character issue 27's protocols run on: the shared characters, then
    the corpus (``tests/conftest.py``'s lists; the paths may be missing)."""
    from conftest import ASSETS, CHARACTERS, CORPUS, CORPUS_CHARACTERS

    return {**{n: ASSETS / p for n, p in CHARACTERS.items()}, **{n: CORPUS / p for n, p in CORPUS_CHARACTERS.items()}}


def stored_protocol_results(protocols, stem):
    """Protocol -> the per-character results stored in ``benchmarks/results/<stem(protocol)>.json``
    (empty where there is no file): what ``--update`` keeps."""
    results = {p: {} for p in protocols}
    for p in protocols:
        f = RESULTS / f"{stem(p)}.json"
        if f.exists():
            results[p] = json.loads(f.read_text())["characters"]
    return results


def main_protocols(argv, protocols=PROTOCOLS):
    """Issue 27's ``protocols`` over the shared characters and the corpus, each character's fields
    made once for all of them.

    ``argv``: ``[--direct-only] [--update] [CHARACTER ...]``. ``--direct-only`` skips the distilled
    encoders; ``--update`` keeps the characters already in the result files and replaces only those
    run now (a distilled pass over part of the characters after a direct pass over all).
    """
    every = protocol_characters()
    flags = {a for a in argv if a.startswith("--")}
    names = [a for a in argv if not a.startswith("--")] or list(every)
    encoders = () if "--direct-only" in flags else FIELD_ENCODERS
    results = (stored_protocol_results(protocols, PROTOCOL_FILES.get) if "--update" in flags
               else {p: {} for p in protocols})
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name in names:
        path = every[name]
        if not path.exists():
            print(f"band_fill: skipping {name}: {path} is missing", flush=True)
            continue
        t0 = time.perf_counter()
        for p, r in run_protocols(path, protocols=protocols, encoders=encoders).items():
            results[p][name] = r
            if r["methods"]:
                write_protocol(results[p], p)  # after every character: a long run leaves partial results
            means = {m: round(v["mean_error"], 3) for m, v in r["methods"].items()}
            print(f"band_fill {p}: {name} cases {r['cases']} {means} field s {r.get('field_seconds')}", flush=True)
        print(f"band_fill: {name} done in {time.perf_counter() - t0:.0f} s", flush=True)
    return results


def main(argv=None):
    from conftest import ASSETS, CHARACTERS

    argv = list(argv or [])
    if argv[:1] == ["--both-hidden"]:
        return main_protocols(argv[1:], ("both_hidden",))
    if argv[:1] == ["--similar-ambient"]:
        return main_protocols(argv[1:], ("similar", "ambient"))
    if argv[:1] == ["--protocols"]:
        return main_protocols(argv[1:])
    # argv None (``benchmarks.run`` calls main(), its own argv names benchmarks): every character
    names = argv or list(CHARACTERS)
    results = {}
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name in names:
        path = ASSETS / CHARACTERS[name]
        if not path.exists():
            print(f"band_fill: skipping {name}: {path} is missing", flush=True)
            continue
        results[name] = run_character(name, path)
        means = {m: round(v["mean_error"], 3) for m, v in results[name]["methods"].items()}
        print(f"band_fill: {name} {means}", flush=True)
        payload = write(results)  # after every character, so a long run leaves partial results
    print(markdown(results, summarize(results)))
    return payload


def write(results):
    summary = summarize(results)
    payload = {"protocol": {"low": LOW, "high": HIGH, "max_influences": 4, "distill": DISTILL},
               "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
               "characters": results, "summary": summary}
    (RESULTS / "band_fill.json").write_text(json.dumps(payload, indent=2) + "\n")
    (RESULTS / "band_fill.md").write_text(markdown(results, summary))
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
