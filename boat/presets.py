"""Typed hull presets `otter`, `heron`, `wamv`: Fossen's 3-DOF parameters, windage, thrusters, inner loop.

Frame: x forward, y to port, yaw counter-clockwise (the contract's); the CG sits x_g ahead of the origin.
Each value says where it comes from: [S] ../shared/reference/sea-physics.md (its sources: Fossen's
`otter.py`, VRX, heron_controller, ArduPilot), [D] derived from [S] values (the arithmetic is in docs/sea.md,
"Hull dynamics"), [C] our choice, with its reason. `preset(name, overrides)` gives a checked copy.
"""

from __future__ import annotations

import math

from pydantic import Field, model_validator

from agent.config import ConfigError, NonNegativeFloat, PositiveFloat, StrictModel, deep_merge, parse_mapping

G = 9.81   # m/s^2, as otter.py


class Hull(StrictModel):
    """M = M_RB + M_A and D(nu_r) of Fossen's 3-DOF model (surge, sway, yaw)."""

    mass: PositiveFloat = Field(description="m, rigid-body mass with payload (kg)")
    yaw_inertia: PositiveFloat = Field(description="I_z about the body origin (kg m^2)")
    x_g: float = Field(0.0, ge=-10.0, le=10.0, description="x of the centre of gravity ahead of the origin (m)")
    added_mass_surge: NonNegativeFloat = Field(description="-X_udot (kg)")
    added_mass_sway: NonNegativeFloat = Field(description="-Y_vdot (kg)")
    added_mass_yaw: NonNegativeFloat = Field(description="-N_rdot (kg m^2)")
    surge_damping: NonNegativeFloat = Field(description="-X_u, linear surge damping (N s/m)")
    sway_damping: NonNegativeFloat = Field(description="-Y_v, linear sway damping (N s/m)")
    yaw_damping: NonNegativeFloat = Field(description="-N_r, linear yaw damping (N m s)")
    surge_damping_quadratic: NonNegativeFloat = Field(0.0, description="-X_|u|u (N s^2/m^2)")
    sway_damping_quadratic: NonNegativeFloat = Field(0.0, description="-Y_|v|v (N s^2/m^2)")
    yaw_damping_quadratic: NonNegativeFloat = Field(0.0, description="-N_|r|r (N m s^2)")


class Windage(StrictModel):
    """What the environment's wind and wave loads need of the boat."""

    length: PositiveFloat = Field(description="length overall (m)")
    beam: PositiveFloat = Field(description="beam (m)")
    mass: PositiveFloat = Field(description="mass (kg)")
    frontal_area: PositiveFloat = Field(description="area above water seen from ahead (m^2)")
    lateral_area: PositiveFloat = Field(description="area above water seen from the side (m^2)")


class Thrusters(StrictModel):
    """Two thrusters pushing along x at y = +half_beam (port) and y = -half_beam (starboard)."""

    half_beam: PositiveFloat = Field(description="distance of each thruster from the centreline (m)")
    max_forward: PositiveFloat = Field(description="largest forward thrust of one thruster (N)")
    max_reverse: PositiveFloat = Field(description="largest reverse thrust of one thruster, as a magnitude (N)")
    time_constant: PositiveFloat = Field(description="first-order lag of the thrust behind its demand (s)")


class InnerLoop(StrictModel):
    """Speed PI + feed-forward and turn-rate PID + feed-forward (after ArduPilot's AR_AttitudeControl)."""

    speed_p: NonNegativeFloat = Field(description="surge force per m/s of speed error (N s/m)")
    speed_i: NonNegativeFloat = Field(description="surge force per m of integrated speed error (N/m)")
    speed_imax: NonNegativeFloat = Field(description="bound on the speed integrator's force (N)")
    speed_ff: NonNegativeFloat = Field(description="feed-forward surge force per m/s of demanded speed (N s/m)")
    speed_ff_quadratic: NonNegativeFloat = Field(0.0, description="feed-forward force per (m/s)^2 (N s^2/m^2)")
    speed_ff_accel: NonNegativeFloat = Field(0.0, description="feed-forward force per m/s^2 of demand ramp (kg)")
    accel_max: PositiveFloat = Field(description="largest change of the demanded speed (m/s^2)")
    max_speed: PositiveFloat = Field(description="demanded speed bound, forward (m/s)")
    max_reverse_speed: NonNegativeFloat = Field(description="demanded speed bound, astern (m/s)")
    rate_p: NonNegativeFloat = Field(description="yaw moment per rad/s of rate error (N m s)")
    rate_i: NonNegativeFloat = Field(description="yaw moment per rad of integrated rate error (N m)")
    rate_d: NonNegativeFloat = Field(0.0, description="yaw moment per rad/s^2 of rate-error change (N m s^2)")
    rate_imax: NonNegativeFloat = Field(description="bound on the rate integrator's moment (N m)")
    rate_ff: NonNegativeFloat = Field(description="feed-forward yaw moment per rad/s of demanded rate (N m s)")
    rate_ff_quadratic: NonNegativeFloat = Field(0.0, description="feed-forward moment per (rad/s)^2 (N m s^2)")
    rate_ff_accel: NonNegativeFloat = Field(0.0, description="feed-forward moment per rad/s^2 of ramp (kg m^2)")
    rate_max: PositiveFloat = Field(description="demanded yaw-rate bound (rad/s)")
    rate_accel_max: PositiveFloat = Field(description="largest change of the demanded yaw rate (rad/s^2)")
    d_filter: PositiveFloat = Field(10.0, description="low-pass corner of the rate error's derivative (Hz)")
    timeout: PositiveFloat = Field(0.5, description="a command older than this gives zero thrust (s)")


