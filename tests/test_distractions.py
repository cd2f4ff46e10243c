"""Distractions: DAVIS loader, procedural videos, compositing, colour/camera/background state."""

import copy
import importlib.util
import json
import logging
import os
import pathlib

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from envs import distractions as D
from envs import render as R
from envs.labels import LABEL_AGENT, LABEL_BACKGROUND, LABEL_FLOOR, LABEL_OTHER

SUITE = pathlib.Path(importlib.util.find_spec("dm_control").origin).parent / "suite"


def walker():
    model = mujoco.MjModel.from_xml_path(str(SUITE / "walker.xml"))
    return model, list(range(1, model.ngeom)), [model.geom("floor").id]


def write_davis(root: pathlib.Path, videos: dict[str, list[int]], train, val):
    """A tiny DAVIS-2017 tree: each frame a flat colour (r, g, b) = (video, frame, 100)."""
    for name, (index, length) in videos.items():
        folder = root / "JPEGImages" / "480p" / name
        folder.mkdir(parents=True)
        for f in range(length):
            bgr = np.zeros((48, 64, 3), np.uint8)
            bgr[:] = (100, 20 * f, 40 * index)  # OpenCV writes BGR
            cv2.imwrite(str(folder / f"{f:05d}.jpg"), bgr)
    sets = root / "ImageSets" / "2017"
    sets.mkdir(parents=True)
    (sets / "train.txt").write_text("\n".join(train) + "\n")
    (sets / "val.txt").write_text("\n".join(val) + "\n")


@pytest.fixture
def davis(tmp_path):
    videos = {f"v{i}": (i, 3 + i) for i in range(6)}  # lengths 3..8
    # list order differs from name order: the loader must keep the list's order
    write_davis(tmp_path, videos, train=["v3", "v0", "v4", "v1", "v5"], val=["v2"])
    return tmp_path


def test_davis_loader_reads_first_n_of_the_split_list(davis):
    bgs = D.load_backgrounds(davis, "train", num_videos=4, size=84)
    assert bgs.dtype == np.uint8
    # longest of v3, v0, v4, v1 has 3 + 4 = 7 frames
    assert bgs.shape == (4, 7, 84, 84, 3)
    for slot, index in enumerate([3, 0, 4, 1]):
        frame0 = bgs[slot, 0].reshape(-1, 3).mean(0)
        np.testing.assert_allclose(frame0, [40 * index, 0, 100], atol=3)  # JPEG is lossy
        # frames in order, shorter videos continue back and forth (no jump cut)
        length = 3 + index
        want, pos, step = [], 0, 1
        for _ in range(7):
            want.append(pos)
            if not 0 <= pos + step < length:
                step = -step
            pos += step
        green = bgs[slot, :, 40, 40, 1].astype(int)
        np.testing.assert_allclose(green, [20 * f for f in want], atol=3)
    assert D.load_backgrounds(davis, "train", num_videos=None).shape[0] == 5
    # each video's own length, every frame read (no cap unless asked)
    padded, lengths = D.load_backgrounds(davis, "train", 4, with_lengths=True)
    np.testing.assert_array_equal(lengths, [6, 3, 7, 4])
    np.testing.assert_array_equal(padded, bgs)
    capped, lengths = D.load_backgrounds(davis, "train", 4, max_frames=5, with_lengths=True)
    assert capped.shape[1] == 5 and list(lengths) == [5, 3, 5, 4]
    val = D.load_backgrounds(davis, "val", num_videos=None)
    np.testing.assert_allclose(val[0, 0].reshape(-1, 3).mean(0), [80, 0, 100], atol=3)


