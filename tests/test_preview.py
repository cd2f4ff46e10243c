"""`python -m envs.preview`: a task's frames above their masks, in the distraction setting asked."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from envs import preview

SIDE = 84 * 2 + 2  # a tile drawn at scale 2, with its gap


def _preview(tmp_path, name, *args):
    out = tmp_path / f"{name}.png"
    preview.main(["walker-walk", "--out", str(out), "--envs", "1", "--frames", "2", *args])
    image = cv2.imread(str(out))
    assert image.shape == (2 * SIDE + 2, 2 * SIDE + 2, 3)  # an RGB row above a mask row
    return image[: SIDE + 2], image[SIDE + 2 :]


def test_preview_draws_the_papers_background_only_setting_by_default(tmp_path):
    """--distraction medium with the default types changes the background only: the masks (the
    agent seen from the camera) are those of the undistracted env on the same episode starts;
    with all types the camera moves, and so do the masks."""
    plain_rgb, plain_mask = _preview(tmp_path, "none")
    rgb, mask = _preview(tmp_path, "background", "--distraction", "medium")
    np.testing.assert_array_equal(mask, plain_mask)
    assert not np.array_equal(rgb, plain_rgb)
    full_rgb, full_mask = _preview(
        tmp_path, "all", "--distraction", "medium", "--distraction-types", "all"
    )
    assert not np.array_equal(full_mask, plain_mask)
    # configs/paper.py's name of that setting, "medium-full", draws the same pictures.
    named_rgb, named_mask = _preview(tmp_path, "named", "--distraction", "medium-full")
    np.testing.assert_array_equal(named_rgb, full_rgb)
    np.testing.assert_array_equal(named_mask, full_mask)


def test_preview_refuses_an_unknown_distraction_type(tmp_path, capsys):
    with pytest.raises(SystemExit):
        preview.main(
            ["walker-walk", "--out", str(tmp_path / "x.png"), "--distraction-types", "fog"]
        )
    assert "unknown 'fog' in distraction types" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, message",
    [
        (["walker"], "unknown task 'walker'; valid tasks: ball_in_cup-catch"),
        (["walker-walk", "--mask", "fuzzy"], "unknown mask 'fuzzy'; valid: true, noisy"),
        (
            ["walker-walk", "--distraction", "extreme"],
            "unknown distraction 'extreme'; valid: none, easy, medium, hard, easy-full, "
            "medium-full, hard-full",
        ),
        # Checked before anything is drawn, where OpenCV would fail once the frames are ready.
        (["walker-walk", "--envs", "0"], "--envs must be >= 1, got 0"),
    ],
)
def test_preview_says_what_is_wrong_in_one_line(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exit_:
        preview.main([*args, "--out", str(tmp_path / "x.png")])
    assert exit_.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"python -m envs.preview: error: {message}")


def test_preview_refuses_an_image_name_opencv_cannot_write(tmp_path, capsys):
    with pytest.raises(SystemExit):
        preview.main(["walker-walk", "--out", str(tmp_path / "x.txt")])
    assert "OpenCV writes no image of that extension; give a .png" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_preview_draws_and_steps_as_a_run_of_the_task_does(tmp_path, monkeypatch):
    """The kitchen's preview takes the kitchen config's pictures ("fast", simplified arm meshes),
    CPU physics and action repeat; a DMC task's, configs/base.py's."""
    import envs

    made = {}

    def make(task, **kwargs):
        made[task] = kwargs
        raise ValueError("stop here")

    monkeypatch.setattr(envs, "make", make)
    for task in ("kitchen-kettle", "walker-walk"):
        with pytest.raises(SystemExit):
            preview.main([task, "--out", str(tmp_path / "x.png")])
    kettle, walker = made["kitchen-kettle"], made["walker-walk"]
    kettle_render = kettle["render"]
    assert (kettle_render.quality, kettle_render.mesh_faces) == ("fast", 1000)
    assert (kettle_render.num_slices, kettle_render.num_stacks) == (16, 4)
    assert (kettle["backend"], kettle["action_repeat"]) == ("cpu", 1)
    assert (walker["render"].quality, walker["render"].mesh_faces) == ("dm_control", 0)
    assert (walker["render"].num_slices, walker["render"].num_stacks) == (0, 0)
    assert (walker["backend"], walker["action_repeat"]) == ("cpu", 2)
