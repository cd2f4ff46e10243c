"""SEAR on walker-walk, no distraction."""

import functools

from configs.base import make

get_config = functools.partial(make, "walker", "sear", distraction="none")