def test_davis_loader_errors_name_the_layout(tmp_path, davis):
    with pytest.raises(FileNotFoundError, match=r"JPEGImages/480p.*ImageSets/2017/train\.txt"):
        D.load_backgrounds(tmp_path / "nowhere", "train", 4)
    with pytest.raises(ValueError, match="lists 5 videos"):
        D.load_backgrounds(davis, "train", 8)
    with pytest.raises(ValueError, match="valid"):
        D.load_backgrounds(davis, "test", 4)
    (davis / "ImageSets" / "2017" / "val.txt").write_text("v2\nmissing\n")
    with pytest.raises(FileNotFoundError, match="missing"):
        D.load_backgrounds(davis, "val", None)
    with pytest.raises(
        ValueError, match="^unknown distraction 'extreme'; valid: none, easy, medium, hard$"
    ):
        D.difficulty_videos("extreme")


def test_procedural_videos_are_announced_and_move(caplog):
    with caplog.at_level(logging.WARNING):
        train = D.load_backgrounds(None, "train", num_videos=4, max_frames=20)
    assert "procedurally generated" in caplog.text
    assert train.shape == (4, 20, 84, 84, 3) and train.dtype == np.uint8
    np.testing.assert_array_equal(train, D.load_backgrounds(None, "train", 4, max_frames=20))
    val = D.load_backgrounds(None, "val", 4, max_frames=20)
    assert not np.array_equal(train, val), "val videos differ from train videos"
    step = np.abs(np.diff(train.astype(int), axis=1)).mean()
    assert 0.5 < step < 30, "consecutive frames differ, smoothly"
    assert train.std() > 30, "textured, colourful frames"


ONE_TILE = R.RenderSettings(tiles_per_sheet=1)


def render_walker(qpos, perturb=None, settings=ONE_TILE):
    model, agent, floor = walker()
    tr = R.TileRenderer(
        copy.deepcopy(model),
        camera=0,
        agent_geom_ids=agent,
        floor_geom_ids=floor,
        settings=settings,
    )
    rgb = np.zeros((len(qpos), 84, 84, 3), np.uint8)
    labels = np.zeros((len(qpos), 84, 84), np.uint8)
    tr.render(qpos, rgb, labels, perturb=perturb)
    tr.close()
    return rgb, labels


@pytest.fixture(scope="module")
def walker_frames():
    model, _, _ = walker()
    rng = np.random.default_rng(0)
    qpos = np.tile(model.qpos0, (4, 1)) + rng.normal(0, 0.3, (4, model.nq))
    return qpos, *render_walker(qpos)


@pytest.mark.parametrize("alpha", [1.0, 0.3])
def test_background_distraction_changes_no_agent_pixel(walker_frames, alpha):
    _, rgb, labels = walker_frames
    bgs = D.load_backgrounds(None, "train", 2, max_frames=4)
    bg = bgs[np.array([0, 1, 0, 1]), np.array([0, 1, 2, 3])]
    out = np.asarray(jax.jit(D.composite, static_argnums=3)(rgb, labels, bg, alpha))
    assert out.dtype == np.uint8 and out.shape == rgb.shape
    keep = (labels == LABEL_AGENT) | (labels == LABEL_OTHER)
    np.testing.assert_array_equal(out[keep], rgb[keep])
    back = labels == LABEL_BACKGROUND
    np.testing.assert_array_equal(out[back], bg[back])
    fl = labels == LABEL_FLOOR
    want = np.round(alpha * rgb[fl].astype(np.float64) + (1 - alpha) * bg[fl]).astype(np.uint8)
    np.testing.assert_allclose(out[fl], want, atol=1)  # f32 vs f64 rounding at .5
    if alpha == 1.0:
        np.testing.assert_array_equal(out[fl], rgb[fl])
    assert (labels == LABEL_AGENT).any() and back.any() and fl.any()


def test_composite_vmaps_over_seeds_and_envs(walker_frames):
    _, rgb, labels = walker_frames
    bg = np.zeros_like(rgb)
    out = jax.vmap(jax.vmap(lambda r, lab, b: D.composite(r, lab, b, 0.3)))(
        jnp.asarray(rgb).reshape(2, 2, 84, 84, 3),
        jnp.asarray(labels).reshape(2, 2, 84, 84),
        jnp.asarray(bg).reshape(2, 2, 84, 84, 3),
    )
    np.testing.assert_array_equal(out.reshape(4, 84, 84, 3), D.composite(rgb, labels, bg, 0.3))


