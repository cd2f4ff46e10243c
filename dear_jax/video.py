"""Eval videos: RGB | true agent mask | predicted mask side by side, as mp4 via OpenCV."""

from __future__ import annotations

import os
import pathlib

import numpy as np

SEPARATOR_RGB = (255, 0, 255)  # magenta: absent from the mask panels' grey levels


def _check_frames(name: str, x: np.ndarray, ndim: int) -> None:
    if x.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dims, got shape {x.shape}")


def side_by_side(
    rgb: np.ndarray,  # uint8 [T,H,W,3]
    true_mask: np.ndarray,  # [T,H,W] in {0,1}
    pred_mask: np.ndarray,  # [T,H,W] in {0,1} or probabilities in [0,1]
    *,
    upscale: int = 2,
    separator: int = 2,
) -> np.ndarray:  # uint8 [T, H*upscale, 3*W*upscale + 2*separator, 3]
    """Three panels per frame: the RGB frame, the true mask (white on black), the predicted mask
    (probability as grey level), each enlarged `upscale` times (nearest), split by `separator`
    magenta columns."""
    rgb, true_mask, pred_mask = np.asarray(rgb), np.asarray(true_mask), np.asarray(pred_mask)
    _check_frames("rgb", rgb, 4)
    _check_frames("true_mask", true_mask, 3)
    _check_frames("pred_mask", pred_mask, 3)
    if rgb.shape[-1] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 [T,H,W,3], got {rgb.dtype} {rgb.shape}")
    if true_mask.shape != rgb.shape[:3] or pred_mask.shape != rgb.shape[:3]:
        raise ValueError(
            f"masks must be [T,H,W] = {rgb.shape[:3]}, got true_mask {true_mask.shape} and "
            f"pred_mask {pred_mask.shape}"
        )
    if upscale < 1 or separator < 0:
        raise ValueError(f"need upscale >= 1 and separator >= 0, got {upscale} and {separator}")
    for name, m in (("true_mask", true_mask), ("pred_mask", pred_mask)):
        if m.size and (np.nanmin(m) < 0 or np.nanmax(m) > 1):
            raise ValueError(
                f"{name} values must lie in [0, 1] (got {np.nanmin(m)}..{np.nanmax(m)}); "
                "pass probabilities, not logits"
            )

    def grey(mask):  # [T,H,W] in [0,1] -> uint8 [T,H,W,3]
        levels = np.rint(np.nan_to_num(mask.astype(np.float32)) * 255).astype(np.uint8)
        return np.repeat(levels[..., None], 3, axis=-1)

    t, h, _, _ = rgb.shape
    sep = np.empty((t, h * upscale, separator, 3), np.uint8)
    sep[...] = SEPARATOR_RGB
    panels = []
    for panel in (rgb, grey(true_mask), grey(pred_mask)):
        panels += [panel.repeat(upscale, axis=1).repeat(upscale, axis=2), sep]
    return np.concatenate(panels[:-1], axis=2)


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: int = 30) -> pathlib.Path:
    """Write uint8 RGB frames [T,H,W,3] as an mp4 (mp4v) at `path`; returns the path.

    The file appears complete or not at all: it is written under a temporary name and renamed.
    """
    import cv2

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 [T,H,W,3], got {frames.dtype} {frames.shape}")
    if len(frames) == 0:
        raise ValueError("no frames to write")
    path = pathlib.Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"video path must end in .mp4, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.mp4")  # cv2 picks the muxer by suffix
    _, h, w, _ = frames.shape
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(
            f"OpenCV could not open an mp4v video writer for {tmp} ({w}x{h} at {fps} fps); "
            f"check that the folder is writable and that this OpenCV build has FFmpeg "
            f"(cv2.getBuildInformation() 'Video I/O')"
        )
    try:
        for frame in frames:
            writer.write(np.ascontiguousarray(frame[..., ::-1]))  # OpenCV wants BGR
    finally:
        writer.release()
    os.replace(tmp, path)
    return path
