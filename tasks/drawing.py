"""A tiny numpy rasteriser for ``render_mode="rgb_array"`` of the simulated tasks.

No OpenGL, no matplotlib: shapes are painted into an ``(H, W, 3)`` ``uint8`` array by testing
pixel centres against the shape in world coordinates (metres). Good enough for videos of a
cart with one or two poles, and cheap (a few hundred microseconds per frame).
"""

from __future__ import annotations

import numpy as np

Color = tuple[int, int, int]


class Canvas:
    """An RGB image with a world-coordinate window ``[x_min, x_max] x [y_min, y_max]`` (metres).

    Args:
        x_range: ``(x_min, x_max)`` world window, metres.
        y_range: ``(y_min, y_max)`` world window, metres.
        width: image width in pixels; the height follows from the window's aspect ratio.
        background: RGB fill.
    """

    def __init__(
        self,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        width: int = 480,
        background: Color = (255, 255, 255),
    ) -> None:
        (self.x_min, self.x_max), (self.y_min, self.y_max) = x_range, y_range
        self.scale = width / (self.x_max - self.x_min)  # pixels per metre
        height = max(1, int(round((self.y_max - self.y_min) * self.scale)))
        self.image = np.empty((height, width, 3), dtype=np.uint8)
        self.image[:] = background
        # world coordinates of the pixel centres
        self._xs = self.x_min + (np.arange(width) + 0.5) / self.scale
        self._ys = self.y_max - (np.arange(height) + 0.5) / self.scale

    def _window(self, x0: float, x1: float, y0: float, y1: float):
        """Pixel slices covering the world box, and the pixel-centre grids inside it."""
        h, w = self.image.shape[:2]
        c0 = int(np.clip(np.floor((x0 - self.x_min) * self.scale), 0, w))
        c1 = int(np.clip(np.ceil((x1 - self.x_min) * self.scale) + 1, 0, w))
        r0 = int(np.clip(np.floor((self.y_max - y1) * self.scale), 0, h))
        r1 = int(np.clip(np.ceil((self.y_max - y0) * self.scale) + 1, 0, h))
        rows, cols = slice(r0, r1), slice(c0, c1)
        gx, gy = np.meshgrid(self._xs[cols], self._ys[rows])
        return rows, cols, gx, gy

    def _paint(self, rows: slice, cols: slice, mask: np.ndarray, color: Color) -> None:
        if mask.size:
            self.image[rows, cols][mask] = color

    def rectangle(self, cx: float, cy: float, half_w: float, half_h: float, color: Color) -> None:
        """Axis-aligned filled rectangle centred at ``(cx, cy)``."""
        rows, cols, gx, gy = self._window(cx - half_w, cx + half_w, cy - half_h, cy + half_h)
        self._paint(rows, cols, (np.abs(gx - cx) <= half_w) & (np.abs(gy - cy) <= half_h), color)

    def segment(self, p: tuple[float, float], q: tuple[float, float], thickness: float, color: Color) -> None:
        """Filled capsule of the given ``thickness`` (metres) from ``p`` to ``q``."""
        r = 0.5 * thickness
        rows, cols, gx, gy = self._window(
            min(p[0], q[0]) - r, max(p[0], q[0]) + r, min(p[1], q[1]) - r, max(p[1], q[1]) + r
        )
        dx, dy = q[0] - p[0], q[1] - p[1]
        length2 = dx * dx + dy * dy
        if length2 > 0.0:
            s = np.clip(((gx - p[0]) * dx + (gy - p[1]) * dy) / length2, 0.0, 1.0)
        else:
            s = np.zeros_like(gx)
        ex, ey = gx - (p[0] + s * dx), gy - (p[1] + s * dy)
        self._paint(rows, cols, ex * ex + ey * ey <= r * r, color)

    def disc(self, cx: float, cy: float, radius: float, color: Color) -> None:
        """Filled circle."""
        self.segment((cx, cy), (cx, cy), 2.0 * radius, color)
