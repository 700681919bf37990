"""Angles in the one convention every package uses: radians in (-pi, pi], wrapped the same way everywhere."""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(angle):
    """The angle (rad) moved by a multiple of 2 pi into (-pi, pi]; floats give floats, arrays give arrays.

    pi stays pi and -pi becomes pi, so the seam has one side only; an angle already in range comes back
    bit for bit unchanged.
    """
    if isinstance(angle, np.ndarray):
        turns = np.ceil((angle - math.pi) / TWO_PI)  # 0 for every angle already in (-pi, pi]
        wrapped = angle - turns * TWO_PI
        # Rounding in the subtraction can land a hair outside the interval; one more turn puts it back.
        wrapped = np.where(wrapped > math.pi, wrapped - TWO_PI, wrapped)
        return np.where(wrapped <= -math.pi, wrapped + TWO_PI, wrapped)
    angle = float(angle)
    wrapped = angle - math.ceil((angle - math.pi) / TWO_PI) * TWO_PI
    if wrapped > math.pi:
        wrapped -= TWO_PI
    elif wrapped <= -math.pi:
        wrapped += TWO_PI
    return wrapped
