"""DEAR on kitchen-light (turn the light switch on)."""

import functools

from configs.kitchen import make

get_config = functools.partial(make, "light", "dear")
