"""SE(2) helpers on ``(..., 3)`` pose arrays (x, y, yaw): angle wrapping and body-frame composition."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.floating[Any]]


def wrap_angle(a: npt.ArrayLike) -> F64:
    """Angles to (-pi, pi]."""
    a = np.asarray(a, dtype=np.float64)
    return -((-a + np.pi) % (2 * np.pi) - np.pi)


def compose(poses: npt.ArrayLike, delta: npt.ArrayLike) -> F64:
    """``x (+) u``: apply body-frame increments ``delta (..., 3)`` to poses ``(..., 3)``."""
    x = np.asarray(poses, dtype=np.float64)
    d = np.asarray(delta, dtype=np.float64)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    return np.stack(
        [x[..., 0] + c * d[..., 0] - s * d[..., 1], x[..., 1] + s * d[..., 0] + c * d[..., 1],
         wrap_angle(x[..., 2] + d[..., 2])],
        axis=-1,
    )


def between(a: npt.ArrayLike, b: npt.ArrayLike) -> F64:
    """``a^-1 b``: poses ``b (..., 3)`` in the frames of poses ``a (..., 3)``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)
