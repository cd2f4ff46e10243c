"""Pixel labels: the four classes, and the rule that turns MuJoCo's segmentation into them.

Each pixel is BACKGROUND, FLOOR, AGENT or OTHER. The render workers (envs/render.py) draw MuJoCo's
segmentation pass beside each frame and map it through the tables made here; the masks
(envs/masks.py) and the compositing of distractions (envs/distractions.py) read the labels.

Agent rule (docs/method.md, Masks), per segmentation object type:
- geom: AGENT if its id is one of the task's agent geoms, FLOOR if one of its floor geoms,
  else OTHER.
- site, tendon: OTHER, always. The mask is exactly "pixels of agent geoms", as the reference
  computes it from MuJoCo's geom segmentation. ball_in_cup's string (a tendon 3 mm wide, a pixel
  at most at 84x84) and visible sites (the cup's 5 mm site, finger's spinner tip and target
  sites) are therefore scenery, never mask; tests/test_render.py checks both cases.
- anything else drawn (decor, skins, flexes): OTHER. Pixels where nothing is drawn: BACKGROUND.
"""

import mujoco
import numpy as np

LABEL_BACKGROUND, LABEL_FLOOR, LABEL_AGENT, LABEL_OTHER = 0, 1, 2, 3
LABEL_NAMES = ("background", "floor", "agent", "other")


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
