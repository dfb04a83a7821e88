"""Rig operators that several stages and file formats share: parents-first order, unique names,
left/right side swap.

Both are written once here, beside no stage in particular: the glTF reader orders the joints
of a skin and the operations order the output skeleton with :func:`topological_order`
(:mod:`rigmix.character`'s convention ``parents[j] < j``); the glTF reader, the operations, the
USD writer and the clip completion make names unique with :func:`unique_names`, each with the
suffix its format allows; the mirror operation and the weights' joint mirror pair left and
right joints with :func:`swap_side`.
"""

from __future__ import annotations

import heapq
import re
from collections.abc import Callable, Hashable, Iterable, Sequence

__all__ = ["topological_order", "unique_names", "swap_side"]


def topological_order(nodes: Iterable[int], parent: Callable[[int], int],
                      key: Callable[[int], Hashable]) -> list[int]:
    """Parents-first order of a forest, choosing among the ready nodes by a preference key.

    A node is ready once its parent is placed (a root at once); the ready node with the smallest
    ``(key(node), node)`` comes next. Among the valid orders this keeps the one the keys prefer,
    and it is deterministic for any keys (ties fall back to the node ids).

    Parameters
    ----------
    nodes : iterable of int
        The forest's nodes (each once).
    parent : callable
        ``parent(node)``: the parent's node id, negative for a root.
    key : callable
        ``key(node)``: a comparable preference, smaller first.

    Returns
    -------
    list of int
        The nodes reachable from a root, parents first (a node on a cycle is left out).
    """
    kids: dict[int, list[int]] = {}
    heap = []
    for n in nodes:
        p = parent(n)
        if p < 0:
            heap.append((key(n), n))
        else:
            kids.setdefault(p, []).append(n)
    heapq.heapify(heap)
    order = []
    while heap:
        _, n = heapq.heappop(heap)
        order.append(n)
        for c in kids.get(n, []):
            heapq.heappush(heap, (key(c), c))
    return order


def unique_names(names: Sequence[str], *, suffix: str = ".{:03d}", start: int = 1, taken: Iterable[str] = (),
                 priority: Sequence | None = None) -> list[str]:
    """Unique names: the first of equal names keeps it, the later ones get a numbered suffix.

    The rule, for joints, materials, clips and USD identifiers alike: in ``priority`` order
    (list order by default; ties in list order), a name not used yet is kept; a name already
    used (by an earlier name, generated or given, or in ``taken``) gets
    ``name + suffix.format(k)`` for the smallest ``k >= start`` whose result is not used yet.
    Only the names before it count: with ``suffix="_{}", start=2``, ``["a", "a", "a_2"]``
    gives ``["a", "a_2", "a_2_2"]``.

    Parameters
    ----------
    names : sequence of str
    suffix : str
        Format of the suffix for the number ``k``: ``".{:03d}"`` (``Hand.001``, Blender's
        rule, for output joints), ``".{}"`` (glTF joints on load), ``"_{}"`` (USD identifiers,
        which cannot hold a dot, and clip names).
    start : int
        First number tried.
    taken : iterable of str
        Names already in use elsewhere (e.g. sibling prims): a name in it is renamed.
    priority : sequence, optional
        One comparable per name; smaller keeps its name first.

    Returns
    -------
    list of str
        Same length and order as ``names``.
    """
    used = set(taken)
    out = list(names)
    next_k: dict[str, int] = {}  # numbers below it are used for good: linear in len(names)
    order = range(len(out)) if priority is None else sorted(range(len(out)), key=lambda o: (priority[o], o))
    for o in order:
        name = out[o]
        if name in used:
            k = next_k.get(name, start)
            new = name + suffix.format(k)
            while new in used:
                k += 1
                new = name + suffix.format(k)
            next_k[name] = k + 1
            out[o] = new
        used.add(out[o])
    return out


# Side tokens: a single letter L/R (either case) between separators or at either end of the name
# (".L", "_L", "_L_", "L_", "-l", "leg_L1"), and the words Left/Right (any of three cases, not
# inside a lower-case word: "upright" is not a side).
_SIDE = re.compile(
    r"(?<![A-Za-z0-9])[LlRr](?![A-Za-z])"             # .L, _R, _L_, L_Hand, leg_L1, arm_joint_L__4_
    r"|(?<![a-z])(?:Left|Right|LEFT|RIGHT)"           # b_LeftUpperArm_09, mixamorig:RightHand
    r"|(?<![A-Za-z])(?:left|right)"                   # hand_left (not upright)
)
_SWAP = {"L": "R", "R": "L", "l": "r", "r": "l", "Left": "Right", "Right": "Left", "LEFT": "RIGHT",
         "RIGHT": "LEFT", "left": "right", "right": "left"}


def swap_side(name: str) -> str:
    """``name`` with every side token swapped (``.L`` <-> ``.R``, ``Left`` <-> ``Right``, ...).

    Tokens: a single ``L``/``R``/``l``/``r`` with no letter or digit before it and no letter after
    it (``UpperArm.L``, ``arm_joint_L__4_``, ``L_Hand``, ``leg_L1``),
    and ``Left``/``Right``/``LEFT``/``RIGHT``/``left``/``right`` not inside a word
    (``b_LeftUpperArm_09``, ``mixamorig:RightHand``, ``hand_left``; not ``upright``). Every token
    is swapped at once, so ``swap_side(swap_side(n)) == n``. A name without a token is returned
    unchanged.
    """
    return _SIDE.sub(lambda m: _SWAP[m.group(0)], name)
