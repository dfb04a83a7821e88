"""The junction stretch ratio (:func:`rigmix.quality.junction_stretch_ratio`) compares the seam
with each part it joins: the Wasp's rigid wings attached to the Witch, who has no clip of her own
and moves only as completion animates her with the Wasp's clips."""

from __future__ import annotations

import pytest
from conftest import asset, corpus


@pytest.fixture(scope="module")
def witch_wings(tmp_path_factory):
    from rigmix.pipeline import compose

    cfg = tmp_path_factory.mktemp("wings") / "wings.toml"
    text = (f'[characters.body]\npath = "{corpus("Witch").as_posix()}"\n'
            f'[characters.donor]\npath = "{asset("Wasp").as_posix()}"\nscale = "auto"\n')
    for side in ("L", "R"):
        text += (f'[[actions]]\nop = "attach"\nsource = "donor"\nsource_joint = "Wing.{side}"\n'
                 'target = "body"\ntarget_joint = "Chest"\n')
    cfg.write_text(text)
    return compose(cfg)


def test_a_clip_less_input_is_measured_under_the_clips_it_gets(witch_wings):
    comp = witch_wings
    assert not comp.inputs["body"].clips and comp.inputs["donor"].clips
    q = comp.report["quality"]
    figures = q["source_p95_by_input"]
    assert set(figures) == {"body", "donor"}
    assert all(v > 0 for v in figures.values())


def test_the_ratio_is_over_the_most_supple_part(witch_wings):
    q = witch_wings.report["quality"]
    figures = q["source_p95_by_input"]
    # the wing is rigid: pooled by vertex count, it would make the body's own motion look like a seam
    assert figures["donor"] < figures["body"]
    assert q["source_p95"] == max(figures.values())
    assert q["junction_stretch_ratio"] == pytest.approx(q["output_p95"] / q["source_p95"])
    assert q["junction_stretch_ratio"] <= 1.5
