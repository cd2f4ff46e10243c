"""DEAR on ball_in_cup-catch, no distraction."""

import functools

from configs.base import make

get_config = functools.partial(make, "cup", "dear", distraction="none")
