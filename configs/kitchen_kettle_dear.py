"""DEAR on kitchen-kettle (move the kettle to the top-left burner)."""

import functools

from configs.kitchen import make

get_config = functools.partial(make, "kettle", "dear")
