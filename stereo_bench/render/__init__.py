"""Rendering backends behind one interface.

``Renderer(camera, pattern, settings, ...).render(R, t, rng, velocity)`` returns the (H, W) uint8
image of the board at ``cam_from_board = (R, t)``. The default backend is :mod:`.analytic`
(exact ray-plane geometry through the camera model, anti-aliased, fast), which carries the
imaging model of :mod:`.imaging`; :mod:`.blender` renders with Cycles in a worker process and
shares the same ground truth (the rig file's ``renderer.kind`` chooses, dataset.write_dataset
builds them).
"""

from .analytic import AnalyticRenderer, PixelRays, RenderSettings
from .texels import noise_draws

__all__ = ["AnalyticRenderer", "PixelRays", "RenderSettings", "noise_draws"]
