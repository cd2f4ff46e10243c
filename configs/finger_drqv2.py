"""DrQ-v2 on finger-spin, no distraction."""

import functools

from configs.base import make

get_config = functools.partial(make, "finger", "drqv2", distraction="none")