def make_distractor(difficulty, dynamic, batch=6, seed=0):
    model, _, _ = walker()
    return model, D.Distractor(
        model, 0, difficulty, dynamic=dynamic, batch=batch, num_videos=3, num_frames=10, seed=seed
    )


@pytest.mark.parametrize("difficulty", ["easy", "hard"])
def test_colour_ranges_and_static_mode(difficulty):
    model, dis = make_distractor(difficulty, dynamic=False)
    scale = D.DIFFICULTY_SCALE[difficulty]
    dis.reset()
    p0 = dis.perturb()
    base = model.mat_rgba[:, :3]
    mat = p0["mat_rgb"]
    assert mat.shape == (6, model.nmat, 3)
    assert (np.abs(mat - base) <= scale + 1e-6).all() and (mat >= 0).all() and (mat <= 1).all()
    assert np.abs(mat - base).max() > 0.5 * scale, "colours really move"
    r0, h0, v0, _ = dis.cam_default
    cam = p0["cam_sphere"]
    assert (cam[:, 0] >= r0 * (1 - 0.5 * scale) - 1e-9).all()
    assert (cam[:, 0] <= r0 * (1 + 1.5 * scale) + 1e-9).all()
    assert (np.abs(cam[:, 1] - h0) <= np.pi / 2 * scale + 1e-9).all()
    assert (np.abs(cam[:, 3]) <= np.pi / 2 * scale + 1e-9).all()
    assert (cam[:, 2] <= np.pi / 2 + 1e-9).all()
    video0, frame0 = dis.background_index()
    for _ in range(5):
        dis.step()
    p1 = dis.perturb()
    for key in p0:
        np.testing.assert_array_equal(p0[key], p1[key])  # static: nothing moves in an episode
    np.testing.assert_array_equal(dis.background_index()[1], frame0)
    # reset of some envs redraws those only
    which = np.array([True, False, True, False, False, False])
    dis.reset(which)
    p2 = dis.perturb()
    np.testing.assert_array_equal(p2["mat_rgb"][~which], mat[~which])
    assert (p2["mat_rgb"][which] != mat[which]).any()
    assert (dis.background_index()[0] < 3).all() and (dis.background_index()[1] < 10).all()


