"""How much the relative motion of a pair has told its filter: the observability analysis of the paper,
(36)-(42), kept up to date per pair.

The paper. p_ij is observable from the range pairs (12) and the displacements (15) when the Gramian

    Phi_ij,l = sum_{k=l}^{l+N-1} delta_ij,k delta_ij,k^T > 0                                        (41)

over a window of N steps, which holds when the relative velocity is persistently exciting, (37)-(39).

What is computed. The relative path D_m at the range epochs m (the measured relative displacement delta~_ij
of (15), summed from the track's start), and its spread over a window that forgets with time constant tau:

    w_m = exp(-(t - t_m) / tau),   D_bar = sum_m w_m D_m / sum_m w_m,
    S = sum_m w_m (D_m - D_bar)(D_m - D_bar)^T / sum_m w_m.

Reading it (the verdict, `verdict`):
- "unobservable": lambda_max(S) < w_min^2. No relative motion to speak of (parallel motion at one
  velocity, or both still): the ranges say how far the neighbour is, not in which direction.
- "mirror-ambiguous": lambda_min(S) < w_min^2 <= lambda_max(S). The relative path is a straight line: p and
  its reflection across that line explain every range equally well, (12) sees only the component of p
  along the line (Phi has rank one).
- "observable": both eigenvalues at least w_min^2.

More: docs/estimation.md §10, `agent/core/observability.py`.
"""

from __future__ import annotations

import math

from pydantic import Field

from agent.config import PositiveFloat, StrictModel

OBSERVABLE = "observable"
MIRROR_AMBIGUOUS = "mirror-ambiguous"
UNOBSERVABLE = "unobservable"
VERDICTS = (OBSERVABLE, MIRROR_AMBIGUOUS, UNOBSERVABLE)


class ObservabilityParams(StrictModel):
    """The window and the threshold of the pair observability (docs/estimation.md, "Observability")."""

    window: PositiveFloat = Field(
        10.0, description="tau (s): time constant of the exponential forgetting of the relative path's spread")
    # Narrower in one direction: a line (mirror-ambiguous); in both: no motion (unobservable).
    min_width: PositiveFloat = Field(
        0.25, description="w_min (m): RMS width of the relative path below which a direction counts as flat")


def eigenvalues(s11: float, s12: float, s22: float) -> tuple[float, float]:
    """(lambda_min, lambda_max) of the symmetric 2x2 [[s11, s12], [s12, s22]], closed form; lambda_min is
    kept at 0 or above (a spread is positive semi-definite, round-off aside)."""
    half_trace = 0.5 * (s11 + s22)
    radius = math.hypot(0.5 * (s11 - s22), s12)
    return max(half_trace - radius, 0.0), half_trace + radius


def verdict(low: float, high: float, min_width: float) -> str:
    """The pair's observability from the eigenvalues (m^2) of its path spread S and the width w_min (m)."""
    floor = min_width * min_width
    if high < floor:
        return UNOBSERVABLE
    if low < floor:
        return MIRROR_AMBIGUOUS
    return OBSERVABLE


class PathSpread:
    """The exponentially forgotten spread S of a pair's relative path at its range epochs (module docstring),
    kept as running sums: a weighted mean and the weighted scatter about it, updated in the stable
    one-pass form (West 1979) so a path far from its origin loses no precision."""

    __slots__ = ("c11", "c12", "c22", "mean_x", "mean_y", "weight", "x", "y")

    def __init__(self) -> None:
        self.x = self.y = 0.0                 # D, the relative path since the track started (m)
        self.weight = 0.0                     # sum_m w_m: the ranges in the window, forgetting counted
        self.mean_x = self.mean_y = 0.0       # D_bar
        self.c11 = self.c12 = self.c22 = 0.0  # sum_m w_m (D_m - D_bar)(D_m - D_bar)^T

    def add(self, dx: float, dy: float, elapsed: float, tau: float) -> None:
        """A range epoch `elapsed` seconds after the previous one, the pair having moved by (dx, dy) since:
        the window forgets by exp(-elapsed / tau), and D moved by (dx, dy) enters it with weight 1."""
        # In locals, each field read and written once: the same operations, per neighbour and range.
        x, y = self.x + dx, self.y + dy
        forget = math.exp(-elapsed / tau) if elapsed > 0.0 else 1.0
        kept = forget * self.weight
        self.weight = weight = kept + 1.0
        mean_x, mean_y = self.mean_x, self.mean_y
        ex, ey = x - mean_x, y - mean_y
        share = kept / weight                 # (D - D_bar_old)(D - D_bar_new)^T = share * e e^T
        self.x, self.y, self.mean_x, self.mean_y = x, y, mean_x + ex / weight, mean_y + ey / weight
        self.c11 = forget * self.c11 + share * ex * ex
        self.c12 = forget * self.c12 + share * ex * ey
        self.c22 = forget * self.c22 + share * ey * ey

    def eigenvalues(self) -> tuple[float, float]:
        """(lambda_min, lambda_max) of S (m^2); (0, 0) before two range epochs."""
        if self.weight <= 0.0:
            return 0.0, 0.0
        w = self.weight
        return eigenvalues(self.c11 / w, self.c12 / w, self.c22 / w)

    # ----- saving and restoring (agent/core/snapshot.py) -----
    def export_state(self) -> list[float]:
        return [self.x, self.y, self.weight, self.mean_x, self.mean_y, self.c11, self.c12, self.c22]

    def restore_state(self, values: list[float]) -> None:
        (self.x, self.y, self.weight, self.mean_x, self.mean_y,
         self.c11, self.c12, self.c22) = (float(v) for v in values)
