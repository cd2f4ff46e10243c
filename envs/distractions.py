"""Distracting Control Suite: background videos, colour and camera perturbations (docs/method.md).

This file owns
- the difficulty table (easy / medium / hard: scale 0.1 / 0.2 / 0.3, videos 4 / 8 / all),
- background videos: a user's DAVIS-2017 folder (`load_backgrounds`), or built-in procedurally
  generated moving videos when none is given (announced with a logged warning),
- `Distractor`: host-side (numpy) per-env distraction state for a batch of envs, sampled per
  episode and, in dynamic mode, moved every step with the Distracting Control Suite's rules.
  Its `perturb()` feeds `RenderPool.render(perturb=...)` (colours and camera are applied in the
  render workers) and its `background_index()` picks each env's background frame,
- `composite`: the background frame drawn wherever the labels say BACKGROUND and blended into
  FLOOR pixels by (1 - floor_alpha), in jnp on the accelerator.

How the Env uses it, per batch of B = S*E envs:
    bgs, lengths = load_backgrounds(dir, split, difficulty_videos(d), with_lengths=True)
    bgs = jnp.asarray(bgs)                                    # [N,T,84,84,3], videos padded to T
    dis = Distractor(render_model, camera, d, dynamic, batch=B, num_videos=N, num_frames=T,
                     lengths=lengths, seed)
    reset: dis.reset(first)  (bool [B], the envs starting an episode);  step: dis.step()
    rgb, labels = pool.render(qpos, perturb=dis.perturb())
    video, frame = dis.background_index()
    frames = composite(rgb, labels, bgs[video, frame], floor_alpha)

Meaning of the perturbations (read from the Distracting Control Suite's code):
- colour: every material's RGB (and the RGB of any geom drawn without a material) is redrawn
  per episode uniformly within +-scale of the original, clipped to [0, 1]; alpha is kept.
  Dynamic: each step adds N(0, (0.03 scale)^2) per channel, clipped to that range.
- camera: the camera position in spherical coordinates (radius, horizontal angle, vertical angle
  from +z) around the agent's centre of mass (tracking cameras) or the world origin (fixed
  cameras); per episode each angle is drawn within +-(pi/2) scale of the default, the radius
  within [r (1 - 0.5 scale), r (1 + 1.5 scale)] (zoom in / out), and a roll about the viewing
  axis within +-(pi/2) scale. The camera then looks at the point on its default viewing axis at
  the agent's distance (fixed cameras: that point at the default state). The vertical angle is
  kept in [0, pi/2] and the horizontal one in [-pi, 0] (the upper front quadrant, as the
  suite does for these domains). Dynamic: the position moves with a velocity that random-walks
  (std 0.1 scale, speed at most 0.4 scale, scaled by r/4) and the roll with an angular velocity
  (std pi/300 scale, at most pi/50 scale), clipped to the ranges above.
- background: per episode a random video of the first N of the split's list; static: one random
  frame of it for the whole episode; dynamic: a random start frame and direction, one frame per
  step, bouncing at the ends.
"""

from __future__ import annotations

import dataclasses
import logging
import pathlib

import jax.numpy as jnp
import mujoco
import numpy as np

from envs.camera import cart_to_sphere, kinematics, lookat_point, sphere_to_cart
from envs.labels import LABEL_BACKGROUND, LABEL_FLOOR

log = logging.getLogger(__name__)

DIFFICULTIES = ("none", "easy", "medium", "hard")
# The kinds of distraction, any subset: the paper's setting is background only (docs/method.md);
# all three are the full Distracting Control Suite.
DISTRACTION_TYPES = ("background", "color", "camera")
DIFFICULTY_SCALE = {"none": 0.0, "easy": 0.1, "medium": 0.2, "hard": 0.3}
DIFFICULTY_VIDEOS = {"none": 0, "easy": 4, "medium": 8, "hard": None}  # None: every video
SPLITS = ("train", "val")
PROCEDURAL_VIDEOS = {"train": 60, "val": 30}  # as many as DAVIS-2017's train / val lists
PROCEDURAL_FRAMES = 60  # frames of a built-in video
DAVIS_LAYOUT = (
    "DAVIS-2017 root with JPEGImages/480p/<video>/<frame>.jpg and ImageSets/2017/train.txt, "
    "ImageSets/2017/val.txt (one video name per line)"
)


