"""Rendering backends behind one interface.

``Renderer(camera, pattern, settings).render(R, t, rng)`` returns the (H, W) uint8 image of the
board at ``cam_from_board = (R, t)``. The default backend is :mod:`.analytic` (exact ray-plane
geometry through the camera model, anti-aliased, fast).
"""

from .analytic import AnalyticRenderer, PixelRays, RenderSettings, gaussian_noise

__all__ = ["AnalyticRenderer", "PixelRays", "RenderSettings", "gaussian_noise"]