class BoatPreset(StrictModel):
    name: str = Field(min_length=1)
    hull: Hull
    windage: Windage
    thrusters: Thrusters
    inner_loop: InnerLoop

    @model_validator(mode="after")
    def _positive_definite(self) -> BoatPreset:
        h = self.hull
        m22, m23, m33 = h.mass + h.added_mass_sway, h.mass * h.x_g, h.yaw_inertia + h.added_mass_yaw
        if m22 * m33 - m23 * m23 <= 0:
            raise ValueError("the mass matrix is not positive definite (x_g too large for the yaw inertia)")
        return self


def _otter() -> BoatPreset:
    # [S] otter.py: hull 55 kg + payload 25 kg; hull CG (0.2, 0, -0.2) m, payload at (0, 0, -0.35) m
    hull_mass, payload = 55.0, 25.0
    total = hull_mass + payload
    x_g = 0.2 * hull_mass / total                                  # [D] 0.1375 m
    iz_cg = hull_mass * (0.25 * 2.0) ** 2 + hull_mass * x_g ** 2   # [D] R66 = 0.25 L, as otter.py's Ig
    iz = iz_cg + total * x_g ** 2                                  # [D] about the origin: 16.30 kg m^2
    u_max = 6 * 0.5144                                             # [S] 6 kn = 3.086 m/s
    m33 = iz + 1.7 * iz_cg                                         # [D] with N_rdot = -1.7 Ig: 41.44
    draft = total / 1025 / (2 * 0.4 * 0.25 * 2.0)                  # [D] otter.py's T: 0.195 m
    cross = 0.5 * 1026 * draft * 1.004                             # [D] cross-flow: rho T C_D (Hoerner, B/2T 0.64)
    forward, reverse = 0.5 * 24.4 * G, 0.5 * 13.6 * G              # [S] bollard 239 N / 133 N for the pair
    hull = Hull(mass=total, yaw_inertia=iz, x_g=x_g,
                added_mass_surge=0.1 * hull_mass,                 # [S] X_udot = -0.1 m
                added_mass_sway=1.5 * hull_mass,                  # [S] Y_vdot = -1.5 m
                added_mass_yaw=1.7 * iz_cg,                       # [S] N_rdot = -1.7 I_z
                surge_damping=24.4 * G / u_max,                   # [S] X_u = -24.4 g / U_max = -77.6
                sway_damping=0.0,                                 # [S] Y_v = 0
                yaw_damping=m33 / 1.0,                            # [S] N_r = -M_33 / T_yaw, T_yaw = 1 s
                sway_damping_quadratic=cross * 2.0,               # [D] cross-flow drag at r = 0: rho T C_D L / 2
                yaw_damping_quadratic=10 * m33 + cross * 2.0 ** 4 / 32)  # [S] 10 N_r |r| r, + cross-flow
    return BoatPreset(
        name="otter", hull=hull,
        windage=Windage(length=2.0, beam=1.08, mass=total,           # [S]
                        frontal_area=1.08 * 0.4, lateral_area=2.0 * 0.4),  # [C] 0.4 m of windage height
        thrusters=(thrusters := Thrusters(half_beam=0.395, max_forward=forward, max_reverse=reverse,  # [S]
                                          time_constant=0.1)),      # [S] propeller T_n 0.1 s
        inner_loop=_tuned(hull, thrusters, max_speed=3.0, max_reverse_speed=1.0, accel_max=1.0, rate_max=0.3,
                          rate_accel_max=2.09),  # [S] ArduPilot: ATC_ACCEL_MAX 1 m/s^2, 120 deg/s^2
    )


