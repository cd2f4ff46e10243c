"""The PyTorch reference: DEAR's and DrQ-v2's updates, and a training pipeline of the reference's shape.

Written from docs/method.md, not from the DEAR or DrQ-v2 code, so that the JAX
trainer's speed is measured against the same architecture and losses in PyTorch, on the same GPU,
on the same machine. Nothing in dear_jax imports this file; PyTorch is an optional extra of the
project: `pip install -e ".[torch]"`.

    python -m benchmarks.torch_reference update --methods dear drqv2 --batch 512 --iters 20 \
        [--variants eager fp32 channels_last fused bf16 compile best] [--encoders pool plain] \
        [--aug grid_sample gather]
    python -m benchmarks.torch_reference pipeline --frames 4000 --warmup-frames 4000 --procs 1 5 \
        [--method dear] [--variant eager]

update: one learner update = random shift of obs (+ mask) and next_obs; encoder on both (next_obs
    without gradient); target y = r + gamma_n min(Q1', Q2')(z', a' ~ pi(z'), clip 0.3) with the
    target critic; L = MSE(Q1, y) + MSE(Q2, y) [+ 0.25 L_mask + 100 mean|cos(z_A, sg(z_E))| for
    DEAR]; one Adam step over encoder + critic (+ mask decoder); the actor step on the detached
    features against the updated critic; target EMA (tau 0.01). Timed with CUDA synchronisation
    after `--warmup` untimed updates, on random uint8 batches made on the device. Variants are
    '+'-joined flags (every variant is timed in this one process, one after another):
      eager          PyTorch's defaults: cuDNN convolutions in TF32, matmuls in full fp32,
                     Adam's default (foreach) implementation, NCHW, no compilation
      fp32           TF32 off everywhere            tf32      TF32 for matmuls too
      channels_last  NHWC memory format for the conv layers and their inputs
      fused          Adam(fused=True)               bf16      torch.autocast(bfloat16) forwards
      compile        torch.compile of the two loss functions (backward compiled by AOTAutograd)
      cudagraphs     torch.compile(mode="reduce-overhead") (implies compile)
      best           compile+channels_last+fused+bf16
    A variant that fails (e.g. `compile` without a working C++ toolchain on CPU) is reported as
    failed with its error, and the others still run. cudnn.benchmark is on, as in DrQ-v2.
    Augmentation: `grid_sample` (the reference's way: replicate pad, float images, bilinear
    sampling at pixel centres, so an integer shift) or `gather` (the same integer shift as an
    index gather on uint8, cheaper); both give the same pixels (tests/test_torch_reference.py).

pipeline: P processes (multiprocessing, spawn), each: CPU MuJoCo walker-walk (dm_control's XML,
    task, stepping and reward through envs.dmc / envs.physics.CpuPhysics), action repeat 2,
    `mujoco.Renderer` (EGL) at 84x84 with the model's own visuals (dm_control's defaults:
    skybox, shadows, reflections), one RGB render per agent step plus one segmentation render
    for the agent mask (DEAR only), frame stack 3, the policy on the GPU for every agent step,
    uniform actions for the first 2000 agent steps, the update every 2 agent steps once
    `--seed-frames` frames are collected, metrics read back with .item() after every update (as
    the reference logs them). Replay: an in-process CPU numpy buffer of single frames (and
    masks), stacks and n-step returns rebuilt at sample time, never crossing an episode end,
    no eviction (sized for the run); batches are sampled by one background thread into two
    pinned buffers and copied to the GPU asynchronously; the reference instead writes episodes
    to disk and samples them with a 4-worker DataLoader. Measured: env frames/s over `--frames`
    frames after a warm-up of `--warmup-frames` frames and the first 2 updates; with P > 1 the
    processes start measuring together (a barrier) and the aggregate is the sum of their
    frames/s.

JSON goes to benchmarks/results/torch_<cpu|cuda>.json (or --out): each subcommand merges its rows
into its own section of that file, replacing rows with the same settings.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import json
import os
import pathlib
import platform
import queue
import threading
import time
import traceback

import numpy as np

try:
    import torch
    import torch.nn.functional as F
    from torch import nn
except ImportError as e:  # an optional extra, not a dependency
    raise SystemExit("benchmarks.torch_reference needs PyTorch: pip install -e '.[torch]'") from e

from benchmarks.common import save_json

# docs/method.md, Hyperparameters (walker overrides batch 512 and nstep 1).
LR = 1e-4
TAU = 0.01
STDDEV_CLIP = 0.3
ALPHA = 0.25  # mask loss weight
BETA = 100.0  # orthogonality loss weight (dear_jax's default; see docs/method.md)
AUGMENT_PAD = 4
FRAME_STACK = 3
LATENT_DIM = 4096
FEATURE_DIM = 50
HIDDEN_DIM = 1024

FLAGS = ("fp32", "tf32", "channels_last", "fused", "bf16", "compile", "cudagraphs")
BEST = "compile+channels_last+fused+bf16"
DEFAULT_VARIANTS = ("eager", "fp32", "channels_last", "fused", "bf16", "compile", "best")

# dear_jax's parameter counts for |A| = 6 (dear, pool encoder); the test checks them against
# `dear_jax.update.init_params` shapes as well.
JAX_PARAM_COUNTS = {
    "encoder": 8_423_072,
    "actor": 1_312_924,
    "critic": 2_422_936,
    "mask_decoder": 2_126_291,
}


# ------------------------------------------------------------------------------------------
# Networks (NCHW, as PyTorch lays them out).


def init_weights(module: nn.Module) -> None:
    """Orthogonal weights (gain 1 for linear layers, sqrt(2) for convs and transposed convs, on
    PyTorch's own weight layouts), zero biases; LayerNorm keeps ones and zeros."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight, 1.0)
        nn.init.zeros_(module.bias)
    elif isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.orthogonal_(module.weight, nn.init.calculate_gain("relu"))
        nn.init.zeros_(module.bias)


class Encoder(nn.Module):
    """Four 3x3 convs (9->32 stride 2, then 3x 32->32), ReLU after each: 84 -> 41 -> 39 -> 37 -> 35.
    "pool": 4x4 average pool (-> 32x8x8 = 2048) and Linear(2048 -> 4096), no activation.
    "plain": DrQ-v2's flattened 32x35x35 = 39200 features."""

    def __init__(self, kind: str = "pool", latent_dim: int = LATENT_DIM):
        super().__init__()
        if kind not in ("pool", "plain"):
            raise ValueError(f"unknown encoder {kind!r}; valid: 'pool', 'plain'")
        self.kind = kind
        self.channels_last = False
        layers: list[nn.Module] = [nn.Conv2d(3 * FRAME_STACK, 32, 3, stride=2), nn.ReLU()]
        for _ in range(3):
            layers += [nn.Conv2d(32, 32, 3, stride=1), nn.ReLU()]
        self.convs = nn.Sequential(*layers)
        if kind == "pool":
            self.pool = nn.AvgPool2d(4, stride=4)
            self.fc = nn.Linear(32 * 8 * 8, latent_dim)
            self.out_dim = latent_dim
        else:
            self.out_dim = 32 * 35 * 35

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """obs: pixels 0..255, uint8 or float, [B, 9, 84, 84] -> [B, out_dim]."""
        x = obs.float() / 255.0 - 0.5
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.convs(x)
        if self.kind == "pool":
            return self.fc(self.pool(x).flatten(1))
        return x.flatten(1)


def _trunk(in_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, FEATURE_DIM), nn.LayerNorm(FEATURE_DIM), nn.Tanh())


