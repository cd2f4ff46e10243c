"""TED on ball_in_cup-catch, Distracting Control Suite (medium, static)."""

import functools

from configs.base import make

get_config = functools.partial(make, "cup", "ted", distraction="medium")
