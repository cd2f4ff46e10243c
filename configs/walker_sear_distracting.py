"""SEAR on walker-walk, Distracting Control Suite (medium, static)."""

import functools

from configs.base import make

get_config = functools.partial(make, "walker", "sear", distraction="medium")