def _heron() -> BoatPreset:
    mass, length = 28.0, 1.35                                       # [S]
    iz = mass * (0.25 * length) ** 2                                # [C] R66 = 0.25 L, as the Otter's
    m33 = iz * 2.7                                                  # [C] N_rdot = -1.7 I_z, as the Otter's
    forward, reverse = 35.0, 20.0                                   # [S] per thruster
    drag = (2 * forward - 10) / 1.7                                 # [S] heron_controller's speed map: 35.3
    hull = Hull(mass=mass, yaw_inertia=iz, x_g=0.0,
                added_mass_surge=0.1 * mass, added_mass_sway=1.5 * mass, added_mass_yaw=1.7 * iz,  # [C]
                surge_damping=drag,
                surge_damping_quadratic=(2 * forward - drag * 1.7) / 1.7 ** 2,  # [D] full thrust at 1.7 m/s
                sway_damping=2.5 * mass,                          # [C] sway time constant 1 s
                yaw_damping=m33 / 1.0)                            # [C] T_yaw = 1 s, as the Otter's
    return BoatPreset(
        name="heron", hull=hull,
        windage=Windage(length=length, beam=0.98, mass=mass,        # [C] beam: Clearpath's 0.98 m
                        frontal_area=0.98 * 0.3, lateral_area=length * 0.3),  # [C] 0.3 m windage height
        thrusters=(thrusters := Thrusters(half_beam=0.381 / 2, max_forward=forward,  # [S] 0.381 m apart
                                          max_reverse=reverse, time_constant=0.1)),  # [C] as the Otter's
        inner_loop=_tuned(hull, thrusters, max_speed=1.7, max_reverse_speed=0.5,
                          accel_max=1.0, rate_max=0.5, rate_accel_max=2.09),  # [S] 0.5 rad/s
    )


def _wamv() -> BoatPreset:
    mass, iz = 180.0, 446.0                                         # [S] VRX
    x_u, x_uu, u_max = 51.3, 72.4, 7.71667                          # [S] VRX
    thrust = (x_u + x_uu * u_max) * u_max / 2                       # [S] VRX max_thrust_cmd: 2354 N
    hull = Hull(mass=mass, yaw_inertia=iz, x_g=0.0,
                added_mass_surge=0.0, added_mass_sway=0.0, added_mass_yaw=0.0,  # [S] VRX xDotU etc. 0
                surge_damping=x_u, surge_damping_quadratic=x_uu, sway_damping=40.0,  # [S]
                yaw_damping=400.0)                                # [S] nR 400, nRR 0
    return BoatPreset(
        name="wamv", hull=hull,
        windage=Windage(length=4.9, beam=2.4, mass=mass,            # [S] VRX hull 4.9 m; beam 2.4 m
                        frontal_area=2.4 * 0.8, lateral_area=4.9 * 0.8),  # [C] 0.8 m windage height
        thrusters=(thrusters := Thrusters(half_beam=1.027, max_forward=thrust,  # [S] VRX, symmetric
                                          max_reverse=thrust, time_constant=0.2)),  # [C] in sea-physics' 0.1-1 s
        inner_loop=_tuned(hull, thrusters, max_speed=7.5, max_reverse_speed=2.0,
                          accel_max=1.0, rate_max=1.0, rate_accel_max=2.09),
    )


def _tuned(hull: Hull, thrusters: Thrusters, **limits: float) -> InnerLoop:
    """Gains by one rule for every preset: the proportional gain that gives the linearised loop (hull
    M s + d behind the thruster lag T s + 1) a damping ratio of 0.8, k = (M + T d)^2 / (4 0.8^2 T M) - d; the
    integrator's time 1 s and its bound the thrusters' whole range (ArduPilot's IMAX 1); feed-forward the
    hull's own damping, linear and quadratic, as ArduPilot's CRUISE_SPEED / CRUISE_THROTTLE calibrate it, and
    its inertia times the demand's ramp (docs/sea.md, "Inner loop")."""
    def gain(m: float, d: float) -> float:
        return max((m + lag * d) ** 2 / (4 * 0.64 * lag * m) - d, 0.0)

    lag = thrusters.time_constant
    m11, m33 = hull.mass + hull.added_mass_surge, hull.yaw_inertia + hull.added_mass_yaw
    speed_p, rate_p = gain(m11, hull.surge_damping), gain(m33, hull.yaw_damping)
    force, moment = 2 * thrusters.max_forward, thrusters.half_beam * (thrusters.max_forward + thrusters.max_reverse)
    return InnerLoop(speed_p=speed_p, speed_i=speed_p, speed_imax=force, speed_ff=hull.surge_damping,
                     speed_ff_quadratic=hull.surge_damping_quadratic, speed_ff_accel=m11,
                     rate_p=rate_p, rate_i=rate_p, rate_imax=moment, rate_ff=hull.yaw_damping,
                     rate_ff_quadratic=hull.yaw_damping_quadratic, rate_ff_accel=m33, **limits)


PRESETS: dict[str, BoatPreset] = {p.name: p for p in (_otter(), _heron(), _wamv())}


def preset(name: str, overrides: dict | None = None) -> BoatPreset:
    """The preset `name` with `overrides` deep-merged onto it and checked; a ConfigError names a bad field."""
    if name not in PRESETS:
        raise ConfigError(f"unknown hull preset {name!r}; known: {', '.join(sorted(PRESETS))}")
    base = PRESETS[name]
    if not overrides:
        return base
    return parse_mapping(BoatPreset, deep_merge(base.model_dump(), overrides), f"hull preset {name}")


def steady_speed(hull: Hull, thrust: float) -> float:
    """u with X_u u + X_|u|u u^2 = thrust (thrust >= 0): the straight-run force balance."""
    a, b = hull.surge_damping_quadratic, hull.surge_damping
    return thrust / b if a == 0 else (-b + math.sqrt(b * b + 4 * a * thrust)) / (2 * a)