def _mlp(in_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_dim, HIDDEN_DIM),
        nn.ReLU(),
        nn.Linear(HIDDEN_DIM, HIDDEN_DIM),
        nn.ReLU(),
        nn.Linear(HIDDEN_DIM, out_dim),
    )


class Actor(nn.Module):
    """Trunk (Linear -> 50, LayerNorm, Tanh), MLP 50 -> 1024 -> 1024 -> |A|, tanh: the mean."""

    def __init__(self, repr_dim: int, action_dim: int):
        super().__init__()
        self.trunk = _trunk(repr_dim)
        self.policy = _mlp(FEATURE_DIM, action_dim)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.policy(self.trunk(z)))


class Critic(nn.Module):
    """Its own trunk, then twin heads Q1, Q2 on [trunk(z), a]: [B] each."""

    def __init__(self, repr_dim: int, action_dim: int):
        super().__init__()
        self.trunk = _trunk(repr_dim)
        self.q1 = _mlp(FEATURE_DIM + action_dim, 1)
        self.q2 = _mlp(FEATURE_DIM + action_dim, 1)

    def forward(self, z: torch.Tensor, action: torch.Tensor):
        h = torch.cat([self.trunk(z), action.to(z.dtype)], dim=-1)
        return self.q1(h).squeeze(-1), self.q2(h).squeeze(-1)


class MaskDecoder(nn.Module):
    """DEAR's pool decoder on z_A: Linear(2048 -> 16*8*8), ReLU, 16x8x8; ConvT 16->16 4x4 s4 op3
    (35), ConvT 16->32 (37), 32->32 (39), 32->32 (41), ConvT 32->3 3x3 s2 op1 (84); ReLU between;
    returns logits (the sigmoid is in the loss)."""

    def __init__(self, in_dim: int = LATENT_DIM // 2, out_channels: int = FRAME_STACK):
        super().__init__()
        self.channels_last = False
        self.fc = nn.Linear(in_dim, 16 * 8 * 8)
        self.deconvs = nn.Sequential(
            nn.ConvTranspose2d(16, 16, 4, stride=4, output_padding=3),
            nn.ReLU(),
            nn.ConvTranspose2d(16, 32, 3),
            nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3),
            nn.ReLU(),
            nn.ConvTranspose2d(32, 32, 3),
            nn.ReLU(),
            nn.ConvTranspose2d(32, out_channels, 3, stride=2, output_padding=1),
        )

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.fc(z)).view(-1, 16, 8, 8)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return self.deconvs(x)


def count_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# ------------------------------------------------------------------------------------------
# Augmentation: replicate pad by 4, integer crop back to 84x84, offset 0..8 per sample.


def random_shifts(n: int, device, generator=None, pad: int = AUGMENT_PAD) -> torch.Tensor:
    """Per-sample (dx, dy) crop offsets in 0..2*pad, int64 [n, 2]."""
    return torch.randint(0, 2 * pad + 1, (n, 2), device=device, generator=generator)


def shift_grid_sample(x: torch.Tensor, shifts: torch.Tensor, pad: int = AUGMENT_PAD):
    """The reference's form: float images [B, C, H, W], replicate-padded to P = H + 2 pad, sampled
    bilinearly at the centres of the shifted crop's pixels. With align_corners=False the centre of
    padded pixel k sits at (2k + 1) / P - 1, so output pixel (i, j) reads padded pixel
    (i + dy, j + dx) exactly: an integer shift done by an interpolating sampler."""
    n, _, h, w = x.shape
    if h != w:
        raise ValueError(f"square images only, got {h}x{w}")
    size = h + 2 * pad
    x = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    centres = (2 * torch.arange(h, device=x.device, dtype=x.dtype) + 1) / size - 1  # [h]
    offsets = shifts.to(x.dtype) * (2.0 / size)  # [n, 2] as (dx, dy) in normalised units
    gx = centres.view(1, 1, w).expand(n, h, w) + offsets[:, 0].view(n, 1, 1)
    gy = centres.view(1, h, 1).expand(n, h, w) + offsets[:, 1].view(n, 1, 1)
    grid = torch.stack([gx, gy], dim=-1)  # grid_sample wants (x, y) last
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def shift_gather(x: torch.Tensor, shifts: torch.Tensor, pad: int = AUGMENT_PAD):
    """The same shift as an index gather, any dtype: replicate padding then cropping at offset s
    reads source row clamp(i + s - pad, 0, H - 1), so no padded copy is made."""
    n, c, h, w = x.shape
    ar_h = torch.arange(h, device=x.device)
    ar_w = torch.arange(w, device=x.device)
    rows = (ar_h.view(1, h) + shifts[:, 1:2] - pad).clamp(0, h - 1)  # [n, h]
    cols = (ar_w.view(1, w) + shifts[:, 0:1] - pad).clamp(0, w - 1)  # [n, w]
    index = (rows.view(n, h, 1) * w + cols.view(n, 1, w)).view(n, 1, h * w).expand(n, c, h * w)
    return x.reshape(n, c, h * w).gather(2, index).view(n, c, h, w)