def check_difficulty(difficulty: str) -> None:
    if difficulty not in DIFFICULTIES:
        raise ValueError(f"unknown distraction {difficulty!r}; valid: {', '.join(DIFFICULTIES)}")


def parse_types(types: str | tuple | list) -> tuple[str, ...]:
    """Distraction types from "background,color" (or a sequence), in DISTRACTION_TYPES' order;
    "all" is every type. Refused: an unknown or repeated type, or none."""
    names = [t.strip() for t in types.split(",")] if isinstance(types, str) else list(types)
    if names == ["all"]:
        return DISTRACTION_TYPES
    unknown = [t for t in names if t not in DISTRACTION_TYPES]
    if unknown or not names or len(set(names)) != len(names):
        what = f"unknown {', '.join(map(repr, unknown))} in" if unknown else "bad"
        raise ValueError(
            f"{what} distraction types {types!r}: give one or more of "
            f"{', '.join(DISTRACTION_TYPES)} separated by commas, each once, or 'all'"
        )
    return tuple(t for t in DISTRACTION_TYPES if t in names)


def check_background_dir(env) -> None:
    """An env config's background_dir (when its distraction shows backgrounds) holds DAVIS-2017's
    layout: the train and val lists, each with the videos its difficulty draws, and their
    folders with frames (none is read)."""
    if not env.background_dir or env.distraction == "none":
        return
    if "background" not in parse_types(env.distraction_types):
        return
    wanted = difficulty_videos(env.distraction)
    for split in SPLITS:
        names = davis_video_names(env.background_dir, split)
        if wanted is not None and wanted > len(names):
            raise ValueError(
                f"distraction {env.distraction!r} draws {wanted} videos, but {split}.txt lists "
                f"{len(names)}"
            )
        for name in names[:wanted]:
            folder = pathlib.Path(env.background_dir) / "JPEGImages" / "480p" / name
            if not folder.is_dir():
                raise FileNotFoundError(
                    f"video folder {folder} is missing; expected a {DAVIS_LAYOUT}"
                )
            if not any(p.suffix.lower() in (".jpg", ".jpeg", ".png") for p in folder.iterdir()):
                raise FileNotFoundError(f"{folder} holds no frames; expected a {DAVIS_LAYOUT}")


def difficulty_videos(difficulty: str) -> int | None:
    check_difficulty(difficulty)
    return DIFFICULTY_VIDEOS[difficulty]


# ---------------------------------------------------------------------------------------------
# Background videos.


