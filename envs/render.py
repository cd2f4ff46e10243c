"""The render pool: batched MuJoCo states -> uint8 RGB frames and per-pixel labels.

This file owns the CPU side of the picture: worker processes, each with its own MjModel, MjData,
EGL context and MuJoCo render context; the kinematics needed to draw a state; the visual settings
(`RenderSettings`, recorded in run summaries); the per-sample colour / camera perturbations of the
Distracting Control Suite applied just before drawing; and the rule that turns MuJoCo's
segmentation into the four labels BACKGROUND / FLOOR / AGENT / OTHER.

Agent rule (docs/method.md, Masks), per segmentation object type:
- geom: AGENT if its id is one of the task's agent geoms, FLOOR if one of its floor geoms,
  else OTHER.
- site, tendon: OTHER, always. The mask is exactly "pixels of agent geoms", as the reference
  computes it from MuJoCo's geom segmentation. ball_in_cup's string (a tendon 3 mm wide, a pixel
  at most at 84x84) and visible sites (the cup's 5 mm site, finger's spinner tip and target
  sites) are therefore scenery, never mask; tests/test_render.py checks both cases.
- anything else drawn (decor, skins, flexes): OTHER. Pixels where nothing is drawn: BACKGROUND.

Pictures (`RenderSettings.quality`, the config's `env.render.quality`): "dm_control" draws what
dm_control's `physics.render(84, 84, camera_id)` draws, i.e. mujoco.Renderer's default frame
(skybox, shadows, floor reflection, the model's 4x multisampling), with a 256-texel shadow map
instead of 2048; "fast" draws none of these effects (black sky). The segmentation pass is MuJoCo's
flat-colour pass, which skips every effect, so labels are the same under both.

Drawing: each worker renders its samples into "tile sheets". Each picture (a sample's RGB frame,
then its segmentation) is drawn by `mjr_render` at the origin of a one-picture offscreen buffer,
as mujoco.Renderer draws a frame, so every effect works per picture (one shadow-map pass per
light, one reflection pass, one skybox), and the frame equals mujoco.Renderer's bit for bit; a
GPU-side copy (resolving the multisamples) then puts it in its place on the sheet, an auxiliary
buffer. One `mjv_updateScene` per sample serves both pictures, and one readback per sheet reads
everything (per-frame readback is what limits throughput, docs/design.md). Results return through one
shared-memory block; only the small inputs (qpos, perturbations) are pickled.

The earlier layout drew each picture in place on a sheet-sized buffer (`RenderSettings.in_place`,
kept for measurements): there MuJoCo's reflection pass clears the stencil of the whole sheet for
every picture, and pictures at other offsets could differ from mujoco.Renderer by a level in a
few pixels on a GPU. Measured that way without effects (benchmarks/results/render_h100.json,
H100 + 16 cores, walker, 84x84, batch 1024): 64 tiles per sheet 8.1k obs/s with 1 worker and
24.7k with 16; one tile per sheet 6.4k with 1 worker and ~4.8k with 4-16 (readback contention).
"""

from __future__ import annotations

import ctypes
import dataclasses
import os
import signal
import threading
import traceback
from collections.abc import Callable
from multiprocessing import connection, get_context, resource_tracker, shared_memory
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

LABEL_BACKGROUND, LABEL_FLOOR, LABEL_AGENT, LABEL_OTHER = 0, 1, 2, 3
LABEL_NAMES = ("background", "floor", "agent", "other")

# Perturbation keys understood by RenderPool.render (all numpy, leading batch dim B):
#   "mat_rgb"    f32 [B, nmat, 3]   material RGB (alpha kept from the model)
#   "geom_rgb"   f32 [B, ngeom, 3]  RGB of geoms drawn without a material (alpha kept)
#   "cam_sphere" f32 [B, 4]         (radius, horizontal angle, vertical angle, roll) of the camera,
#                                   relative to the agent's centre of mass for tracking cameras
#                                   and to the world origin for fixed ones
#   "cam_lookat" f32 [B, 3]         point a fixed camera looks at (ignored for tracking cameras)
PERTURB_KEYS = ("mat_rgb", "geom_rgb", "cam_sphere", "cam_lookat")