AUGMENTS = {"grid_sample": shift_grid_sample, "gather": shift_gather}


def augment(x: torch.Tensor, how: str) -> torch.Tensor:
    shifts = random_shifts(x.shape[0], x.device)
    if how == "grid_sample":
        return shift_grid_sample(x.float(), shifts)
    return shift_gather(x, shifts)


# ------------------------------------------------------------------------------------------
# The agent.


def sample_action(mean: torch.Tensor, std, clip: float | None = None) -> torch.Tensor:
    """DrQ-v2's truncated normal: mean + std * eps (eps clipped to +-clip if given), clamped to
    (-1, 1) with the gradient passed straight through."""
    noise = torch.randn_like(mean) * std
    if clip is not None:
        noise = noise.clamp(-clip, clip)
    x = mean + noise
    eps = 1e-6
    return x + (x.clamp(-1.0 + eps, 1.0 - eps) - x).detach()


@dataclasses.dataclass(frozen=True)
class Variant:
    name: str
    flags: frozenset

    @classmethod
    def parse(cls, name: str) -> Variant:
        spec = BEST if name == "best" else name
        flags = frozenset() if spec == "eager" else frozenset(spec.split("+"))
        unknown = flags - set(FLAGS)
        if unknown:
            raise ValueError(
                f"unknown variant flag(s) {sorted(unknown)} in {name!r}; valid: eager, best, "
                f"or '+'-joined {FLAGS}"
            )
        if {"fp32", "tf32"} <= flags:
            raise ValueError(f"{name!r}: fp32 and tf32 exclude each other")
        if "cudagraphs" in flags:
            flags = flags | {"compile"}
        return cls(name, flags)

    def __contains__(self, flag: str) -> bool:
        return flag in self.flags


def set_precision(variant: Variant) -> None:
    """TF32 switches for this variant: convs TF32 unless fp32; matmuls TF32 only with tf32.

    The legacy flags: torch 2.9+ also has `fp32_precision` attributes, but reading the legacy
    flags (as other code may) after setting those to "ieee" raises in torch 2.13."""
    torch.backends.cudnn.allow_tf32 = "fp32" not in variant
    torch.backends.cuda.matmul.allow_tf32 = "tf32" in variant


def precision_flags() -> dict:
    """What PyTorch reports for the TF32 switches now."""
    out = {}
    for name, get in (
        ("cudnn_allow_tf32", lambda: torch.backends.cudnn.allow_tf32),
        ("matmul_allow_tf32", lambda: torch.backends.cuda.matmul.allow_tf32),
        ("float32_matmul_precision", torch.get_float32_matmul_precision),
    ):
        try:
            out[name] = get()
        except RuntimeError as e:
            out[name] = f"unreadable: {str(e)[:80]}"
    return out


def precision_label(variant: Variant, device: torch.device) -> str:
    if device.type != "cuda":
        return "bf16 autocast" if "bf16" in variant else "fp32"
    conv = "fp32" if "fp32" in variant else "tf32"
    matmul = "tf32" if "tf32" in variant else "fp32"
    label = f"conv {conv}, matmul {matmul}"
    return "bf16 autocast (" + label + " elsewhere)" if "bf16" in variant else label


