"""The bounds every input is held to, and the error a rig file that breaks one raises.

They keep every input within what one machine can render and calibrate; beyond them a run would
end in a MemoryError or an overflow rather than in a result. The exchange formats and the web app
hold what they read to the same bounds.
"""

from __future__ import annotations


# Upper bounds that keep every input within what one machine can render and calibrate; beyond
# them a run would end in a MemoryError or an overflow rather than in a result.
MAX_IMAGE_SIDE = 16384


MAX_IMAGE_PIXELS = 64_000_000


MAX_CAMERAS = 64


MAX_FRAMES = 10_000


MAX_PATTERN_COUNT = 100  # squares, rows or columns of a board


MAX_BOARD_MM = 1200.0  # the board's outline, per side (its texture is written at 10 px/mm)


MAX_BLUR_PX = 50.0


# A lens and a position: the same bounds hold for every camera read from an exchange file.
MAX_FOCAL_PX = 1e6


MAX_SKEW_PX = 1e4


#: fx / fy (or fy / fx) at most: anamorphic lenses reach 2, a sensor's pixels are near square.
MAX_PIXEL_ASPECT = 10.0


MAX_DISTORTION = 1e4


MAX_DISTANCE_MM = 1e6

#: A camera's clock offset, ms: a minute covers a consumer camera started by hand.
MAX_TIME_OFFSET_MS = 60_000.0


MAX_FILE_BYTES = 1 << 20


MAX_NESTING = 64


#: Values (scalars, lists, mappings) a YAML document may hold once its aliases are expanded: a
#: studio of 64 cameras with explicit per-frame poses is under 100,000.
MAX_NODES = 1_000_000


class ConfigError(ValueError):
    """A rig file that cannot be used; the message names the file and the field."""