def davis_video_names(background_dir: str | pathlib.Path, split: str) -> list[str]:
    """Names listed in ImageSets/2017/<split>.txt, in the list's order."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {SPLITS}")
    root = pathlib.Path(background_dir)
    if not root.is_dir():
        raise FileNotFoundError(
            f"background_dir {str(root)!r} does not exist; expected a {DAVIS_LAYOUT}"
        )
    listing = root / "ImageSets" / "2017" / f"{split}.txt"
    if not listing.is_file():
        raise FileNotFoundError(f"{listing} is missing; expected a {DAVIS_LAYOUT}")
    names = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
    if not names:
        raise ValueError(f"{listing} lists no videos")
    return names


def _read_video(folder: pathlib.Path, size: int, max_frames: int | None) -> np.ndarray:
    import cv2

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not files:
        raise FileNotFoundError(f"{folder} holds no .jpg frames; expected a {DAVIS_LAYOUT}")
    frames = []
    for path in files[:max_frames]:
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"cannot decode {path}")
        small = cv2.resize(bgr, (size, size), interpolation=cv2.INTER_AREA)
        frames.append(cv2.cvtColor(small, cv2.COLOR_BGR2RGB))
    return np.stack(frames)


def _bounce_to_length(video: np.ndarray, length: int) -> np.ndarray:
    """Pads a [T,...] video to `length` frames by playing it back and forth (no jump cut)."""
    if len(video) >= length:
        return video[:length]
    period = max(2 * len(video) - 2, 1)
    idx = np.arange(length) % period
    idx = np.where(idx < len(video), idx, period - idx)
    return video[idx]


def load_backgrounds(
    background_dir: str | pathlib.Path | None,
    split: str,
    num_videos: int | None,
    size: int = 84,
    max_frames: int | None = None,
    seed: int = 0,
    with_lengths: bool = False,
):
    """-> uint8 [N, T, size, size, 3]: the first `num_videos` videos of the split (None = all),
    each of its own frames up to `max_frames` (None: all, as the Distracting Control Suite).

    Videos of different lengths are padded to the longest by playing them back and forth;
    `with_lengths` also returns each video's own length (int [N]: `Distractor` draws frames
    within it). background_dir None -> procedurally generated videos (logged), 60 frames each.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {SPLITS}")
    if background_dir is None:
        n = PROCEDURAL_VIDEOS[split] if num_videos is None else num_videos
        log.warning(
            "No background_dir given: using %d built-in procedurally generated background videos "
            "(%s split), not DAVIS-2017. Pass background_dir=<DAVIS root> for the benchmark's "
            "videos.",
            n,
            split,
        )
        frames = min(max_frames or PROCEDURAL_FRAMES, PROCEDURAL_FRAMES)
        videos = procedural_videos(
            n, frames, size, seed=seed + (0 if split == "train" else 1_000_003)
        )
        return (videos, np.full(n, frames)) if with_lengths else videos
    names = davis_video_names(background_dir, split)
    if num_videos is not None:
        if not 0 < num_videos <= len(names):
            raise ValueError(f"num_videos={num_videos}, but {split}.txt lists {len(names)} videos")
        names = names[:num_videos]
    root = pathlib.Path(background_dir) / "JPEGImages" / "480p"
    videos = []
    for name in names:
        folder = root / name
        if not folder.is_dir():
            raise FileNotFoundError(f"video folder {folder} is missing; expected a {DAVIS_LAYOUT}")
        videos.append(_read_video(folder, size, max_frames))
    lengths = np.array([len(v) for v in videos])
    padded = np.stack([_bounce_to_length(v, lengths.max()) for v in videos])
    return (padded, lengths) if with_lengths else padded


