"""Everything one vessel's core carries from one tick to the next.

`step` reads and updates a `VesselState`; nothing else persists between ticks (no globals, no clock), so a
state saved after tick k and the inputs of tick k+1 give exactly what the original run gave
(`agent/core/snapshot.py` writes and reads it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agent.core.estimators.plkf import PLKF
from agent.core.neighbours import History, NeighbourPrior, NeighbourTrack


@dataclass
class Health:
    """What the core refused or did out of the ordinary, counted since the start (published in `status`)."""

    bad_odometry: int = 0
    bad_bearing: int = 0
    bad_ranges: int = 0
    bad_shares: int = 0
    bad_obstacles: int = 0
    stops: int = 0
    neighbours_dropped: int = 0
    neighbours_joined: int = 0
    non_finite_commands: int = 0
    target_estimates_gated: int = 0
    ranges_late: int = 0          # came after the pair filter had moved past their time
    ranges_unpaired: int = 0      # the neighbour's odometry of their time never came
    ranges_gap: int = 0           # their time fell in a gap of an odometry history
    priors_stale: int = 0         # initial estimates too old to carry to now
    priors_refused: int = 0       # initial estimates the measured range contradicts
    separation_stops: int = 0     # ticks the separation guard stopped or cut the surge
    target_restarts: int = 0      # target filter started again: its estimate went behind the bearing
    target_ranges_fixed: int = 0  # a target range unobserved (a start without estimates) taken from neighbours

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class OwnMotion:
    """The vessel's own velocity over the last odometry interval, for (33) and the PLKF input of (24)."""

    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    stamp: float | None = None
    position: np.ndarray | None = None
    yaw_rate: float = 0.0      # the boat's yaw rate as the agent models it (control.yaw_lag > 0)
    # w of the leeway model sway = w . n(heading) (control.leeway_time_constant > 0; control/leeway.py)
    leeway: np.ndarray = field(default_factory=lambda: np.zeros(2))
    # c of the set model: surge over ground less through the water = c . t(heading) (control.set_time_constant)
    set: np.ndarray = field(default_factory=lambda: np.zeros(2))
    surge_command: float = 0.0   # the last surge commanded (m/s), with control.set_time_constant > 0
    surge: float = 0.0         # the boat's surge through the water as the agent models it (control.surge_lag)
    # the leeway's displacement summed over the odometry's intervals (target.leeway_variance > 0; target.py)
    drift: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass
class VesselState:
    vessel: str
    own: History                                  # own cumulative odometry by stamp
    motion: OwnMotion
    tracks: dict[str, NeighbourTrack]             # one pair filter and its bookkeeping per neighbour
    priors: dict[str, NeighbourPrior]             # initial estimates of neighbours not yet started
    tracker: PLKF | None                          # the target filter, once there is a target estimate
    phase: float | None                           # phi_i of (28); None until the first tick sets it
    health: Health
    # own antenna's arm vector R(psi) a by stamp, as `own` (agent/core/antenna.py); empty with no lever arm
    own_arms: History = field(default_factory=lambda: History(2))
    # the last raw ranges (stamp s, range m) to each id ranged, tracked or not: the range guard's (step.py)
    recent_ranges: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
