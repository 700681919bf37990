"""Typed parameters of the agent, with the paper's Table I as defaults (strict models: unknown keys are errors)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import Field, model_validator

from agent.config import NonNegativeFloat, PositiveFloat, StrictModel, commented_yaml
from agent.core.estimators.registry import RelativeEstimationParams


class TargetEstimationParams(StrictModel):
    """Pseudo-linear Kalman filter of the target, Sec. III-B."""

    # Table I's 0.01 must also absorb the vessel's own turns, which this filter takes as a known input, and
    # with it the range collapses (docs/estimation.md, PLKF; docs/fleet.md §4).
    process_noise: PositiveFloat = Field(
        1e-5,
        description="Q_o = value * I_4 per step (Table I: 0.01)",
    )
    # 'measured' is (25) as printed, biased towards the target; 'predicted' is the instrumental-variable
    # form of Nguyen and Dogancay 2018.
    gain_bearing: Literal["predicted", "measured"] = Field(
        "predicted",
        description="bearing the PLKF gain (25) is built from: 'predicted' (instrumental variable) or 'measured'",
    )
    bearing_variance: PositiveFloat = Field(1e-4, description="R_b = value * I_2 (Table I)")
    initial_covariance: PositiveFloat = Field(1.0, description="P_io,0 = value * I_4 (Table I)")
    min_range: PositiveFloat = Field(
        0.1, description="floor on the predicted range used to scale R_z, so R_z never vanishes"
    )
    initial_range_guess: PositiveFloat = Field(
        10.0, description="range assumed along the first bearing when no initial target estimate is given (m)"
    )
    # The wind's leeway as two more states, seen in the bearings to a ground-fixed target (plkf_leeway.py):
    # for water-referenced odometry (a speed log), which does not see the hull's sideways drift.
    leeway_variance: NonNegativeFloat = Field(
        0.0, description="initial variance of the leeway w ((m/s)^2 per axis), from the bearings; 0: none")
    leeway_process_noise: PositiveFloat = Field(
        1e-6, description="Q of the leeway w per step ((m/s)^2 per axis), with leeway_variance > 0")
    # Measured harmful with the w the bearings give (docs/sea.md, (h)): each vessel's error in w drifts its
    # odometry away from its neighbours', and the pair filters trust the odometry.
    leeway_odometry: bool = Field(
        False, description="with leeway_variance > 0, the pair filters and the share take the odometry plus N w")


class ControlParams(StrictModel):
    """Formation control and obstacle avoidance, Sec. IV (Table I)."""

    radius: PositiveFloat = Field(5.0, description="r*_io, circumnavigation radius (m)")
    yaw_rate: Annotated[float, Field(allow_inf_nan=False)] = Field(
        math.pi / 30, description="omega*_i, desired yaw rate (rad/s); sign = direction (+: counter-clockwise "
                                  "from above)")
    safety_distance: PositiveFloat = Field(3.0, description="d_s (m)")
    max_correction_yaw_rate: PositiveFloat = Field(math.pi / 3, description="U_omega_c (rad/s)")
    max_speed: PositiveFloat = Field(5.0, description="U_v (m/s)")
    max_target_speed: PositiveFloat = Field(0.5, description="U_vo (m/s)")
    max_formation_speed: PositiveFloat = Field(1.5, description="U_vf (m/s)")
    max_avoidance_speed: PositiveFloat = Field(0.7, description="U_vs (m/s)")
    gain_neighbour: PositiveFloat = Field(1.5, description="kappa_ij")
    gain_target: PositiveFloat = Field(0.9, description="kappa_io")
    # Table I's value for n = 4; keeps the sampled loop damped for large fleets
    # (agent/core/control/formation.py).
    neighbour_gain_cap: PositiveFloat | None = Field(
        4.5,
        description="cap on the sum of kappa_ij over the neighbours; null for (33) as written",
    )
    avoidance_gain: PositiveFloat = Field(1.7, description="k_1")
    avoidance_spread: PositiveFloat = Field(0.5, description="k_2")
    min_clearance: NonNegativeFloat = Field(
        1.0, description="safety filter: closest a vessel may come to an obstacle point (m); see avoidance.py"
    )
    clearance_rate: PositiveFloat = Field(
        1.0, description="safety filter: closing speed allowed per metre of clearance left (1/s)"
    )
    # Closer than this by the ranges to a neighbour it has not localised, the vessel does not move.
    min_separation: NonNegativeFloat = Field(
        3.0, description="the separation guard keeps the vessels at least this far apart (m)")
    # Room for the estimate's error. The guard keeps apart from the localised neighbours and from those
    # whose pair covariance has a trace within this squared (agent/core/control/separation.py).
    separation_margin: NonNegativeFloat = Field(
        0.5, description="the guard keeps a neighbour's estimated distance at least min_separation + this (m)")
    # rate * dt at most 1/2, so that a pair never closes past the guard's distance in a period.
    separation_rate: PositiveFloat = Field(
        2.0, description="closing speed the guard allows towards a neighbour per metre beyond its distance (1/s)")
    safety_filter: bool = Field(True, description="apply the safety filter after (35); false: (35) alone")
    oscillator_gain: PositiveFloat = Field(
        1.0, description="K of (28): K_m = K for m <= n/2, 0 above (the paper leaves K_m open)"
    )
    # The boat as it is (docs/sea.md (What the agent does)): all inert by default, the paper's kinematic boat.
    heading_gain: PositiveFloat | None = Field(
        None, description="K of the heading correction omega^c = K (heading error) (1/s); None: 1/dt, (31)")
    yaw_lag: NonNegativeFloat = Field(
        0.0, description="the boat's yaw-rate time constant tau_r (s) the heading loop compensates; 0: none")
    heading_bandwidth: PositiveFloat = Field(
        2.0, description="w_n of the lag-compensated heading loop (rad/s), with yaw_lag > 0")
    heading_damping: PositiveFloat = Field(0.8, description="zeta of the lag-compensated heading loop")
    boat_max_yaw_rate: PositiveFloat | None = Field(
        None, description="the boat's turn-rate limit (rad/s): no command exceeds it; None: no limit")
    boat_max_astern: PositiveFloat | None = Field(
        None, description="the boat's astern speed limit (m/s): no command goes astern faster; None: max_speed")
    leeway_time_constant: NonNegativeFloat = Field(
        0.0, description="time constant of the leeway model the command steers against (s); 0: none")
    set_time_constant: NonNegativeFloat = Field(
        0.0, description="time constant of the set model (a current along the heading) the command steers "
                         "against (s); 0: none")
    surge_lag: NonNegativeFloat = Field(
        0.0, description="the boat's surge time constant tau_u (s): the separation guard adds its coasting "
                         "distance |u| tau_u; 0: none")

    @model_validator(mode="after")
    def _circling(self) -> ControlParams:
        if self.yaw_rate == 0.0:
            raise ValueError("yaw_rate must not be 0: a fleet that does not turn does not circle")
        return self


class FleetParams(StrictModel):
    """How a vessel keeps track of its neighbours."""

    neighbour_timeout: PositiveFloat = Field(
        1.0, description="a neighbour silent for longer than this (s) leaves the formation"
    )
    history_ticks: int = Field(50, ge=2, le=100_000, description="odometry and ranges kept per neighbour")
    # Covariance intersection, so the two vessels of a pair agree (agent/core/fusion.py, docs/fleet.md §3);
    # false: each vessel keeps its own, as in the paper.
    fuse_shared_estimates: bool = Field(
        True,
        description="fuse each neighbour's shared estimate of p_ji with our p_ij (false: as in the paper)",
    )
    # Moved to this vessel through p_ij and fused by covariance intersection: bearings from several angles
    # triangulate (docs/fleet.md §3).
    fuse_target_estimates: bool = Field(
        True,
        description="fuse the neighbours' target estimates with our own (false: as in the paper)",
    )
    # The positions at the range's time are interpolated; a range in a longer gap is counted, not used.
    max_odometry_gap: PositiveFloat = Field(
        0.5, description="widest gap between the two odometry samples around a range's time (s)")
    # That odometry comes in the neighbour's share, typically a tick later; then the range counts as unpaired.
    range_wait: PositiveFloat = Field(
        1.0, description="how long a range waits for the neighbour's odometry of its time (s)")
    # An initial estimate older than the odometry kept is stale too: it would start the pair filter from a
    # past position.
    prior_max_age: PositiveFloat = Field(
        5.0, description="an initial estimate older than this at the first tick is stale and not used (s)")
    # A range-only start (r^2 I) is above it.
    localised_trace: PositiveFloat = Field(
        2.0, description="trace of P_ij at most which a neighbour steers the formation and lends its target (m^2)")
    # The chi-square 99.9 % point for 4 degrees of freedom: a good estimate is dropped once in a thousand,
    # and beyond it a faulty one is more likely than noise. Left out estimates are counted.
    target_gate: PositiveFloat = Field(
        18.47,
        description="squared Mahalanobis distance from ours beyond which a neighbour's target is not fused",
    )
    # Measured on the join scenario, 10 runs (docs/fleet.md §7): 4 left 2 runs with pair errors of 3 m, 1
    # settles all 10 with half the error, 0.25 waits too long and falls back to the far worse range prior.
    target_route_factor: PositiveFloat = Field(
        1.0,
        description="a joiner's pair starts from both target estimates once trace(both covs) <= this * P_io,0",
    )


class AgentParams(StrictModel):
    """Everything one vessel's agent needs; Table I of the paper by default."""

    dt: PositiveFloat = Field(0.1, description="sampling period (s) (Table I)")
    fleet: FleetParams = FleetParams()
    relative: RelativeEstimationParams = RelativeEstimationParams()
    target: TargetEstimationParams = TargetEstimationParams()
    control: ControlParams = ControlParams()

    @model_validator(mode="after")
    def _guard_holds(self) -> AgentParams:
        if self.control.separation_rate * self.dt > 0.5:
            raise ValueError(f"control.separation_rate * dt must be at most 0.5 (is "
                             f"{self.control.separation_rate * self.dt:g}): both vessels of a pair closing "
                             "faster would pass the separation guard's distance within one period")
        if self.target.leeway_variance > 0.0 and self.control.leeway_time_constant > 0.0:
            raise ValueError("target.leeway_variance and control.leeway_time_constant are two leeway models "
                             "(from the bearings, for a speed log; from the odometry, for a DVL): choose one")
        return self


if __name__ == "__main__":
    print("# Parameters of one vessel's agent: the paper's Table I (Liu et al., Sec. VI).")
    print("# Every key is optional; a file need only name what it changes. Unknown keys are errors.")
    print("# Regenerate with: python -m agent.core.params > configs/agent.yaml")
    print(commented_yaml(AgentParams()))