class Agent:
    """DrQ-v2 (+ DEAR's heads) in PyTorch; `update(batch, std)` is one learner update."""

    def __init__(
        self,
        method: str,
        action_dim: int,
        device: torch.device,
        variant: Variant,
        *,
        encoder: str = "pool",
        aug: str = "grid_sample",
        seed: int = 0,
    ):
        if method not in ("dear", "drqv2"):
            raise ValueError(f"unknown method {method!r}; valid: 'dear', 'drqv2'")
        if method == "dear" and encoder != "pool":
            raise ValueError("dear needs the pool encoder (its heads read the 4096 latent)")
        if aug not in AUGMENTS:
            raise ValueError(f"unknown augmentation {aug!r}; valid: {tuple(AUGMENTS)}")
        self.method, self.device, self.variant, self.aug = method, device, variant, aug
        torch.manual_seed(seed)
        # Initialised on the CPU (orthogonal_ runs a QR there), then moved.
        self.encoder = Encoder(encoder)
        repr_dim = self.encoder.out_dim
        self.actor = Actor(repr_dim, action_dim)
        self.critic = Critic(repr_dim, action_dim)
        self.decoder = MaskDecoder() if method == "dear" else None
        modules = [self.encoder, self.actor, self.critic] + ([self.decoder] if self.decoder else [])
        for m in modules:
            m.apply(init_weights)
            m.to(device)
        self.critic_target = copy.deepcopy(self.critic)
        for p in self.critic_target.parameters():
            p.requires_grad_(False)
        if "channels_last" in variant:
            for m in (self.encoder, self.decoder):
                if m is not None:
                    m.to(memory_format=torch.channels_last)
                    m.channels_last = True
        learner = list(self.encoder.parameters()) + list(self.critic.parameters())
        if self.decoder is not None:
            learner += list(self.decoder.parameters())
        adam = dict(lr=LR, fused=True) if "fused" in variant else dict(lr=LR)
        self.opt = torch.optim.Adam(learner, **adam)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), **adam)
        self._online = list(self.critic.parameters())
        self._target = list(self.critic_target.parameters())
        self.learner_loss = self._learner_loss
        self.actor_loss = self._actor_loss
        if "compile" in variant:
            mode = "reduce-overhead" if "cudagraphs" in variant else None
            self.learner_loss = torch.compile(self._learner_loss, mode=mode)
            self.actor_loss = torch.compile(self._actor_loss, mode=mode)

    def param_counts(self) -> dict[str, int]:
        out = {
            "encoder": count_params(self.encoder),
            "actor": count_params(self.actor),
            "critic": count_params(self.critic),
        }
        if self.decoder is not None:
            out["mask_decoder"] = count_params(self.decoder)
        out["total"] = sum(out.values())
        return out

    def autocast(self):
        if "bf16" in self.variant:
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _learner_loss(self, obs, action, reward, discount, next_obs, mask, std):
        """obs, next_obs uint8 [B, 9, 84, 84]; mask {0, 1} [B, 3, 84, 84] (dear); std a 0-d
        tensor. Returns (L, z detached, metrics)."""
        n = obs.shape[0]
        if self.decoder is not None:  # the mask takes its observation's shift
            both = augment(torch.cat([obs, mask.to(obs.dtype)], dim=1), self.aug)
            obs_aug, mask_aug = both[:, : obs.shape[1]], both[:, obs.shape[1] :]
        else:
            obs_aug, mask_aug = augment(obs, self.aug), None
        next_aug = augment(next_obs, self.aug)
        with self.autocast():
            z = self.encoder(obs_aug)
            with torch.no_grad():  # no target encoder: the online one, without gradient
                z_next = self.encoder(next_aug)
                next_action = sample_action(self.actor(z_next), std, STDDEV_CLIP)
                tq1, tq2 = self.critic_target(z_next, next_action)
                target = reward + discount * torch.minimum(tq1, tq2).float()
            q1, q2 = self.critic(z, action)
            critic_loss = F.mse_loss(q1.float(), target) + F.mse_loss(q2.float(), target)
            metrics = {"critic_loss": critic_loss.detach()}
            total = critic_loss
            if self.decoder is not None:
                half = z.shape[-1] // 2
                z_env, z_agent = z[:, :half], z[:, half:]
                logits = self.decoder(z_agent).float()
                # BCE summed over pixels and frames, averaged over the batch.
                mask_loss = (
                    F.binary_cross_entropy_with_logits(logits, mask_aug.float(), reduction="sum")
                    / n
                )
                cos = F.cosine_similarity(z_agent.float(), z_env.detach().float(), dim=-1, eps=1e-8)
                ortho_loss = cos.abs().mean()
                total = total + ALPHA * mask_loss + BETA * ortho_loss
                metrics.update(mask_loss=mask_loss.detach(), ortho_loss=ortho_loss.detach())
        return total, z.detach(), metrics

    def _actor_loss(self, z, std):
        with self.autocast():
            action = sample_action(self.actor(z), std, STDDEV_CLIP)
            q1, q2 = self.critic(z, action)
            return -torch.minimum(q1, q2).float().mean()

    def update(self, batch: dict, std: torch.Tensor) -> dict:
        loss, z, metrics = self.learner_loss(
            batch["obs"],
            batch["action"],
            batch["reward"],
            batch["discount"],
            batch["next_obs"],
            batch.get("mask"),
            std,
        )
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        # The actor reads the stopped features of the pre-update encoder, against the updated
        # critic (its backward also leaves gradients on the critic, cleared by the next update).
        actor_loss = self.actor_loss(z, std)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._target, self._online, TAU)
        metrics["actor_loss"] = actor_loss.detach()
        return metrics

    @torch.no_grad()
    def act(self, obs: np.ndarray, std: float, uniform: bool) -> np.ndarray:
        """One observation uint8 [9, 84, 84] -> action [|A|] (policy on the device every step;
        uniform actions replace it during exploration, as DrQ-v2 does)."""
        x = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        with self.autocast():
            mean = self.actor(self.encoder(x)).float()
        action = sample_action(mean, std)
        if uniform:
            action.uniform_(-1.0, 1.0)
        return action[0].cpu().numpy()


def random_batch(batch: int, action_dim: int, device, with_mask: bool, seed: int = 1) -> dict:
    g = torch.Generator(device=device).manual_seed(seed)
    img = lambda: torch.randint(  # noqa: E731
        0, 256, (batch, 3 * FRAME_STACK, 84, 84), dtype=torch.uint8, device=device, generator=g
    )
    out = {
        "obs": img(),
        "action": torch.rand(batch, action_dim, device=device, generator=g) * 2 - 1,
        "reward": torch.rand(batch, device=device, generator=g),
        "discount": torch.full((batch,), 0.99, device=device),
        "next_obs": img(),
    }
    if with_mask:
        out["mask"] = (torch.rand(batch, 3, 84, 84, device=device, generator=g) > 0.8).to(
            torch.uint8
        )
    return out


# ------------------------------------------------------------------------------------------
# update: timing.


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_update(
    method: str,
    encoder: str,
    batch: int,
    iters: int,
    warmup: int,
    variant_name: str,
    device: torch.device,
    aug: str,
    action_dim: int = 6,
) -> dict:
    variant = Variant.parse(variant_name)
    row = dict(
        method=method,
        encoder=encoder,
        variant=variant_name,
        flags=sorted(variant.flags),
        aug=aug,
        batch=batch,
        precision=precision_label(variant, device),
        iters=iters,
        warmup=warmup,
    )
    set_precision(variant)
    row["tf32_flags"] = precision_flags()
    if hasattr(torch, "_dynamo"):
        torch._dynamo.reset()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    agent = None
    try:
        agent = Agent(method, action_dim, device, variant, encoder=encoder, aug=aug)
        row["params"] = agent.param_counts()
        data = random_batch(batch, action_dim, device, with_mask=agent.decoder is not None)
        std = torch.tensor(0.2, device=device)
        _sync(device)
        t0 = time.perf_counter()
        metrics = agent.update(data, std)
        _sync(device)
        row["first_update_s"] = time.perf_counter() - t0  # includes compilation
        for _ in range(max(warmup - 1, 0)):
            metrics = agent.update(data, std)
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(iters):
            metrics = agent.update(data, std)
        _sync(device)
        row["ms_per_update"] = (time.perf_counter() - t0) / iters * 1e3
        row["metrics"] = {k: float(v) for k, v in metrics.items()}
        if device.type == "cuda":
            row["peak_mib"] = torch.cuda.max_memory_allocated(device) / 2**20
        row["status"] = "ok"
    except Exception as e:  # one variant failing must not stop the others
        row["status"] = "failed"
        row["error"] = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e) else ''}"
        row["traceback"] = traceback.format_exc()[-4000:]
    finally:
        del agent
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return row


