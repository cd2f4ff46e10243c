"""Drawing: the visual settings, and the renderer that turns MuJoCo states into frames and labels.

This file owns what one render worker does with a batch of states: the visual settings
(`RenderSettings`, recorded in run summaries, and the effects each quality turns on), and
`TileRenderer`, which sets each sample's state, applies the per-sample colour / camera
perturbations of the Distracting Control Suite just before drawing (the camera's pose from
envs/camera.py), and draws its uint8 RGB frame and its per-pixel labels (the rule is in
envs/labels.py). The worker processes that run one `TileRenderer` each are envs/render_pool.py.

Pictures (`RenderSettings.quality`, the config's `env.render.quality`): "dm_control" draws what
dm_control's `physics.render(84, 84, camera_id)` draws, i.e. mujoco.Renderer's default frame
(skybox, shadows, floor reflection, the model's 4x multisampling), with a 256-texel shadow map
instead of 2048; "fast" draws none of these effects (black sky). The segmentation pass is MuJoCo's
flat-colour pass, which skips every effect, so labels are the same under both.

Meshes (`RenderSettings.mesh_faces`): the tasks' model factories can draw every mesh of more
faces simplified to about that many (`simplify_meshes`); only the kitchen's arm has such meshes.
Spheres, capsules and cylinders (`RenderSettings.num_slices`, `num_stacks`): MuJoCo draws them as
meshes it makes with the render context, of `vis.quality.numslices` slices around and `numstacks`
stacks along (28 and 16 unless a model says otherwise); fewer draw faster and rounder shapes a
little more faceted.

Drawing: each worker renders its samples into "tile sheets". Each picture (a sample's RGB frame,
then its segmentation) is drawn by `mjr_render` at the origin of a one-picture offscreen buffer,
as mujoco.Renderer draws a frame, so every effect works per picture (one shadow-map pass per
light, one reflection pass, one skybox), and the frame equals mujoco.Renderer's bit for bit; a
GPU-side copy (resolving the multisamples) then puts it in its place on the sheet, an auxiliary
buffer. One `mjv_updateScene` per sample serves both pictures, and one readback per sheet reads
everything (per-frame readback is what limits throughput, docs/design.md).

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
import re

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from envs.camera import kinematics, perturbed_camera_pose  # noqa: E402
from envs.labels import LABEL_BACKGROUND, LABEL_OTHER, label_tables  # noqa: E402

# Perturbation keys understood by TileRenderer.render and RenderPool.render (all numpy, leading
# batch dim B):
#   "mat_rgb"    f32 [B, nmat, 3]   material RGB (alpha kept from the model)
#   "geom_rgb"   f32 [B, ngeom, 3]  RGB of geoms drawn without a material (alpha kept)
#   "cam_sphere" f32 [B, 4]         (radius, horizontal angle, vertical angle, roll) of the camera,
#                                   relative to the agent's centre of mass for tracking cameras
#                                   and to the world origin for fixed ones
#   "cam_lookat" f32 [B, 3]         point a fixed camera looks at (ignored for tracking cameras)
PERTURB_KEYS = ("mat_rgb", "geom_rgb", "cam_sphere", "cam_lookat")


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
# map is smaller: 256 instead of the XMLs' 2048 texels per side moves 84x84 frames by at most
# 0.02-0.08 levels of 255 on average (walker, cup, finger; tests/test_render.py) and took an H100 pool
# (16 workers, pictures drawn in place) from 1.5k to 4.1k obs/s. "fast": no effect at all, so the
# sky is black: a different picture (32-45 levels from dm_control's), for quick runs on CPU-only
# machines (Mesa llvmpipe draws it ~7x faster; benchmarks/results/render_quality_cpu.json).
QUALITY_VISUALS = {
    "dm_control": Visuals(
        skybox=True, shadows=True, reflections=True, multisample=True, shadow_size=256
    ),
    "fast": Visuals(skybox=False, shadows=False, reflections=False, multisample=False),
}


# Fewer faces change the picture more (the kitchen's frames 0.5 of 255 levels from the shipped
# meshes' at 4,000, 1.4 at 1,000: benchmarks/results/render_kitchen_mesh_faces_cpu.json), and
# targets of a few hundred faces are not met.
MIN_MESH_FACES = 1000
# RenderSettings.gpus for drawing on the CPU's cores (Mesa's llvmpipe) instead of a GPU.
CPU = "cpu"
# A cylinder is drawn as a prism of `num_slices` sides: fewer than 8 no longer look round. One
# stack draws no sphere at all (and capsules without their caps).
MIN_SLICES = 8
MIN_STACKS = 2


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """Settings of the render pool; the config's `env.render` fields (recorded in summaries)."""

    width: int = 84
    height: int = 84
    quality: str = "dm_control"  # QUALITIES: "dm_control" (its picture) | "fast" (no effects)
    # 0 -> min(cores this process may use, 8), capped by envs_per_worker; drawn on the CPU
    # (gpus "cpu"): those cores but one, uncapped (each pool: the training env's and each
    # evaluation process's, which share the cores while an evaluation runs).
    num_workers: int = 0
    # With num_workers 0 and GPUs drawing: at least this many envs per worker (fewer workers
    # for small batches: each worker holds a GL context on the GPU the updates run on); 0: no cap.
    envs_per_worker: int = 0
    # Samples drawn before one readback (one "sheet"). 0 -> auto: 64.
    tiles_per_sheet: int = 0
    # Drawn meshes of more faces simplified to about this many (`simplify_meshes`); 0: as
    # shipped. The model factories (the tasks' `render_model`, `render_factory`) read it.
    mesh_faces: int = 0
    # Spheres, capsules and cylinders drawn with this many slices around (>= MIN_SLICES) and
    # stacks along (>= MIN_STACKS); 0: the model's own (vis.quality.numslices / numstacks).
    num_slices: int = 0
    num_stacks: int = 0
    # False: no segmentation pass, labels all 0 (LABEL_BACKGROUND), for an env that needs no
    # agent mask and composites no background (dear_jax.experiment.make_env decides, by method).
    labels: bool = True
    # The GPUs the workers draw on: "auto" (MuJoCo's choice: MUJOCO_EGL_DEVICE_ID if set, else
    # the process's first GPU; `dear_jax.experiment.make_env` makes it GPUs the training leaves
    # idle, else the GPUs of the env's lanes) or GPU numbers as MUJOCO_EGL_DEVICE_ID takes them
    # (the process's visible GPUs, in CUDA's order), e.g. "1" or "0,1": the workers spread over
    # them in blocks (`worker_gpus`). "cpu": no GPU; Mesa's software rasteriser (llvmpipe)
    # draws on the CPU's cores, through EGL as well (`use_cpu_drawing`), one worker per core
    # the process may use but one unless num_workers says otherwise.
    # Drawing shares its GPU with the updates: DEAR walker's loop, 5 lanes, drawn on a second GPU
    # ran at 1,709-1,711 env frames/s against 1,355-1,398 (benchmarks/RESULTS.md, "End to end").
    gpus: str = "auto"
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
        for name in ("num_workers", "envs_per_worker"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be 0 (auto) or more, got {getattr(self, name)}")
        if self.gpus not in ("auto", CPU) and not re.fullmatch(r"\d+(,\d+)*", self.gpus):
            raise ValueError(
                f"render gpus {self.gpus!r}: 'auto', 'cpu' or GPU numbers separated by commas, "
                "e.g. '1' or '0,1'"
            )
        if self.mesh_faces < 0 or 0 < self.mesh_faces < MIN_MESH_FACES:
            raise ValueError(
                f"mesh_faces must be 0 (meshes as shipped) or >= {MIN_MESH_FACES}, got "
                f"{self.mesh_faces}"
            )

        for name, least in (("num_slices", MIN_SLICES), ("num_stacks", MIN_STACKS)):
            value = getattr(self, name)
            if value < 0 or 0 < value < least:
                raise ValueError(f"{name} must be 0 (the model's own) or >= {least}, got {value}")

    def resolved_workers(self, batch: int | None = None) -> int:
        """The pool's number of workers for batches of `batch` samples (None: not known)."""
        if self.num_workers > 0:
            return self.num_workers
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        if self.gpus == CPU:
            return max((cores or 1) - 1, 1)
        workers = min(cores or 1, 8)
        if self.envs_per_worker > 0 and batch:
            workers = min(workers, -(-batch // self.envs_per_worker))
        return workers

    def worker_gpus(self, workers: int) -> list[int | str | None]:
        """The GPU each of `workers` workers draws on (None: MuJoCo's choice; "cpu": Mesa's
        software rasteriser, `use_cpu_drawing`): worker i of W on
        gpus[i * G // W], so that each GPU draws for the block of the batch its lanes own."""
        if self.gpus == "auto":
            return [None] * workers
        if self.gpus == CPU:
            return [CPU] * workers
        gpus = [int(g) for g in self.gpus.split(",")]
        return [gpus[i * len(gpus) // workers] for i in range(workers)]

    def resolved_visuals(self) -> Visuals:
        return self.visuals or QUALITY_VISUALS[self.quality]


def simplify_meshes(spec: mujoco.MjSpec, max_faces: int, meshdir: str) -> list[str]:
    """Every STL mesh of `spec` with more than `max_faces` faces, simplified to about that many
    (quadric edge collapse, fast-simplification) and put back as user vertices and faces;
    returns their names. STL only: it has no texture coordinates to lose. For drawing only: a
    mesh's inertia changes with its shape. MuJoCo places each mesh by its own centroid and
    principal axes, so a simplified mesh stays where the original was (the kitchen's links
    within 1.2 mm). meshdir: the folder the meshes' file names are relative to."""
    if max_faces <= 0:
        return []
    import fast_simplification
    import trimesh

    names = []
    for mesh in spec.meshes:
        if not mesh.file.lower().endswith(".stl"):
            continue
        shape = trimesh.load(os.path.join(meshdir, mesh.file), force="mesh")  # merges vertices
        if len(shape.faces) <= max_faces:
            continue
        verts, faces = fast_simplification.simplify(
            np.asarray(shape.vertices, np.float32),
            np.asarray(shape.faces, np.int32),
            target_reduction=1.0 - max_faces / len(shape.faces),
        )
        mesh.file = ""
        mesh.uservert = np.asarray(verts, np.float32).ravel()
        mesh.userface = np.asarray(faces, np.int32).ravel()
        names.append(mesh.name)
    return names


def use_cpu_drawing() -> None:
    """Make this process's EGL contexts Mesa's llvmpipe on the CPU, whatever GPUs the machine
    has: MuJoCo's EGL display is made on Mesa's software device (EGL_MESA_device_software),
    which EGL lists beside the GPUs' where Mesa's EGL is installed. Call it before the process
    makes its first context (a render worker does, first thing). Each picture is rasterised in
    the calling thread (LP_NUM_THREADS=0, unless set): a worker per core draws side by side."""
    if os.environ.get("MUJOCO_GL", "egl") != "egl":
        raise RuntimeError(
            f"render gpus 'cpu' draws through EGL, but MUJOCO_GL={os.environ['MUJOCO_GL']!r}: "
            "unset it or set it to 'egl'"
        )
    import mujoco.egl
    from mujoco.egl import egl_ext as EGL
    from OpenGL import error

    if mujoco.egl.EGL_DISPLAY is not None:
        raise RuntimeError(
            "render gpus 'cpu': this process has an EGL display already (its contexts are on it); "
            "call use_cpu_drawing before the process's first context"
        )
    os.environ.setdefault("LP_NUM_THREADS", "0")  # read when the display is initialised
    address = EGL.eglGetProcAddress("eglQueryDeviceStringEXT")
    devices = EGL.eglQueryDevicesEXT(max_devices=64) if address else []
    query = ctypes.CFUNCTYPE(ctypes.c_char_p, EGL.EGLDeviceEXT, EGL.EGLint)(address or 0)
    for device in devices:
        if b"EGL_MESA_device_software" not in (query(device, EGL.EGL_EXTENSIONS) or b"").split():
            continue
        display = EGL.eglGetPlatformDisplayEXT(EGL.EGL_PLATFORM_DEVICE_EXT, device, None)
        try:
            ready = display != EGL.EGL_NO_DISPLAY and EGL.eglInitialize(display, None, None)
        except error.GLError:
            ready = False
        if ready:
            mujoco.egl.EGL_DISPLAY = display
            return
    raise RuntimeError(
        f"render gpus 'cpu' draws with Mesa's software rasteriser through EGL, but none of the "
        f"{len(devices)} EGL devices is Mesa's (EGL_MESA_device_software) and usable. Install "
        "Mesa's EGL and drivers (apt-get install libegl-mesa0 libgl1-mesa-dri), or draw on a GPU "
        "(render gpus 'auto' or GPU numbers)."
    )


def apply_visuals(model: mujoco.MjModel, visuals: Visuals) -> None:
    """Sets the model-side options (read when a render context is made, so set them before)."""
    if not visuals.multisample:
        model.vis.quality.offsamples = 0
    if not visuals.shadows:
        model.vis.quality.shadowsize = 0  # no shadow map allocated
    elif visuals.shadow_size is not None:
        model.vis.quality.shadowsize = int(visuals.shadow_size)


def apply_tessellation(model: mujoco.MjModel, settings: RenderSettings) -> None:
    """Sets the primitives' slices and stacks the settings ask for (read when a render context
    is made, so set them before)."""
    if settings.num_slices:
        model.vis.quality.numslices = settings.num_slices
    if settings.num_stacks:
        model.vis.quality.numstacks = settings.num_stacks


def apply_scene_flags(scene: mujoco.MjvScene, visuals: Visuals) -> None:
    scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = visuals.shadows
    scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = visuals.reflections
    scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = visuals.skybox


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
        apply_tessellation(model, settings)
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
        label_rows: np.ndarray | None = None,
    ) -> None:
        """qpos [B,nq] -> rgb_out uint8 [B,H,W,3], labels_out uint8 [B,H,W] (written in place).
        label_rows: bool [B], the samples whose segmentation pass is drawn (None: every one);
        the others' labels, as every label without `settings.labels`, are LABEL_BACKGROUND."""
        perturb = perturb or {}
        if label_rows is None:
            label_rows = np.full(qpos.shape[0], self.settings.labels)
        else:
            label_rows = np.asarray(label_rows, bool) & self.settings.labels
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
                if not label_rows[start + k]:
                    luts.append(None)
                    continue
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
                lut = luts[k]
                if lut is None:
                    labels_out[start + k] = LABEL_BACKGROUND
                    continue
                seg = tile[::-1, (2 * c + 1) * w : (2 * c + 2) * w]
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
