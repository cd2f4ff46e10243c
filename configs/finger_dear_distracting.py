"""DEAR on finger-spin, Distracting Control Suite (medium, static)."""

import functools

from configs.base import make

get_config = functools.partial(make, "finger", "dear", distraction="medium")
