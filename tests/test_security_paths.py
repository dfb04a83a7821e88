"""Messages name an input file by its name, never by the folders it lives in (issue 23).

A character is read from a deep absolute folder; each message that names it (an unknown joint of
an action, a missing clip when writing USD or rendering, a character without skin) must carry its
file name and none of its folders. The reference is ``Character.label``.
"""

from __future__ import annotations

import shutil

import pytest
from conftest import asset

from rigmix.errors import RigmixError

SECRET = "private_folder_do_not_print"


@pytest.fixture()
def hidden_fox(tmp_path):
    """(folder, path) of the Fox copied under ``tmp_path/SECRET/assets``."""
    folder = tmp_path / SECRET / "assets"
    folder.mkdir(parents=True)
    path = folder / "Fox.glb"
    shutil.copyfile(asset("Fox"), path)
    return folder, path


def _assert_names_file_only(message: str, folder) -> None:
    assert "Fox.glb" in message, message
    assert SECRET not in message and str(folder) not in message, message


def test_unknown_joint_names_the_file_not_its_folder(hidden_fox, tmp_path, capsys):
    from rigmix.cli import main

    folder, path = hidden_fox
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[characters.body]\npath = "{path}"\n[characters.donor]\npath = "{path}"\n'
                   '[[actions]]\nop = "replace"\nsource = "donor"\nsource_joint = "NoSuchJoint"\n'
                   'target = "body"\ntarget_joint = "b_LeftUpperArm_09"\n')
    capsys.readouterr()
    assert main(["compose", str(cfg), "-o", str(tmp_path / "out.glb"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "no joint 'NoSuchJoint' in character 'donor' (Fox.glb)" in err, err
    _assert_names_file_only(err, folder)


def test_missing_clip_in_render_names_the_file_not_its_folder(hidden_fox):
    from rigmix.io import load_character
    from rigmix.preview.render import pose_scene

    folder, path = hidden_fox
    with pytest.raises(RigmixError, match="has no clip 'nope'") as exc:
        pose_scene(load_character(path), clip="nope")
    _assert_names_file_only(str(exc.value), folder)


def test_missing_clip_in_usd_names_the_file_not_its_folder(hidden_fox, tmp_path):
    pytest.importorskip("pxr")
    from rigmix.io import load_character
    from rigmix.io.usd import write_usd

    folder, path = hidden_fox
    with pytest.raises(RigmixError, match="has no clip 'nope'") as exc:
        write_usd(load_character(path), tmp_path / "out.usda", clips=["nope"])
    _assert_names_file_only(str(exc.value), folder)


def test_unskinned_character_names_the_file_not_its_folder(hidden_fox):
    from dataclasses import replace

    from rigmix.io import load_character

    folder, path = hidden_fox
    fox = load_character(path)
    static = replace(fox, meshes=tuple(replace(m, joints=None, weights=None) for m in fox.meshes))
    with pytest.raises(RigmixError, match="has no skinned mesh") as exc:
        static.require_skinned()
    _assert_names_file_only(str(exc.value), folder)
