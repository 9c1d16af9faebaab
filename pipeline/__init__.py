"""pipeline layer."""

import reachwatch.systems  # noqa: F401,E402  (first: process-wide settings before torch)
