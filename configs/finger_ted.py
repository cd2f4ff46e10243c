"""TED on finger-spin, no distraction."""

import functools

from configs.base import make

get_config = functools.partial(make, "finger", "ted", distraction="none")
