"""DrQ-v2 on finger-spin, Distracting Control Suite (medium, static)."""

import functools

from configs.base import make

get_config = functools.partial(make, "finger", "drqv2", distraction="medium")