_WORKER_TIMEOUT_S = 600.0


QUALITIES = ("dm_control", "fast")


@dataclasses.dataclass(frozen=True)
class Visuals:
    """MuJoCo's visual effects, as a render quality resolves them."""

    skybox: bool
    shadows: bool
    reflections: bool  # the floor's mirror image (dm_control's floors have reflectance 0.2)
    multisample: bool  # the model's own offscreen multisampling (vis.quality.offsamples, 4) or none
    shadow_size: int | None = None  # shadow map texels per side; None = the model's own (2048)


# "dm_control": the picture of dm_control's `physics.render(84, 84, camera_id)`, which is
# mujoco.Renderer's default picture: every effect on, the model's 4x multisampling. Only the shadow
# map is smaller: 256 instead of the XMLs' 2048 texels per side moves 84x84 frames by 0.02-0.11
# levels of 255 on average (walker, cup, finger; tests/test_render.py) and took an H100 pool
# (16 workers, pictures drawn in place) from 1.5k to 4.1k obs/s. "fast": no effect at all, so the
# sky is black: a different picture (32-45 levels from dm_control's), for quick runs on CPU-only
# machines (Mesa llvmpipe draws it ~7x faster; benchmarks/results/render_quality_cpu.json).
QUALITY_VISUALS = {
    "dm_control": Visuals(
        skybox=True, shadows=True, reflections=True, multisample=True, shadow_size=256
    ),
    "fast": Visuals(skybox=False, shadows=False, reflections=False, multisample=False),
}


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """Settings of the render pool; the config's `env.render` fields (recorded in summaries)."""

    width: int = 84
    height: int = 84
    quality: str = "dm_control"  # QUALITIES: "dm_control" (its picture) | "fast" (no effects)
    num_workers: int = 0  # 0 -> min(os.cpu_count(), 8)
    # Samples drawn before one readback (one "sheet"). 0 -> auto: 64.
    tiles_per_sheet: int = 0
    # For measurements only (benchmarks/render.py), never set by configs:
    # visuals: effects other than the quality's (None = the quality's);
    # in_place: draw each sample straight into its place in a sheet-sized MuJoCo buffer (the
    #   layout before samples were drawn at the origin and copied; see TileRenderer).
    visuals: Visuals | None = None
    in_place: bool = False

    def __post_init__(self):
        if self.quality not in QUALITY_VISUALS:
            raise ValueError(
                f"unknown render quality {self.quality!r}; valid: {', '.join(QUALITIES)}"
            )

    def resolved_workers(self) -> int:
        return self.num_workers if self.num_workers > 0 else min(os.cpu_count() or 1, 8)

    def resolved_visuals(self) -> Visuals:
        return self.visuals or QUALITY_VISUALS[self.quality]


def apply_visuals(model: mujoco.MjModel, visuals: Visuals) -> None:
    """Sets the model-side options (read when a render context is made, so set them before)."""
    if not visuals.multisample:
        model.vis.quality.offsamples = 0
    if not visuals.shadows:
        model.vis.quality.shadowsize = 0  # no shadow map allocated
    elif visuals.shadow_size is not None:
        model.vis.quality.shadowsize = int(visuals.shadow_size)


def apply_scene_flags(scene: mujoco.MjvScene, visuals: Visuals) -> None:
    scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = visuals.shadows
    scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = visuals.reflections
    scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = visuals.skybox