def test_saved_state_continues_the_same_draws():
    """What a checkpoint keeps (get_state, through json) makes another Distractor draw the same."""
    _, dis = make_distractor("hard", dynamic=True)
    dis.reset()
    dis.step()
    saved = json.loads(json.dumps(dis.get_state(), default=lambda a: a.tolist()))
    _, other = make_distractor("hard", dynamic=True, seed=99)
    other.set_state(saved)
    for d in (dis, other):
        d.step()
        d.reset(np.array([True, False] * 3))
        d.step()
    for key, value in dis.perturb().items():
        np.testing.assert_array_equal(value, other.perturb()[key])
    for a, b in zip(dis.background_index(), other.background_index(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_state_saved_with_another_batch_continues_the_draws_after_a_reset():
    """An evaluation env resumed with more episodes: the saved generator goes on, and the first
    full reset draws every env (the per-env arrays of another batch are not taken)."""
    _, one = make_distractor("hard", dynamic=False, batch=1)
    one.reset()
    _, three = make_distractor("hard", dynamic=False, batch=3, seed=99)
    three.set_state(one.get_state())
    assert three.video.shape == (3,)
    expected = np.random.default_rng()
    expected.bit_generator.state = one.rng.bit_generator.state
    three.reset()
    assert three.rng.bit_generator.state != one.rng.bit_generator.state  # it drew from it
    _, fresh = make_distractor("hard", dynamic=False, batch=3, seed=7)
    fresh.rng = expected
    fresh.reset()
    for key, value in fresh.perturb().items():
        np.testing.assert_array_equal(value, three.perturb()[key])
    for a, b in zip(fresh.background_index(), three.background_index(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_dynamic_mode_moves_within_ranges():
    model, dis = make_distractor("hard", dynamic=True)
    dis.reset()
    first = dis.perturb()
    frames = [dis.background_index()[1]]
    for _ in range(30):
        dis.step()
        frames.append(dis.background_index()[1])
        mat = dis.perturb()["mat_rgb"]
        assert (mat >= dis.mat_range.lo - 1e-6).all() and (mat <= dis.mat_range.hi + 1e-6).all()
        cam = dis.perturb()["cam_sphere"]
        assert (cam >= dis.cam_lo - 1e-9).all() and (cam <= dis.cam_hi + 1e-9).all()
    last = dis.perturb()
    assert (np.abs(last["mat_rgb"] - first["mat_rgb"]) > 0).mean() > 0.5
    assert (last["cam_sphere"] != first["cam_sphere"]).any()
    frames = np.stack(frames)
    steps = np.abs(np.diff(frames, axis=0))
    assert (steps <= 1).all() and (frames >= 0).all() and (frames < 10).all()
    assert (steps == 1).mean() > 0.8, "one frame per step, bouncing at the ends"


def test_background_frames_are_drawn_and_played_within_each_videos_own_length():
    """Videos padded to the longest: a static episode shows a frame drawn uniformly from its
    video's own frames (never the padding), and dynamic mode bounces at the video's own end."""
    model, _, _ = walker()
    static = D.Distractor(
        model, 0, "medium", batch=4000, num_videos=2, num_frames=10, lengths=[2, 10], seed=1
    )
    static.reset()
    video, frame = static.background_index()
    short, long = frame[video == 0], frame[video == 1]
    assert set(short) == {0, 1} and abs(short.mean() - 0.5) < 0.05
    assert set(long) == set(range(10)) and abs(long.mean() - 4.5) < 0.3
    playing = D.Distractor(
        model, 0, "medium", dynamic=True, batch=64, num_videos=2, num_frames=10,
        lengths=[3, 10], seed=2,
    )  # fmt: skip
    playing.reset()
    video = playing.background_index()[0]
    frames = []
    for _ in range(25):
        playing.step()
        frames.append(playing.background_index()[1])
    frames = np.stack(frames)
    assert frames[:, video == 0].max() == 2 and frames[:, video == 1].max() == 9
    assert (np.abs(np.diff(frames, axis=0)) == 1).all()
    with pytest.raises(ValueError, match=r"lengths must be 2 counts in \[1, 10\]"):
        D.Distractor(model, 0, "medium", batch=1, num_videos=2, num_frames=10, lengths=[3, 11])


def test_colour_and_camera_perturbation_on_rendered_frames(walker_frames):
    """Colour: same labels bit for bit, agent pixels recoloured. Camera: the agent moves in the
    picture, but each perturbed frame still shows it and keeps its pixel count within the zoom
    range's bounds (area ~ 1/r^2: r in [0.5, 1.45] of the default for hard)."""
    qpos, rgb, labels = walker_frames
    _, dis = make_distractor("hard", dynamic=False, batch=4, seed=3)
    dis.reset()
    p = dis.perturb()
    rgb_c, labels_c = render_walker(qpos, perturb={"mat_rgb": p["mat_rgb"]})
    np.testing.assert_array_equal(labels_c, labels)
    agent = labels == LABEL_AGENT
    assert (rgb_c != rgb).any(-1)[agent].mean() > 0.9
    _, labels_cam = render_walker(qpos, perturb={k: p[k] for k in ("cam_sphere", "cam_lookat")})
    moved = (labels_cam == LABEL_AGENT) != agent
    assert moved.any(axis=(1, 2)).all(), "a different view in every env"
    area = (labels_cam == LABEL_AGENT).sum(axis=(1, 2)) / agent.sum(axis=(1, 2))
    r_ratio = p["cam_sphere"][:, 0] / dis.cam_default[0]
    assert (area > 0).all()
    assert (area < 2.0 / r_ratio**2).all() and (area > 0.3 / r_ratio**2).all(), (area, r_ratio)


def test_distraction_types_pick_what_an_env_perturbs(caplog):
    """env distraction_types: background only (the paper's setting) composites videos and
    leaves the agent's colours and the camera alone; colour + camera perturb without videos; the
    spec says which, and where the videos come from. The agent's pixels of the background-only
    env equal the undistracted env's on the same episode starts."""
    import envs

    def make(**kwargs):
        settings = envs.RenderSettings(num_workers=1, quality="fast")
        return envs.make(
            "walker-walk",
            num_seeds=1,
            envs_per_seed=2,
            backend="cpu",
            render=settings,
            seed=5,
            **kwargs,
        )

    frames = {}
    for name, kwargs in {
        "plain": {},
        "background": {"distraction": "medium", "distraction_types": "background"},
        "color,camera": {"distraction": "medium", "distraction_types": ("camera", "color")},
    }.items():
        env = make(**kwargs)
        try:
            _, ts = env.reset(jax.random.key(0))
            frames[name] = (np.asarray(ts.frame), np.asarray(ts.true_mask), env)
            perturbed = set(env._distractor.perturb())
        finally:
            env.close()
        if name == "background":
            assert env.spec.distraction_types == ("background",)
            assert env.spec.backgrounds == "built-in procedural videos"
            assert perturbed == set()
        elif name == "color,camera":
            assert env.spec.distraction_types == ("color", "camera")
            assert env.spec.backgrounds == "none"
            assert {"mat_rgb", "cam_sphere"} <= perturbed
        else:
            assert env.spec.distraction_types == () and env.spec.backgrounds == "none"
    plain, plain_mask, _ = frames["plain"]
    background, mask, _ = frames["background"]
    np.testing.assert_array_equal(mask, plain_mask)
    agent = mask.astype(bool)
    assert agent.any()
    np.testing.assert_array_equal(background[agent], plain[agent])
    assert (background[~agent] != plain[~agent]).any(-1).mean() > 0.5
    with pytest.raises(ValueError, match="'sky'.*one or more of background, color, camera"):
        D.parse_types("background,sky")
    with pytest.raises(ValueError, match="each once"):
        D.parse_types("color,color")
    assert D.parse_types("all") == D.DISTRACTION_TYPES


def test_background_dir_is_checked_only_where_backgrounds_are_shown(davis, tmp_path):
    from ml_collections import ConfigDict

    def env(folder, types="all", distraction="medium"):
        return ConfigDict(
            {"background_dir": str(folder), "distraction": distraction, "distraction_types": types}
        )

    D.check_background_dir(env(davis, distraction="hard"))  # the layout of DAVIS-2017
    # "medium" draws 8 videos of each split: these lists hold 5 and 1
    with pytest.raises(ValueError, match="'medium' draws 8 videos, but train.txt lists 5"):
        D.check_background_dir(env(davis))
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="ImageSets/2017/train.txt is missing"):
        D.check_background_dir(env(tmp_path / "empty"))
    frames = davis / "JPEGImages" / "480p" / "v1"
    for f in frames.iterdir():
        f.rename(davis / f"v1_{f.name}")
    with pytest.raises(FileNotFoundError, match="v1 holds no frames"):
        D.check_background_dir(env(davis, distraction="hard"))
    (davis / "JPEGImages" / "480p" / "v3").rename(davis / "moved")
    with pytest.raises(FileNotFoundError, match="video folder .*v3 is missing"):
        D.check_background_dir(env(davis, distraction="hard"))
    D.check_background_dir(env(tmp_path / "nope", types="color,camera"))  # no videos shown
    D.check_background_dir(env(tmp_path / "nope", distraction="none"))