def device_info(device: torch.device) -> dict:
    info = dict(
        torch=torch.__version__,
        device_type=device.type,
        python=platform.python_version(),
        cpu_threads=torch.get_num_threads(),
    )
    if device.type == "cuda":
        info.update(
            device=torch.cuda.get_device_name(device),
            cuda=torch.version.cuda,
            cudnn=torch.backends.cudnn.version(),
            cudnn_benchmark=torch.backends.cudnn.benchmark,
        )
    else:
        info["device"] = platform.processor() or platform.machine()
    return info


def merge_rows(path: pathlib.Path, section: str, info: dict, rows: list, keys: tuple) -> dict:
    """The JSON file's content with `section` holding `rows` plus the old rows of other settings."""
    result = {}
    if path.exists():
        try:
            result = json.loads(path.read_text())
        except (OSError, ValueError):
            result = {}
    key = lambda r: tuple(json.dumps(r.get(k), sort_keys=True) for k in keys)  # noqa: E731
    new = {key(r) for r in rows}
    old = [r for r in result.get(section, {}).get("rows", []) if key(r) not in new]
    result[section] = dict(info, rows=old + rows)
    return result


def _fmt(x, spec=".2f"):
    return "-" if x is None else format(x, spec)


def cmd_update(args) -> None:
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = True  # as DrQ-v2's training script sets it
    variants = list(args.variants)
    if device.type != "cuda":
        variants = [v for v in variants if "cudagraphs" not in Variant.parse(v)]
    rows = []
    printed_params = set()
    for batch in args.batch:
        for method in args.methods:
            for encoder in args.encoders if method == "drqv2" else ["pool"]:
                for aug in args.aug:
                    for v in variants:
                        r = time_update(
                            method,
                            encoder,
                            batch,
                            args.iters,
                            args.warmup,
                            v,
                            device,
                            aug,
                            args.action_dim,
                        )
                        rows.append(r)
                        head = f"{method}/{encoder} {v} aug={aug} batch={batch}"
                        if r["status"] != "ok":
                            print(f"{head}: FAILED {r['error']}", flush=True)
                            continue
                        print(
                            f"{head}: {r['ms_per_update']:.2f} ms per update "
                            f"(first update {r['first_update_s']:.1f} s)",
                            flush=True,
                        )
                        if (method, encoder) not in printed_params:
                            printed_params.add((method, encoder))
                            print(f"  parameters {method}/{encoder}: {r['params']}")
    info = device_info(device)
    print(
        f"\ndevice: {info['device']} ({device.type}), torch {info['torch']}, |A| "
        f"{args.action_dim}, {args.iters} timed updates after {args.warmup} warm-up"
    )
    print(
        "| method | encoder | batch | variant | aug | precision | ms per update | vs eager "
        "| first update s | peak MiB | params |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    group = lambda r: (r["method"], r["encoder"], r["batch"])  # noqa: E731
    eager = {
        group(r) + (r["aug"],): r["ms_per_update"]
        for r in rows
        if r["status"] == "ok" and r["variant"] == "eager"
    }
    for r in rows:
        head = (
            f"| {r['method']} | {r['encoder']} | {r['batch']} | {r['variant']} | {r['aug']} "
            f"| {r['precision']} "
        )
        if r["status"] != "ok":
            print(head + f"| failed: {r['error'][:80]} | | | | |")
            continue
        base = eager.get(group(r) + (r["aug"],))
        ratio = f"{base / r['ms_per_update']:.2f}x" if base else "-"
        print(
            head + f"| {r['ms_per_update']:.2f} | {ratio} | {r['first_update_s']:.1f} "
            f"| {_fmt(r.get('peak_mib'), '.0f')} | {r['params']['total']:,} |"
        )
    ok = [r for r in rows if r["status"] == "ok"]
    for key in sorted({group(r) for r in ok}):
        mine = [r for r in ok if group(r) == key]
        best = min(mine, key=lambda r: r["ms_per_update"])
        line = (
            f"best {key[0]}/{key[1]} batch {key[2]}: {best['ms_per_update']:.2f} ms "
            f"({best['variant']}, aug {best['aug']}, {best['precision']})"
        )
        full = [r for r in mine if "bf16" not in r["flags"]]
        if full and "bf16" in best["flags"]:
            b32 = min(full, key=lambda r: r["ms_per_update"])
            line += (
                f"; without bf16: {b32['ms_per_update']:.2f} ms "
                f"({b32['variant']}, aug {b32['aug']}, {b32['precision']})"
            )
        print(line)
    for r in rows:
        if r["status"] != "ok":
            print(
                f"skipped (failed): {r['method']}/{r['encoder']} batch {r['batch']} "
                f"{r['variant']}: {r['error']}"
            )
    path = pathlib.Path(args.out or f"benchmarks/results/torch_{device.type}.json")
    save_json(
        merge_rows(path, "update", info, rows, ("method", "encoder", "variant", "aug", "batch")),
        str(path),
    )


# ------------------------------------------------------------------------------------------
# pipeline: CPU MuJoCo + EGL rendering + GPU policy + updates, P processes.


class Replay:
    """Single frames [3, 84, 84] (and masks [84, 84]) of whole episodes, in arrival order.

    Index t holds frame t, the action taken at t and the reward that followed it; obs at t is
    the stack of frames t-2, t-1, t (repeating the episode's first frame), and a transition
    from t has the n-step return of rewards t .. t+n-1 and the next obs at t+n, only where
    t+n is in t's episode. No eviction: `capacity` must hold the whole run.
    """

    def __init__(self, capacity: int, action_dim: int, with_mask: bool, nstep: int, gamma: float):
        self.frames = np.zeros((capacity, 3, 84, 84), np.uint8)
        self.masks = np.zeros((capacity, 84, 84), np.uint8) if with_mask else None
        self.action = np.zeros((capacity, action_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.first = np.zeros(capacity, np.int64)  # index of the episode's first frame
        self.valid = np.zeros(capacity, np.int64)  # transitions that may be sampled
        self.num_valid = 0
        self.size = 0
        self.episode_start = 0
        self.nstep, self.gamma = nstep, gamma

    def _put(self, frame: np.ndarray, mask: np.ndarray | None) -> int:
        i = self.size
        if i >= len(self.frames):
            raise RuntimeError(f"replay full ({len(self.frames)} frames)")
        self.frames[i] = frame
        if self.masks is not None:
            self.masks[i] = mask
        self.first[i] = self.episode_start
        self.size = i + 1
        return i

    def start_episode(self, frame, mask) -> None:
        self.episode_start = self.size
        self._put(frame, mask)

    def add(self, action, reward: float, frame, mask) -> None:
        t = self.size - 1
        self.action[t] = action
        self.reward[t] = reward
        i = self._put(frame, mask)
        if i - self.nstep >= self.episode_start:
            self.valid[self.num_valid] = i - self.nstep
            self.num_valid += 1  # after the data it points at is written (the sampler reads it)

    def sample_into(self, rng: np.random.Generator, out: dict) -> None:
        """Fill `out` (numpy arrays, e.g. views of pinned tensors) with a uniform batch."""
        n = out["reward"].shape[0]
        idx = self.valid[rng.integers(0, self.num_valid, n)]
        back = np.arange(1 - FRAME_STACK, 1)  # -2, -1, 0
        first = self.first[idx][:, None]
        stack = np.maximum(idx[:, None] + back, first)  # [n, 3]
        next_stack = np.maximum(idx[:, None] + self.nstep + back, first)
        np.take(self.frames, stack, axis=0, out=out["obs"].reshape(n, FRAME_STACK, 3, 84, 84))
        np.take(
            self.frames, next_stack, axis=0, out=out["next_obs"].reshape(n, FRAME_STACK, 3, 84, 84)
        )
        if self.masks is not None:
            np.take(self.masks, stack, axis=0, out=out["mask"])
        np.take(self.action, idx, axis=0, out=out["action"])
        ret = np.zeros(n, np.float32)
        for k in range(self.nstep):
            ret += self.gamma**k * self.reward[idx + k]
        out["reward"][:] = ret
        out["discount"][:] = self.gamma**self.nstep  # dm_control's discount is 1 within episodes


class BatchFeeder:
    """Batches from the replay to the device: a background thread samples into two pinned host
    buffers (the role of the reference's DataLoader workers); the copy to the device is
    asynchronous, and a buffer is refilled only after its copy has finished (a CUDA event)."""

    def __init__(self, replay: Replay, batch: int, device, *, threaded: bool = True, seed: int = 0):
        self.replay, self.device, self.threaded = replay, device, threaded
        self.rng = np.random.default_rng(seed)
        pin = device.type == "cuda"
        shapes = {
            "obs": ((batch, 3 * FRAME_STACK, 84, 84), torch.uint8),
            "next_obs": ((batch, 3 * FRAME_STACK, 84, 84), torch.uint8),
            "action": ((batch, replay.action.shape[1]), torch.float32),
            "reward": ((batch,), torch.float32),
            "discount": ((batch,), torch.float32),
        }
        if replay.masks is not None:
            shapes["mask"] = ((batch, FRAME_STACK, 84, 84), torch.uint8)
        self.buffers = [
            {k: torch.empty(s, dtype=d, pin_memory=pin) for k, (s, d) in shapes.items()}
            for _ in range(2)
        ]
        self.free: queue.Queue = queue.Queue()
        self.ready: queue.Queue = queue.Queue()
        for k in range(2):
            self.free.put((k, None))
        self.thread = None
        if threaded:
            self.thread = threading.Thread(target=self._loop, daemon=True)
            self.thread.start()

    def _fill(self, k: int, event) -> None:
        if event is not None:
            event.synchronize()
        self.replay.sample_into(self.rng, {n: t.numpy() for n, t in self.buffers[k].items()})

    def _loop(self) -> None:
        while True:
            k, event = self.free.get()
            if k is None:
                return
            try:
                self._fill(k, event)
                self.ready.put(k)
            except BaseException as e:  # surfaces in get()
                self.ready.put(e)
                return

    def get(self) -> dict:
        if self.threaded:
            k = self.ready.get()
            if isinstance(k, BaseException):
                raise RuntimeError("replay sampling thread failed") from k
        else:
            k, event = self.free.get()
            self._fill(k, event)
        host = self.buffers[k]
        if self.device.type == "cuda":
            out = {n: t.to(self.device, non_blocking=True) for n, t in host.items()}
            event = torch.cuda.Event()
            event.record()
        else:
            out = {n: t.clone() for n, t in host.items()}
            event = None
        self.free.put((k, event))
        return out

    def close(self) -> None:
        if self.thread is not None:
            self.free.put((None, None))
            self.thread.join(timeout=10)


def run_pipeline(rank: int, cfg: dict, barrier=None) -> dict:
    """One process of the pipeline; returns its measurement."""
    import mujoco

    from envs import camera, dmc, labels
    from envs.physics import CpuPhysics

    device = torch.device(cfg["device"])
    torch.backends.cudnn.benchmark = True
    variant = Variant.parse(cfg["variant"])
    set_precision(variant)
    task = dmc.TASKS[cfg["task"]]
    model = task.physics_model()
    action_dim = model.nu
    action_repeat = cfg["action_repeat"]
    physics = CpuPhysics(
        model,
        task.make_reward(model),
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=action_repeat,
    )
    episode_steps = task.frames_per_episode(model) // action_repeat
    start_data = mujoco.MjData(model)
    rng = np.random.RandomState(cfg["seed"] + rank)

    render_model = task.render_model()
    render_data = mujoco.MjData(render_model)
    renderer = mujoco.Renderer(render_model, 84, 84)
    with_mask = cfg["method"] == "dear"
    tables = labels.label_tables(
        render_model, task.agent_geom_ids(render_model), task.floor_geom_ids(render_model)
    )

    def picture(qpos):
        """RGB [3, 84, 84] and the agent mask [84, 84] (dear), as two renders like the
        reference's pixel observation and segmentation calls."""
        render_data.qpos[:] = qpos
        camera.kinematics(render_model, render_data)
        renderer.update_scene(render_data, camera=task.camera)
        rgb = renderer.render().transpose(2, 0, 1)
        mask = None
        if with_mask:
            renderer.enable_segmentation_rendering()
            renderer.update_scene(render_data, camera=task.camera)
            seg = renderer.render()
            renderer.disable_segmentation_rendering()
            mask = (labels.labels_from_segmentation(seg, tables) == labels.LABEL_AGENT).astype(
                np.uint8
            )
        return rgb, mask

    agent = Agent(
        cfg["method"], action_dim, device, variant, encoder=cfg["encoder"], aug=cfg["aug"]
    )
    total_frames = cfg["warmup_frames"] + cfg["frames"]
    # Enough for the whole run: the warm-up may stretch by the two updates it waits for.
    max_steps = total_frames // action_repeat + 4 * cfg["update_every"] + 2
    capacity = max_steps + max_steps // episode_steps + 2
    replay = Replay(capacity, action_dim, with_mask, cfg["nstep"], cfg["discount"])
    feeder = None
    timers = dict.fromkeys(("reset", "act", "update", "physics", "render", "replay"), 0.0)
    seed_steps = cfg["seed_frames"] // action_repeat
    explore_steps = cfg["explore_steps"]

    def new_episode():
        dmc.episode_start(task, model, start_data, rng)
        state = physics.init(start_data.qpos[None, None], start_data.qvel[None, None])
        rgb, mask = picture(start_data.qpos)
        replay.start_episode(rgb, mask)
        return state, [rgb] * FRAME_STACK

    step = updates = 0
    frames = 0
    t_start = None
    state, stack = new_episode()
    episode_step = 0
    try:
        while True:
            ready = frames >= cfg["warmup_frames"] and (frames < cfg["seed_frames"] or updates >= 2)
            if t_start is None and ready:
                if barrier is not None:
                    barrier.wait()
                timers = dict.fromkeys(timers, 0.0)
                measured_updates = updates
                wall_start = time.time()  # comparable across processes
                t_start = time.perf_counter()
                start_frames = frames
            if t_start is not None and frames - start_frames >= cfg["frames"]:
                break
            t0 = time.perf_counter()
            if episode_step == episode_steps:
                state, stack = new_episode()
                episode_step = 0
            t1 = time.perf_counter()
            std = 1.0 + min(step / cfg["std_steps"], 1.0) * (0.1 - 1.0)
            action = agent.act(np.concatenate(stack, axis=0), std, uniform=step < explore_steps)
            t2 = time.perf_counter()
            if step >= seed_steps and step % cfg["update_every"] == 0:
                if feeder is None:
                    feeder = BatchFeeder(
                        replay, cfg["batch"], device, threaded=cfg["prefetch"], seed=rank
                    )
                metrics = agent.update(feeder.get(), torch.tensor(std, device=device))
                metrics = {k: v.item() for k, v in metrics.items()}  # as the reference logs
                updates += 1
            t3 = time.perf_counter()
            state, reward = physics.step(state, action[None, None])
            t4 = time.perf_counter()
            rgb, mask = picture(state.qpos[0, 0])
            t5 = time.perf_counter()
            replay.add(action, float(reward[0, 0]), rgb, mask)
            stack = stack[1:] + [rgb]
            t6 = time.perf_counter()
            for name, dt in zip(timers, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5)):
                timers[name] += dt
            step += 1
            episode_step += 1
            frames += action_repeat
    finally:
        if feeder is not None:
            feeder.close()
        renderer.close()
    elapsed = time.perf_counter() - t_start
    measured_frames = frames - start_frames
    return dict(
        rank=rank,
        frames=measured_frames,
        seconds=elapsed,
        fps=measured_frames / elapsed,
        updates=updates - measured_updates,
        ms_per_agent_step={
            k: v / (measured_frames / action_repeat) * 1e3 for k, v in timers.items()
        },
        params=agent.param_counts(),
        start=wall_start,
        end=wall_start + elapsed,
    )


def _pipeline_worker(rank: int, cfg: dict, barrier, results) -> None:
    # JAX (the envs' reward functions) stays on the CPU: it must not take GPU memory.
    os.environ["JAX_PLATFORMS"] = "cpu"
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        results.put((rank, run_pipeline(rank, cfg, barrier)))
    except BaseException:
        if barrier is not None:
            barrier.abort()
        results.put((rank, {"error": traceback.format_exc()}))


def run_procs(procs: int, cfg: dict) -> list[dict]:
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(procs)
    results = ctx.Queue()
    workers = [
        # Not daemonic: torch.compile may start compile workers of its own.
        ctx.Process(target=_pipeline_worker, args=(r, cfg, barrier, results))
        for r in range(procs)
    ]
    for w in workers:
        w.start()
    out: dict[int, dict] = {}
    try:
        while len(out) < procs:
            try:
                rank, res = results.get(timeout=5)
                out[rank] = res
            except queue.Empty:
                if not any(w.is_alive() for w in workers) and results.empty():
                    missing = sorted(set(range(procs)) - set(out))
                    codes = [w.exitcode for w in workers]
                    raise RuntimeError(
                        f"pipeline workers {missing} exited without a result (exit codes {codes})"
                    ) from None
    finally:
        for w in workers:
            w.join(timeout=30)
            if w.is_alive():
                w.terminate()
    return [out[r] for r in range(procs)]


def cmd_pipeline(args) -> None:
    device = torch.device(args.device)
    if args.method == "dear" and args.encoder != "pool":
        raise SystemExit("dear needs --encoder pool")
    cfg = dict(
        device=str(device),
        task=args.task,
        method=args.method,
        encoder=args.encoder,
        variant=args.variant,
        aug=args.aug,
        batch=args.batch,
        nstep=args.nstep,
        discount=0.99,
        action_repeat=2,
        frames=args.frames,
        warmup_frames=args.warmup_frames,
        seed_frames=args.seed_frames,
        explore_steps=args.seed_frames // 2,
        update_every=2,
        std_steps=500_000,
        prefetch=not args.no_prefetch,
        seed=args.seed,
    )
    rows = []
    for p in args.procs:
        print(f"pipeline: {p} process(es) of {args.method} on {args.task} ...", flush=True)
        t0 = time.perf_counter()
        per_proc = run_procs(p, cfg)
        errors = [r["error"] for r in per_proc if "error" in r]
        row = dict(cfg, procs=p, wall_s=time.perf_counter() - t0)
        if errors:
            row.update(status="failed", error=errors[0][-4000:])
            print(f"  FAILED:\n{errors[0]}", flush=True)
        else:
            fps = [r["fps"] for r in per_proc]
            span = max(r["end"] for r in per_proc) - min(r["start"] for r in per_proc)
            row.update(
                status="ok",
                per_process=per_proc,
                fps_per_process=float(np.mean(fps)),
                aggregate_fps=float(np.sum(fps)),
                aggregate_fps_wall=sum(r["frames"] for r in per_proc) / span,
                s_per_1000_frames=float(np.mean([1000.0 / f for f in fps])),
            )
            split = {
                k: float(np.mean([r["ms_per_agent_step"][k] for r in per_proc]))
                for k in per_proc[0]["ms_per_agent_step"]
            }
            row["ms_per_agent_step"] = split
            print(
                f"  {row['aggregate_fps']:.0f} frames/s in all, {row['fps_per_process']:.0f} per "
                f"process ({row['s_per_1000_frames']:.2f} s per 1000 frames); ms per agent step: "
                + ", ".join(f"{k} {v:.2f}" for k, v in split.items()),
                flush=True,
            )
        rows.append(row)
    info = device_info(device)
    print(
        f"\ndevice: {info['device']} ({device.type}), torch {info['torch']}; {args.task}, "
        f"{args.method} ({args.encoder} encoder), variant {args.variant}, batch {args.batch}, "
        f"{args.frames} frames measured per process after {args.warmup_frames} (+2 updates)"
    )
    print(
        "| procs | frames/s per process | s per 1000 frames | aggregate frames/s "
        "| aggregate (wall) | act ms | update ms | physics ms | render ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["status"] != "ok":
            print(f"| {r['procs']} | failed | | | | | | | |")
            continue
        s = r["ms_per_agent_step"]
        print(
            f"| {r['procs']} | {r['fps_per_process']:.0f} | {r['s_per_1000_frames']:.2f} "
            f"| {r['aggregate_fps']:.0f} | {r['aggregate_fps_wall']:.0f} | {s['act']:.2f} "
            f"| {s['update']:.2f} | {s['physics']:.2f} | {s['render']:.2f} |"
        )
    path = pathlib.Path(args.out or f"benchmarks/results/torch_{device.type}.json")
    keys = ("task", "method", "encoder", "variant", "aug", "batch", "procs", "device")
    save_json(merge_rows(path, "pipeline", info, rows, keys), str(path))


# ------------------------------------------------------------------------------------------


def main(argv=None) -> None:
    default_device = "cuda" if torch.cuda.is_available() else "cpu"
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)

    up = sub.add_parser("update", help="time the learner update per variant")
    up.add_argument("--methods", nargs="+", default=["dear"], choices=["dear", "drqv2"])
    up.add_argument(
        "--encoders",
        nargs="+",
        default=["pool"],
        choices=["pool", "plain"],
        help="drqv2's encoder(s); dear always uses pool",
    )
    up.add_argument("--batch", nargs="+", type=int, default=[256])
    up.add_argument("--iters", type=int, default=20)
    up.add_argument("--warmup", type=int, default=5, help="untimed updates first (>= 1)")
    up.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS))
    up.add_argument("--aug", nargs="+", default=["grid_sample"], choices=list(AUGMENTS))
    up.add_argument("--action-dim", type=int, default=6)
    up.add_argument("--device", default=default_device)
    up.add_argument("--out", default=None)

    pp = sub.add_parser("pipeline", help="env frames/s of the reference-shaped training loop")
    pp.add_argument("--procs", nargs="+", type=int, default=[1])
    pp.add_argument("--frames", type=int, default=4000, help="measured frames per process")
    pp.add_argument("--warmup-frames", type=int, default=4000)
    pp.add_argument("--seed-frames", type=int, default=4000)
    pp.add_argument("--task", default="walker-walk")
    pp.add_argument("--method", default="dear", choices=["dear", "drqv2"])
    pp.add_argument("--encoder", default="pool", choices=["pool", "plain"])
    pp.add_argument("--variant", default="eager")
    pp.add_argument("--aug", default="grid_sample", choices=list(AUGMENTS))
    pp.add_argument("--batch", type=int, default=512, help="512: walker's batch")
    pp.add_argument("--nstep", type=int, default=1, help="1: walker's n-step")
    pp.add_argument("--no-prefetch", action="store_true", help="sample in the main thread")
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument("--device", default=default_device)
    pp.add_argument("--out", default=None)

    args = parser.parse_args(argv)
    if args.command == "update":
        for v in args.variants:
            Variant.parse(v)  # refuse unknown flags before any timing
        args.warmup = max(args.warmup, 1)
        cmd_update(args)
    else:
        Variant.parse(args.variant)
        cmd_pipeline(args)


if __name__ == "__main__":
    main()