def kinematics(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """What drawing a state needs, and no more than mj_forward's position stage.

    Poses alone (mj_kinematics, mj_comPos, mj_camlight, mj_tendon) are not enough: MuJoCo draws a
    tendon at its limit in the constraint colour (ball_in_cup's taut string turns red), which
    needs the constraint rows of mj_fwdPosition. It costs 2-3 us per state on dm_control's
    models, nothing next to drawing.
    """
    mujoco.mj_fwdPosition(model, data)


def label_tables(model: mujoco.MjModel, agent_geom_ids, floor_geom_ids) -> dict[int, np.ndarray]:
    """Per object type (mjtObj value) -> uint8 label of each object of that type (agent rule)."""
    agent = np.zeros(model.ngeom, bool)
    agent[np.asarray(agent_geom_ids, int)] = True
    floor = np.zeros(model.ngeom, bool)
    floor[np.asarray(floor_geom_ids, int)] = True
    if (agent & floor).any():
        raise ValueError(f"geoms {np.flatnonzero(agent & floor)} are both agent and floor")
    geom = np.full(model.ngeom, LABEL_OTHER, np.uint8)
    geom[agent] = LABEL_AGENT
    geom[floor] = LABEL_FLOOR

    # Sites and tendons (and every other drawn object type) fall back to OTHER.
    return {int(mujoco.mjtObj.mjOBJ_GEOM): geom}


def labels_from_segmentation(seg: np.ndarray, tables: dict[int, np.ndarray]) -> np.ndarray:
    """seg int32 [..., 2] (object id, object type), as mujoco.Renderer returns -> uint8 labels."""
    objid, objtype = seg[..., 0], seg[..., 1]
    out = np.full(objid.shape, LABEL_OTHER, np.uint8)
    out[objtype == -1] = LABEL_BACKGROUND
    for kind, table in tables.items():
        hit = objtype == kind
        out[hit] = table[objid[hit]]
    return out


# ---------------------------------------------------------------------------------------------
# Camera perturbation geometry (used in the workers, after kinematics of the sample).


def sphere_to_cart(sphere: np.ndarray) -> np.ndarray:
    """(radius, horizontal angle, vertical angle from +z) -> xyz."""
    r, h, v = sphere[0], sphere[1], sphere[2]
    return np.array([r * np.sin(v) * np.cos(h), r * np.sin(v) * np.sin(h), r * np.cos(v)])


def cart_to_sphere(xyz: np.ndarray) -> np.ndarray:
    r = float(np.linalg.norm(xyz))
    return np.array([r, np.arctan2(xyz[1], xyz[0]), np.arctan2(np.linalg.norm(xyz[:2]), xyz[2])])


def look_at_xmat(target: np.ndarray, position: np.ndarray, roll: float) -> np.ndarray:
    """Camera frame (MuJoCo: looks along -z, y up) at `position` facing `target`, level horizon,
    then rolled by `roll` about its viewing axis. Returns the 3x3 frame, columns = camera axes."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    norm = np.linalg.norm(right)
    # Looking straight up or down: any horizontal right axis keeps the view well defined.
    right = right / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    up = np.cross(right, forward)
    frame = np.stack([right, up, -forward], axis=1)
    c, s = np.cos(roll), np.sin(roll)
    roll_mat = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return frame @ roll_mat


def lookat_point(data: mujoco.MjData, cam_id: int, anchor: np.ndarray) -> np.ndarray:
    """The point on the camera's viewing axis as far away as `anchor` (the agent's centre)."""
    dist = np.linalg.norm(data.cam_xpos[cam_id] - anchor)
    return data.cam_xpos[cam_id] + data.cam_xmat[cam_id].reshape(3, 3) @ np.array([0, 0, -dist])


def perturbed_camera_pose(
    model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, sphere: np.ndarray, lookat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World position and frame of the perturbed camera for the current (kinematics-done) state."""
    tracking = model.cam_mode[cam_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED
    if tracking:
        com = data.subtree_com[1]
        position = sphere_to_cart(sphere) + com
        target = lookat_point(data, cam_id, com)
    else:
        position = sphere_to_cart(sphere)
        target = np.asarray(lookat, np.float64)
    return position, look_at_xmat(target, position, float(sphere[3]))


# ---------------------------------------------------------------------------------------------
# One worker's renderer.

_SHEET_AUX = 0  # index of the MuJoCo auxiliary buffer that holds the sheet


class _RawGL:
    """The GL calls MuJoCo has no function for: copy a picture into the sheet, read the sheet.

    PyOpenGL's raw entry points (about a microsecond a call); `read` checks GL's error flag once
    per sheet.
    """

    def __init__(self):
        from OpenGL.raw.GL.VERSION import GL_1_0, GL_3_0

        self.g1, self.g3 = GL_1_0, GL_3_0

    def blit(self, src: int, dst: int, w: int, h: int, left: int, bottom: int) -> None:
        g1, g3 = self.g1, self.g3
        g3.glBindFramebuffer(g3.GL_READ_FRAMEBUFFER, src)
        g3.glBindFramebuffer(g3.GL_DRAW_FRAMEBUFFER, dst)
        # Same size, so a multisampled picture is resolved as mjr_readPixels resolves it.
        g3.glBlitFramebuffer(
            0, 0, w, h, left, bottom, left + w, bottom + h, g1.GL_COLOR_BUFFER_BIT, g1.GL_NEAREST
        )

    def read(self, fbo: int, out: np.ndarray) -> None:
        g1, g3 = self.g1, self.g3
        if not out.flags.c_contiguous:
            raise ValueError("the sheet must be C-contiguous")
        g3.glBindFramebuffer(g3.GL_READ_FRAMEBUFFER, fbo)
        g1.glPixelStorei(g1.GL_PACK_ALIGNMENT, 1)
        h, w = out.shape[:2]
        g1.glReadPixels(
            0, 0, w, h, g1.GL_RGB, g1.GL_UNSIGNED_BYTE, out.ctypes.data_as(ctypes.c_void_p)
        )
        err = g1.glGetError()
        if err:
            raise RuntimeError(f"OpenGL error 0x{int(err):04x} copying or reading a sheet")


class TileRenderer:
    """Renders batches of states with one GL context; usable in-process (tests, preview)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        camera: int | str,
        agent_geom_ids,
        floor_geom_ids,
        settings: RenderSettings,
    ):
        from mujoco.rendering.classic import gl_context

        self.model = model
        self.settings = settings
        self.data = mujoco.MjData(model)
        h, w = settings.height, settings.width
        self.cam_id = camera if isinstance(camera, int) else model.camera(camera).id
        if not 0 <= self.cam_id < model.ncam:
            raise ValueError(f"camera {camera!r} not in the model's {model.ncam} cameras")
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.camera.fixedcamid = self.cam_id

        # The offscreen buffer (not this surface) receives the pictures; its size is a model
        # option read when the MuJoCo context is made, so the sheet is decided first.
        self.gl = gl_context.GLContext(w, h)
        self.gl.make_current()
        self.tiles = settings.tiles_per_sheet or self._auto_tiles()
        self.cols = min(self.tiles, 16)  # sample pairs across a sheet
        self.rows = -(-self.tiles // self.cols)
        sheet_w, sheet_h = 2 * self.cols * w, self.rows * h
        self.visuals = settings.resolved_visuals()
        apply_visuals(model, self.visuals)
        self.in_place = settings.in_place
        if self.in_place:
            model.vis.global_.offwidth = max(model.vis.global_.offwidth, sheet_w)
            model.vis.global_.offheight = max(model.vis.global_.offheight, sheet_h)
        else:
            # One picture at a time, at the origin, as mujoco.Renderer draws it. The buffer holds
            # just that picture: the reflection pass clears the stencil of the whole buffer.
            model.vis.global_.offwidth, model.vis.global_.offheight = w, h
        self.con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.con)
        if not self.in_place:
            # The sheet: a single-sample buffer the pictures are copied (resolved) into.
            mujoco.mjr_addAux(_SHEET_AUX, sheet_w, sheet_h, 0, self.con)
            self._gl = _RawGL()
            self._origin = mujoco.MjrRect(0, 0, w, h)
            self._picture_fbo = int(self.con.offFBO)
            self._sheet_fbo = int(self.con.auxFBO[_SHEET_AUX])
        self.scene = mujoco.MjvScene(model, maxgeom=10000)
        self.option = mujoco.MjvOption()
        self.option.flags[mujoco.mjtVisFlag.mjVIS_RANGEFINDER] = False  # as dm_control draws
        apply_scene_flags(self.scene, self.visuals)

        self.tables = label_tables(model, agent_geom_ids, floor_geom_ids)
        self.sheet = np.empty((sheet_h, sheet_w, 3), np.uint8)
        self.mat_rgba0 = model.mat_rgba.copy()
        self.geom_rgba0 = model.geom_rgba.copy()
        self.no_material = model.geom_matid < 0

    def _auto_tiles(self) -> int:
        if not self.settings.in_place:
            # The drawing buffer stays one picture whatever the sheet holds, so a big sheet
            # costs nothing more, on software GL too; fewer readbacks is what counts (docs/design.md).
            return 64
        # Drawing in place, software rasterisers (Mesa llvmpipe) pay per pixel of the whole
        # buffer, so one sample per sheet was fastest there; on a GPU the readbacks dominated.
        renderer = self.gl_info()["GL_RENDERER"].lower()
        return 1 if any(s in renderer for s in ("llvmpipe", "softpipe", "swrast")) else 64

    def gl_info(self) -> dict[str, str]:
        from OpenGL import GL

        self.gl.make_current()
        return {
            "GL_VENDOR": GL.glGetString(GL.GL_VENDOR).decode(),
            "GL_RENDERER": GL.glGetString(GL.GL_RENDERER).decode(),
            "GL_VERSION": GL.glGetString(GL.GL_VERSION).decode(),
        }

    def _scene_labels(self) -> np.ndarray:
        """Label of each segmentation colour of the current scene: [segid + 1], [0] = nothing."""
        n = self.scene.ngeom
        lut = np.full(n + 2, LABEL_OTHER, np.uint8)
        lut[0] = LABEL_BACKGROUND
        for g in self.scene.geoms[:n]:
            if g.segid < 0:
                continue
            table = self.tables.get(int(g.objtype))
            if table is not None and 0 <= g.objid < len(table):
                lut[g.segid + 1] = table[g.objid]
        return lut

    def _set_sample(self, i: int, qpos, mocap_pos, mocap_quat, perturb) -> None:
        m, d = self.model, self.data
        if "mat_rgb" in perturb:
            m.mat_rgba[:, :3] = perturb["mat_rgb"][i]
        else:
            m.mat_rgba[:] = self.mat_rgba0
        if "geom_rgb" in perturb:
            m.geom_rgba[self.no_material, :3] = perturb["geom_rgb"][i][self.no_material]
        else:
            m.geom_rgba[:] = self.geom_rgba0
        d.qpos[:] = qpos[i]
        if mocap_pos is not None:
            d.mocap_pos[:] = mocap_pos[i]
        if mocap_quat is not None:
            d.mocap_quat[:] = mocap_quat[i]
        kinematics(m, d)
        if "cam_sphere" in perturb:
            if "cam_lookat" in perturb:
                lookat = perturb["cam_lookat"][i]
            elif m.cam_mode[self.cam_id] == mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
                raise ValueError(
                    "a fixed camera's perturbation needs 'cam_lookat' with 'cam_sphere'"
                )
            else:
                lookat = None  # tracking cameras look along their own axis
            pos, xmat = perturbed_camera_pose(m, d, self.cam_id, perturb["cam_sphere"][i], lookat)
            d.cam_xpos[self.cam_id] = pos
            d.cam_xmat[self.cam_id] = xmat.reshape(-1)

    def _draw(self, left: int, bottom: int) -> None:
        """Draws the current scene into the sheet with its lower left corner at (left, bottom)."""
        w, h = self.settings.width, self.settings.height
        if self.in_place:
            mujoco.mjr_render(mujoco.MjrRect(left, bottom, w, h), self.scene, self.con)
            return
        mujoco.mjr_render(self._origin, self.scene, self.con)
        self._gl.blit(self._picture_fbo, self._sheet_fbo, w, h, left, bottom)
        mujoco.mjr_restoreBuffer(self.con)

    def _read(self, sheet: np.ndarray) -> None:
        """The sheet's bottom rows (GL order) -> sheet, uint8 [rows, sheet width, 3]."""
        if self.in_place:
            rect = mujoco.MjrRect(0, 0, sheet.shape[1], sheet.shape[0])
            mujoco.mjr_readPixels(sheet, None, rect, self.con)
            return
        self._gl.read(self._sheet_fbo, sheet)
        mujoco.mjr_restoreBuffer(self.con)

    def render(
        self,
        qpos: np.ndarray,
        rgb_out: np.ndarray,
        labels_out: np.ndarray,
        *,
        mocap_pos=None,
        mocap_quat=None,
        perturb: dict[str, np.ndarray] | None = None,
    ) -> None:
        """qpos [B,nq] -> rgb_out uint8 [B,H,W,3], labels_out uint8 [B,H,W] (written in place)."""
        perturb = perturb or {}
        h, w = self.settings.height, self.settings.width
        flags = self.scene.flags
        seg_flags = (mujoco.mjtRndFlag.mjRND_SEGMENT, mujoco.mjtRndFlag.mjRND_IDCOLOR)
        per_sheet = self.rows * self.cols
        self.gl.make_current()
        for start in range(0, qpos.shape[0], per_sheet):
            count = min(per_sheet, qpos.shape[0] - start)
            luts = []
            for k in range(count):
                self._set_sample(start + k, qpos, mocap_pos, mocap_quat, perturb)
                mujoco.mjv_updateScene(
                    self.model,
                    self.data,
                    self.option,
                    None,
                    self.camera,
                    mujoco.mjtCatBit.mjCAT_ALL,
                    self.scene,
                )
                r, c = divmod(k, self.cols)
                self._draw(2 * c * w, r * h)
                # MuJoCo's segmentation pass draws flat colours with no effect (skybox, shadows,
                # reflections, multisampling) whatever the scene's flags say.
                for f in seg_flags:
                    flags[f] = 1
                self._draw((2 * c + 1) * w, r * h)
                for f in seg_flags:
                    flags[f] = 0
                luts.append(self._scene_labels())
            rows_used = -(-count // self.cols)
            sheet = self.sheet[: rows_used * h]
            self._read(sheet)
            for k in range(count):
                r, c = divmod(k, self.cols)
                # GL rows run bottom-up: flip each tile.
                tile = sheet[r * h : (r + 1) * h]
                rgb_out[start + k] = tile[::-1, 2 * c * w : (2 * c + 1) * w]
                seg = tile[::-1, (2 * c + 1) * w : (2 * c + 2) * w]
                lut = luts[k]
                if len(lut) <= 256:  # ids fit the red byte; the others are zero
                    labels_out[start + k] = lut[seg[..., 0]]
                else:
                    seg = seg.astype(np.int32)
                    segid = seg[..., 0] | (seg[..., 1] << 8) | (seg[..., 2] << 16)
                    labels_out[start + k] = lut[np.minimum(segid, len(lut) - 1)]
        if perturb:
            self.model.mat_rgba[:] = self.mat_rgba0
            self.model.geom_rgba[:] = self.geom_rgba0

    def close(self) -> None:
        if getattr(self, "con", None) is not None:
            with self.gl.as_current():  # and back to the context that was current
                self.con.free()
            self.con = None
            self.gl.free()

    def __del__(self) -> None:
        # Left to the garbage collector, the MuJoCo context would free its GL objects in
        # whichever context is current: another renderer's, whose objects have the same ids.
        self.close()


# ---------------------------------------------------------------------------------------------
# Worker processes and the pool.


def _attach_shm(name: str) -> shared_memory.SharedMemory:
    # The parent owns and unlinks the block; a worker that registered it with the resource
    # tracker would make the tracker unlink it (or warn about a leak) when the worker exits.
    register = resource_tracker.register
    resource_tracker.register = lambda *args, **kwargs: None
    try:
        return shared_memory.SharedMemory(name=name)
    finally:
        resource_tracker.register = register


def _worker_main(conn, model_fn, init_kwargs) -> None:
    # Ctrl-C and SIGTERM sent to the whole process group are the parent's to handle: it finishes
    # its step, checkpoints and then closes the pool. A worker also ends when the parent's end of
    # the pipe closes (EOF below), so it never outlives the parent.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    renderer = None
    shm = None
    try:
        renderer = TileRenderer(model_fn(), **init_kwargs)
        conn.send(("ok", None))
    except BaseException:  # noqa: BLE001 - any failure must reach the parent
        conn.send(("error", traceback.format_exc()))
        return
    h, w = init_kwargs["settings"].height, init_kwargs["settings"].width
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            break
        kind = msg[0]
        try:
            if kind == "close":
                break
            if kind == "info":
                conn.send(("ok", renderer.gl_info()))
            elif kind == "render":
                _, shm_name, capacity, lo, qpos, mocap_pos, mocap_quat, perturb = msg
                if shm is None or shm.name != shm_name:
                    if shm is not None:
                        shm.close()
                    shm = _attach_shm(shm_name)
                rgb, labels = _views(shm, capacity, h, w)
                n = qpos.shape[0]
                renderer.render(
                    qpos,
                    rgb[lo : lo + n],
                    labels[lo : lo + n],
                    mocap_pos=mocap_pos,
                    mocap_quat=mocap_quat,
                    perturb=perturb,
                )
                conn.send(("ok", None))
            else:
                conn.send(("error", f"unknown message {kind!r}"))
        except BaseException:  # noqa: BLE001
            conn.send(("error", traceback.format_exc()))
    if shm is not None:
        shm.close()
    renderer.close()


def _views(shm: shared_memory.SharedMemory, capacity: int, h: int, w: int):
    rgb = np.ndarray((capacity, h, w, 3), np.uint8, buffer=shm.buf)
    labels = np.ndarray((capacity, h, w), np.uint8, buffer=shm.buf, offset=capacity * h * w * 3)
    return rgb, labels


def _hint(error: str, workers: int) -> str:
    """What to do about a worker's known failures (empty if none applies)."""
    if "Offscreen framebuffer is not complete" not in error:
        return ""
    # Seen on an H100 (2026-11-24): the 5th and 6th training process on one GPU, each with
    # 8 workers for its training env and 8 for its evaluation env, could not make their
    # offscreen buffers while 4 others ran, with 26 GB of the GPU's memory still free.
    return (
        f"\nThe GPU's EGL driver gave this worker no offscreen buffer. This env has {workers} "
        "render workers, each with its own GL context; other processes on this GPU hold theirs. "
        "Lower env.render.num_workers (e.g. --config.env.render.num_workers=2), or run fewer "
        "training processes on this GPU (several seeds or a sweep in one run share one set)."
    )


class RenderPool:
    """Worker processes turning batched states into RGB frames and pixel labels.

    model_fn: picklable zero-argument callable returning a mujoco.MjModel (each worker calls it).
    camera: camera id or name. agent_geom_ids / floor_geom_ids: geom ids for the labels.
    """

    def __init__(
        self,
        model_fn: Callable[[], mujoco.MjModel],
        *,
        camera: int | str,
        agent_geom_ids,
        floor_geom_ids,
        settings: RenderSettings = RenderSettings(),
    ):
        self.settings = settings
        self._lock = threading.Lock()
        self._shm: shared_memory.SharedMemory | None = None
        self._capacity = 0
        init_kwargs = dict(
            camera=camera,
            agent_geom_ids=[int(i) for i in agent_geom_ids],
            floor_geom_ids=[int(i) for i in floor_geom_ids],
            settings=settings,
        )
        # spawn, not fork: the parent may hold JAX / CUDA threads that a fork would corrupt.
        ctx = get_context("spawn")
        self._conns: list[connection.Connection] = []
        self._procs = []
        for _ in range(settings.resolved_workers()):
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=_worker_main, args=(child, model_fn, init_kwargs), daemon=True
            )
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
        try:
            for i in range(len(self._conns)):
                self._receive(i)
        except BaseException:
            self.close()
            raise

    @property
    def num_workers(self) -> int:
        return len(self._conns)

    def _receive(self, i: int) -> Any:
        conn, proc = self._conns[i], self._procs[i]
        deadline = _WORKER_TIMEOUT_S
        while not conn.poll(1.0):
            deadline -= 1.0
            if not proc.is_alive():
                raise RuntimeError(f"render worker {i} died (exit code {proc.exitcode})")
            if deadline <= 0:
                raise TimeoutError(f"render worker {i} gave no answer in {_WORKER_TIMEOUT_S} s")
        status, payload = conn.recv()
        if status != "ok":
            raise RuntimeError(
                f"render worker {i} failed:\n{payload}{_hint(payload, len(self._procs))}"
            )
        return payload

    def _ensure_capacity(self, batch: int) -> None:
        if batch <= self._capacity:
            return
        h, w = self.settings.height, self.settings.width
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
        self._capacity = batch
        self._shm = shared_memory.SharedMemory(create=True, size=batch * h * w * 4)

    def gl_info(self) -> list[dict[str, str]]:
        """GL vendor / renderer / version strings of every worker's context."""
        with self._lock:
            for conn in self._conns:
                conn.send(("info",))
            return [self._receive(i) for i in range(len(self._conns))]

    def render(
        self,
        qpos: np.ndarray,
        *,
        mocap_pos: np.ndarray | None = None,
        mocap_quat: np.ndarray | None = None,
        perturb: dict[str, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """qpos [B,nq] -> (rgb uint8 [B,H,W,3], labels uint8 [B,H,W]). perturb: PERTURB_KEYS."""
        qpos = np.asarray(qpos, np.float64)
        if qpos.ndim != 2:
            raise ValueError(f"qpos must be [B, nq], got shape {qpos.shape}")
        perturb = {k: np.asarray(v) for k, v in (perturb or {}).items()}
        unknown = set(perturb) - set(PERTURB_KEYS)
        if unknown:
            raise ValueError(f"unknown perturbation keys {sorted(unknown)}; valid: {PERTURB_KEYS}")
        batch = qpos.shape[0]
        for name, arr in [("mocap_pos", mocap_pos), ("mocap_quat", mocap_quat), *perturb.items()]:
            if arr is not None and np.shape(arr)[0] != batch:
                raise ValueError(f"{name} has leading dim {np.shape(arr)[0]}, qpos has {batch}")
        h, w = self.settings.height, self.settings.width
        with self._lock:
            self._ensure_capacity(batch)
            bounds = np.linspace(0, batch, len(self._conns) + 1).round().astype(int)
            busy = []
            for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
                if hi <= lo:
                    continue
                part = slice(lo, hi)
                self._conns[i].send(
                    (
                        "render",
                        self._shm.name,
                        self._capacity,
                        int(lo),
                        qpos[part],
                        None if mocap_pos is None else np.asarray(mocap_pos)[part],
                        None if mocap_quat is None else np.asarray(mocap_quat)[part],
                        {k: v[part] for k, v in perturb.items()},
                    )
                )
                busy.append(i)
            errors = []
            for i in busy:
                try:
                    self._receive(i)
                except RuntimeError as err:
                    errors.append(err)
            if errors:
                raise errors[0]
            rgb, labels = _views(self._shm, self._capacity, h, w)
            return rgb[:batch].copy(), labels[:batch].copy()

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close",))
            except (BrokenPipeError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()  # workers ignore SIGTERM
                proc.join(timeout=10)
        for conn in self._conns:
            conn.close()
        self._conns, self._procs = [], []
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    def __enter__(self) -> RenderPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_conns", None):
            self.close()