def procedural_videos(
    num_videos: int, num_frames: int, size: int = 84, seed: int = 0
) -> np.ndarray:
    """uint8 [N, T, size, size, 3]: textured, coloured, moving scenes (a stand-in for DAVIS).

    Each video: a drifting two-colour sinusoidal plaid (the "scene") with a few soft coloured
    blobs moving along smooth random paths (the "objects"), so both texture and motion vary.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    t = np.arange(num_frames, dtype=np.float32)[:, None, None]
    out = np.empty((num_videos, num_frames, size, size, 3), np.uint8)
    for v in range(num_videos):
        c1, c2 = rng.uniform(0, 1, (2, 3)).astype(np.float32)
        f = rng.uniform(2, 8, 2)
        angle = rng.uniform(0, np.pi, 2)
        speed = rng.uniform(0.02, 0.1, 2)
        waves = 0.0
        for k in range(2):
            phase = (np.cos(angle[k]) * xx + np.sin(angle[k]) * yy) * f[k] * 2 * np.pi
            waves = waves + np.sin(phase[None] + speed[k] * 2 * np.pi * t)
        mix = (0.5 + 0.25 * waves)[..., None]  # [T, H, W, 1] in [0, 1]
        img = mix * c1 + (1 - mix) * c2
        for _ in range(rng.integers(2, 5)):
            colour = rng.uniform(0, 1, 3).astype(np.float32)
            radius = rng.uniform(0.08, 0.25)
            centre0, amp = rng.uniform(0.2, 0.8, 2), rng.uniform(0.1, 0.35, 2)
            freq, ph = rng.uniform(0.01, 0.05, 2), rng.uniform(0, 2 * np.pi, 2)
            cx = centre0[0] + amp[0] * np.sin(2 * np.pi * freq[0] * t + ph[0])
            cy = centre0[1] + amp[1] * np.sin(2 * np.pi * freq[1] * t + ph[1])
            d2 = (xx[None] - cx) ** 2 + (yy[None] - cy) ** 2
            alpha = np.clip(1.5 - np.sqrt(d2) / radius, 0, 1)[..., None]
            img = alpha * colour + (1 - alpha) * img
        out[v] = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    return out


# ---------------------------------------------------------------------------------------------
# Compositing (accelerator).


def composite(
    rgb: jnp.ndarray, labels: jnp.ndarray, background: jnp.ndarray, floor_alpha: float
) -> jnp.ndarray:
    """rgb uint8 [...,H,W,3], labels uint8 [...,H,W], background uint8 [...,H,W,3] -> uint8.

    Background pixels become the video frame; floor pixels become alpha*floor + (1-alpha)*video
    (rounded); agent and other pixels are untouched.
    """
    lab = labels[..., None]
    f = rgb.astype(jnp.float32)
    blend = f * floor_alpha + background.astype(jnp.float32) * (1.0 - floor_alpha)
    floor = jnp.clip(jnp.round(blend), 0, 255).astype(jnp.uint8)
    out = jnp.where(lab == LABEL_FLOOR, floor, rgb)
    return jnp.where(lab == LABEL_BACKGROUND, background.astype(jnp.uint8), out)


# ---------------------------------------------------------------------------------------------
# Per-env perturbation state (host side).


@dataclasses.dataclass
class _Ranges:
    lo: np.ndarray
    hi: np.ndarray


class Distractor:
    """Distraction state of a batch of B envs: colours, camera pose, background frame.

    model: the render model (its default colours and camera); camera: id or name.
    num_videos / num_frames: the shape of the loaded backgrounds (0 videos: no background);
    lengths: each video's own frames (int [num_videos]; None: all num_frames), within which its
    frames are drawn (uniformly at an episode's start) and, in dynamic mode, played.
    color / camera_motion / background switch the three kinds on or off (all on by default).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        camera: int | str,
        difficulty: str,
        *,
        dynamic: bool = False,
        batch: int,
        num_videos: int,
        num_frames: int,
        lengths: np.ndarray | None = None,
        seed: int = 0,
        color: bool = True,
        camera_motion: bool = True,
        background: bool = True,
    ):
        check_difficulty(difficulty)
        self.scale = DIFFICULTY_SCALE[difficulty]
        self.dynamic = dynamic
        self.batch = batch
        self.num_videos = num_videos if background else 0
        self.num_frames = num_frames
        self.lengths = np.full(num_videos, num_frames) if lengths is None else np.asarray(lengths)
        if self.lengths.shape != (num_videos,) or not np.all(
            (self.lengths >= 1) & (self.lengths <= num_frames)
        ):
            raise ValueError(
                f"lengths must be {num_videos} counts in [1, {num_frames}], got {lengths}"
            )
        self.rng = np.random.default_rng(seed)
        self.use_color = color and self.scale > 0
        self.use_camera = camera_motion and self.scale > 0
        s = self.scale

        # Colours.
        self.no_material = model.geom_matid < 0
        mat0 = model.mat_rgba[:, :3].astype(np.float64)
        geom0 = model.geom_rgba[:, :3].astype(np.float64)
        self.mat_range = _Ranges(np.clip(mat0 - s, 0, 1), np.clip(mat0 + s, 0, 1))
        self.geom_range = _Ranges(np.clip(geom0 - s, 0, 1), np.clip(geom0 + s, 0, 1))
        self.mat_rgb = np.broadcast_to(mat0, (batch, *mat0.shape)).copy()
        self.geom_rgb = np.broadcast_to(geom0, (batch, *geom0.shape)).copy()
        self.color_step_std = 0.03 * s if dynamic else 0.0

        # Camera: the default pose at the model's reference state.
        cam_id = camera if isinstance(camera, int) else model.camera(camera).id
        data = mujoco.MjData(model)
        kinematics(model, data)
        com = data.subtree_com[1].copy()
        self.tracking = model.cam_mode[cam_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED
        start = data.cam_xpos[cam_id] - com if self.tracking else data.cam_xpos[cam_id].copy()
        r0, h0, v0 = cart_to_sphere(start)
        self.lookat0 = lookat_point(data, cam_id, com)
        ang = np.pi / 2 * s
        self.cam_lo = np.array(
            [max(r0 * (1 - 0.5 * s), 0.0), max(h0 - ang, -np.pi), max(v0 - ang, 0.0), -ang]
        )
        self.cam_hi = np.array(
            [r0 * (1 + 1.5 * s), min(h0 + ang, 0.0), min(v0 + ang, np.pi / 2), ang]
        )
        self.cam_default = np.array([r0, h0, v0, 0.0])
        self.cam = np.broadcast_to(self.cam_default, (batch, 4)).copy()
        self.vel_scaling = r0 / 4.0
        self.max_vel = 0.4 * s if dynamic else 0.0
        self.vel_std = 0.1 * s if dynamic else 0.0
        self.max_roll_vel = np.pi / 50 * s if dynamic else 0.0
        self.roll_std = np.pi / 300 * s if dynamic else 0.0
        self.cam_vel = np.zeros((batch, 3))
        self.roll_vel = np.zeros(batch)

        # Background.
        self.video = np.zeros(batch, np.int32)
        self.frame = np.zeros(batch, np.int32)
        self.direction = np.ones(batch, np.int32)

    # -- episode start ---------------------------------------------------------------------
    def reset(self, which: np.ndarray | None = None) -> None:
        """New per-episode draws for the envs where `which` (bool [B]) is True (None: all)."""
        idx = np.arange(self.batch) if which is None else np.flatnonzero(np.asarray(which))
        n = len(idx)
        if n == 0:
            return
        rng = self.rng
        if self.use_color:
            m, g = self.mat_range, self.geom_range
            self.mat_rgb[idx] = m.lo + rng.uniform(size=(n, *m.lo.shape)) * (m.hi - m.lo)
            self.geom_rgb[idx] = g.lo + rng.uniform(size=(n, *g.lo.shape)) * (g.hi - g.lo)
        if self.use_camera:
            self.cam[idx] = rng.uniform(self.cam_lo, self.cam_hi, (n, 4))
            vel = rng.normal(size=(n, 3))
            vel /= np.linalg.norm(vel, axis=1, keepdims=True)
            self.cam_vel[idx] = vel * rng.uniform(0, self.max_vel, (n, 1))
            self.roll_vel[idx] = rng.uniform(-self.max_roll_vel, self.max_roll_vel, n)
        if self.num_videos:
            self.video[idx] = rng.integers(0, self.num_videos, n)
            self.frame[idx] = rng.integers(0, self.lengths[self.video[idx]])
            self.direction[idx] = rng.choice([-1, 1], n)

    # -- within an episode -----------------------------------------------------------------
    def step(self) -> None:
        """Dynamic mode: move colours, camera and background one step (static: nothing moves)."""
        if not self.dynamic:
            return
        rng = self.rng
        if self.use_color:
            m, g = self.mat_range, self.geom_range
            self.mat_rgb = np.clip(
                self.mat_rgb + rng.normal(size=self.mat_rgb.shape) * self.color_step_std, m.lo, m.hi
            )
            self.geom_rgb = np.clip(
                self.geom_rgb + rng.normal(size=self.geom_rgb.shape) * self.color_step_std,
                g.lo,
                g.hi,
            )
        if self.use_camera:
            self._step_camera(rng)
        if self.num_videos:  # each video bounces at its own ends
            last = self.lengths[self.video] - 1
            nxt = self.frame + self.direction
            low, high = nxt <= 0, nxt >= last
            self.frame = np.clip(nxt, 0, last).astype(np.int32)
            self.direction = np.where(low, 1, np.where(high, -1, self.direction)).astype(np.int32)

    def _step_camera(self, rng: np.random.Generator) -> None:
        self.cam_vel += rng.normal(size=self.cam_vel.shape) * self.vel_std * self.vel_scaling
        self.roll_vel += rng.normal(size=self.batch) * self.roll_std
        speed = np.linalg.norm(self.cam_vel, axis=1, keepdims=True)
        limit = self.max_vel * self.vel_scaling
        self.cam_vel *= np.where(speed > limit, limit / np.maximum(speed, 1e-12), 1.0)
        self.roll_vel = np.clip(self.roll_vel, -self.max_roll_vel, self.max_roll_vel)
        for b in range(self.batch):
            pos = sphere_to_cart(self.cam[b, :3])
            moved = np.clip(cart_to_sphere(pos + self.cam_vel[b]), self.cam_lo[:3], self.cam_hi[:3])
            self.cam_vel[b] = sphere_to_cart(moved) - pos  # what the clipping let through
            self.cam[b, :3] = moved
        roll = np.clip(self.cam[:, 3] + self.roll_vel, self.cam_lo[3], self.cam_hi[3])
        self.roll_vel = roll - self.cam[:, 3]
        self.cam[:, 3] = roll

    # -- checkpoints ------------------------------------------------------------------------
    _STATE_ARRAYS = (
        "mat_rgb",
        "geom_rgb",
        "cam",
        "cam_vel",
        "roll_vel",
        "video",
        "frame",
        "direction",
    )

    def get_state(self) -> dict:
        """The per-env draws and the generator's state (copies; json-able but for the arrays)."""
        state = {k: getattr(self, k).copy() for k in self._STATE_ARRAYS}
        state["rng"] = self.rng.bit_generator.state
        return state

    def set_state(self, state: dict) -> None:
        """The draws of `get_state`. A state saved with another batch (an evaluation env resumed
        with another num_eval_episodes) gives its generator only: the per-env draws stay as they
        are until the next full reset draws them, as each evaluation's first reset does."""
        if len(state["video"]) == self.batch:
            for k in self._STATE_ARRAYS:
                setattr(self, k, np.array(state[k], dtype=getattr(self, k).dtype))
        else:
            log.warning(
                "distraction state of %d envs given to %d: its generator goes on, the next reset "
                "draws the envs' backgrounds and colours",
                len(state["video"]),
                self.batch,
            )
        self.rng.bit_generator.state = state["rng"]

    # -- outputs ----------------------------------------------------------------------------
    def perturb(self) -> dict[str, np.ndarray]:
        """Per-env parameters for RenderPool.render(perturb=...); {} when nothing is perturbed."""
        out: dict[str, np.ndarray] = {}
        if self.use_color:
            out["mat_rgb"] = self.mat_rgb.astype(np.float32)
            if self.no_material.any():
                out["geom_rgb"] = self.geom_rgb.astype(np.float32)
        if self.use_camera:
            out["cam_sphere"] = self.cam.astype(np.float64)
            out["cam_lookat"] = np.broadcast_to(self.lookat0, (self.batch, 3)).astype(np.float64)
        return out

    def background_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(video int32 [B], frame int32 [B]) into the [N, T, ...] backgrounds."""
        return self.video.copy(), self.frame.copy()
