"""Sensor error models beyond the paper's (5)-(9): odometry, yaw-rate gyro, UWB antennas, a tilting camera.

Each model is a frozen pydantic object chosen in the world config (`WorldConfig.sensors`), and pure numeric
kernels below it that broadcast over vessels. docs/sea.md (Sensors): the equations, figures and sources.

- Odometry `paper`: (5), kept in world.py as it was. `water_log_compass`: a speed log (scale error k, dead
  band) and a compass (per-vessel bias b, white noise): p += s dt [cos psi_c, sin psi_c], s = (1 + k) u_r + n;
  with `sway: hull`, p moves by R(psi_c) (s, v_hat) dt on the arc between readings (boat/sway.py).
  `dvl_gyro`: bottom-track velocity over ground in the body frame, (1 + k) v_b + n, dead-reckoned with a
  gyro-integrated heading psi_g += dpsi + (b + n_r) dt, b += sigma_K sqrt(dt) w (bias random walk).
- UWB: ranges between antennas at a lever arm (forward, left, up) from the hull's centre, which turn with
  heading, roll and pitch; dropouts and positive outliers with probability logistic in range.
- Camera: the azimuth a level-assuming camera measures when tilted by roll and pitch, and optionally the
  bearing referred to the vessel's own heading reading (its compass or gyro) rather than the true heading.

Angles are rad in the kernels, degrees in the config where datasheets give degrees (fields say which).
Every draw comes from the caller's generator in the order the world documents; kernels draw nothing.
Roll is positive starboard down, pitch positive bow up (Fossen's convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Field, model_validator

from agent.angles import wrap_angle
from agent.config import NonNegativeFloat, PositiveFloat, StrictModel, deep_merge
from boat import sway as sway_kernel

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
LeverArm = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
DEG = math.pi / 180.0
ARW_UNIT = DEG / 60.0            # 1 deg/sqrt(h) in rad/sqrt(s)


# --- the kernels ------------------------------------------------------------------------------------------

def speed_log(surge_through_water, scale, dead_band, noise):
    """A speed log's reading: 0 where |u_r| < dead band (the wheel does not turn), else (1 + k) u_r + n."""
    u = np.asarray(surge_through_water, dtype=float)
    return np.where(np.abs(u) < dead_band, 0.0, (1.0 + np.asarray(scale)) * u + np.asarray(noise))


def dead_reckon(position, speed, heading, dt):
    """p + s dt [cos psi, sin psi]: one step of dead reckoning with a speed and a heading reading."""
    speed, heading = np.asarray(speed, dtype=float), np.asarray(heading, dtype=float)
    step = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * (speed * dt)[..., None]
    return np.asarray(position, dtype=float) + step


def rotate(vectors, angle):
    """Each 2-vector (last axis) turned by `angle` (rad, anticlockwise)."""
    v, angle = np.asarray(vectors, dtype=float), np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def gyro_heading_step(heading, bias, turn, rate_noise, bias_step, dt):
    """One gyro step: psi_g + dpsi + (b + n_r) dt and b + db, with dpsi the true turn over the step (rad),
    n_r the white rate noise (rad/s) and db the bias's random-walk increment (rad/s)."""
    return (np.asarray(heading) + np.asarray(turn) + (np.asarray(bias) + np.asarray(rate_noise)) * dt,
            np.asarray(bias) + np.asarray(bias_step))


def gyro_heading_variance(turn_on_std, rate_random_walk, angle_random_walk, dt, steps):
    """Closed form of Var(psi_g - psi) after N steps of `gyro_heading_step` (rad^2): with b_0 ~ N(0, s0^2),
    b_k = b_0 + K sqrt(dt) sum w, n_r = sigma_N / sqrt(dt) w', the error dt sum_k (b_k + n_r,k) has
    dt^2 [N^2 s0^2 + K^2 dt (N-1) N (2N-1) / 6] + N dt sigma_N^2 (sum_{j,k<N} min(j, k) = sum_{i<N} i^2)."""
    n = steps
    return (dt**2 * (n**2 * turn_on_std**2 + rate_random_walk**2 * dt * (n - 1) * n * (2 * n - 1) / 6)
            + n * dt * angle_random_walk**2)


def logistic(distance, floor, ceiling, midpoint, width):
    """p(d) = floor + (ceiling - floor) / (1 + exp(-(d - d50) / w)): from floor to ceiling as d grows."""
    d = np.asarray(distance, dtype=float)
    return floor + (ceiling - floor) / (1.0 + np.exp(-(d - midpoint) / width))


def tilt(points, roll, pitch):
    """Body points (..., 3) as (forward, left, up) after roll phi (starboard down) and pitch theta (bow up):
    R_y(-theta) R_x(phi) p in the heading-level frame (y points left: a bow-up pitch is -theta about it)."""
    p = np.asarray(points, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    y1, z1 = cr * y - sr * z, sr * y + cr * z                     # R_x(phi)
    return np.stack([cp * x - sp * z1, y1, sp * x + cp * z1], axis=-1)   # R_y(-theta)


def antenna_positions(positions, headings, lever_arms, roll=0.0, pitch=0.0):
    """Horizontal world positions (N, 2) of antennas at body lever arms (N, 3) on hulls at `positions` (N, 2)
    with `headings` (N,) and the given roll and pitch: p + R(psi) [tilt(a)]_xy."""
    level = tilt(lever_arms, roll, pitch)[..., :2]
    return np.asarray(positions, dtype=float) + rotate(level, headings)


def tilted_azimuth(azimuth, elevation, roll, pitch):
    """The azimuth (rad, from the bow, anticlockwise) a camera that assumes it is level measures for a sight
    line at `azimuth` and `elevation` in the heading-level frame, when the hull rolls and pitches:
    d_b = R_x(phi)^T R_y(-theta)^T d, alpha_m = atan2(d_b,y, d_b,x). Level (phi = theta = 0): alpha."""
    a, e = np.asarray(azimuth, dtype=float), np.asarray(elevation, dtype=float)
    x, y, z = np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    x1, z1 = cp * x + sp * z, -sp * x + cp * z                    # R_y(-theta)^T = R_y(theta)
    y2 = cr * y + sr * z1                                         # R_x(phi)^T
    return np.arctan2(y2, x1)


# --- the models -------------------------------------------------------------------------------------------

class PaperOdometry(StrictModel):
    """The paper's (5): the true displacement plus N(0, displacement_variance I) per step, and the true
    heading plus N(0, heading_variance); both variances are WorldConfig's fields."""

    kind: Literal["paper"] = "paper"


class WaterLogCompass(StrictModel):
    """A speed-through-water log and a compass, dead-reckoned (what the driver bridge reads at sea)."""

    kind: Literal["water_log_compass"] = "water_log_compass"
    scale_error_std: NonNegativeFloat = Field(
        0.0, description="per-vessel speed log scale error k ~ N(0, std^2), drawn once (0.02: 2 %)")
    scale_errors: dict[str, FiniteFloat] = Field(default_factory=dict, description="vessel id -> k, given")
    dead_band: NonNegativeFloat = Field(0.0, description="speeds through water below this read 0 (m/s)")
    speed_noise_density: NonNegativeFloat = Field(
        0.0, description="white noise of the speed reading (m/s/sqrt(Hz)): std density / sqrt(dt) per step")
    compass_bias_std_deg: NonNegativeFloat = Field(
        0.0, description="per-vessel compass bias b ~ N(0, std^2), drawn once (deg)")
    compass_biases_deg: dict[str, FiniteFloat] = Field(
        default_factory=dict, description="vessel id -> compass bias (deg), not drawn")
    compass_noise_deg: NonNegativeFloat = Field(0.0, description="std of each compass reading's noise (deg)")
    sway: Literal["none", "hull"] = Field(
        "none", description="'hull': the driver adds its hull's sideslip (boat/sway.py, world.dynamics' preset)")


class Gyro(StrictModel):
    """A yaw-rate gyro: r + b + n_r, with a turn-on bias and a bias random walk (Allan-variance terms)."""

    turn_on_bias_std_deg_s: NonNegativeFloat = Field(
        0.0, description="per-vessel bias at the start b_0 ~ N(0, std^2), drawn once (deg/s)")
    turn_on_biases_deg_s: dict[str, FiniteFloat] = Field(
        default_factory=dict, description="vessel id -> b_0 (deg/s), not drawn")
    angle_random_walk_deg_rt_h: NonNegativeFloat = Field(
        0.0, description="white rate noise density N (deg/sqrt(h)): std N / sqrt(dt) per step")
    rate_random_walk_deg_s_rt_s: NonNegativeFloat = Field(
        0.0, description="bias random walk K (deg/s/sqrt(s)): the bias moves by K sqrt(dt) w per step")


class DvlGyro(StrictModel):
    """A DVL's bottom-track velocity over ground, dead-reckoned with a gyro-integrated heading that starts
    at the true heading."""

    kind: Literal["dvl_gyro"] = "dvl_gyro"
    scale_error_std: NonNegativeFloat = Field(
        0.0, description="per-vessel velocity scale error k ~ N(0, std^2), drawn once (0.005: 0.5 %)")
    scale_errors: dict[str, FiniteFloat] = Field(default_factory=dict, description="vessel id -> k, given")
    velocity_noise_density: NonNegativeFloat = Field(
        0.0, description="white noise of each body-axis velocity (m/s/sqrt(Hz)): std density/sqrt(dt) a step")
    gyro: Gyro = Gyro()


Odometry = Annotated[Union[PaperOdometry, WaterLogCompass, DvlGyro], Field(discriminator="kind")]


class RangeLaw(StrictModel):
    """A probability growing with range d: floor + (ceiling - floor) / (1 + exp(-(d - midpoint) / width))."""

    floor: Fraction = Field(description="probability at short range")
    ceiling: Fraction = Field(description="probability far beyond the midpoint")
    midpoint: NonNegativeFloat = Field(description="range where it is half way from floor to ceiling (m)")
    width: PositiveFloat = Field(description="range over which it grows by a factor e of its logistic (m)")

    @model_validator(mode="after")
    def _grows(self) -> RangeLaw:
        if self.ceiling < self.floor:
            raise ValueError("ceiling must not be below floor (the probability grows with range)")
        return self

    def at(self, distance):
        return logistic(distance, self.floor, self.ceiling, self.midpoint, self.width)


class Uwb(StrictModel):
    """UWB ranging as installed: antennas off the hull's centre, dropouts and over-water outliers; on top of
    WorldConfig.range_noise."""

    antenna: LeverArm = Field((0.0, 0.0, 0.0), description="antenna (forward, left, up) from hull centre (m)")
    antennas: dict[str, LeverArm] = Field(default_factory=dict, description="vessel id -> own antenna (m)")
    dropout: RangeLaw | None = Field(None, description="probability that a range is lost; None: never")
    outlier: RangeLaw | None = Field(None, description="probability of a positive outlier; None: never")
    outlier_mean: PositiveFloat = Field(1.0, description="mean of an outlier's exponential excess range (m)")

    def lever_arm(self, vessel: str) -> tuple[float, float, float]:
        return self.antennas.get(vessel, self.antenna)


class Camera(StrictModel):
    """The bearing camera as mounted: it tilts with the hull, and its bearing is referred to a heading."""

    height: NonNegativeFloat = Field(
        0.0, description="camera height above the target's waterline (m): the sight line dips")
    heading_reference: Literal["true", "odometry"] = Field(
        "true", description="'odometry': bearing = own heading reading + azimuth; 'true': true heading")


class SensorsConfig(StrictModel):
    """Which error model each sensor has; the defaults are the paper's (5)-(9)."""

    odometry: Odometry = Field(PaperOdometry(), description="paper, water_log_compass or dvl_gyro")
    uwb: Uwb | None = Field(None, description="UWB installation errors; None: (6) between centres")
    camera: Camera | None = Field(None, description="camera tilt and heading reference; None: (9)")

    @property
    def is_paper(self) -> bool:
        return self.odometry.kind == "paper" and self.uwb is None and self.camera is None

    def named_vessels(self) -> set[str]:
        odometry = self.odometry
        names = set(getattr(odometry, "scale_errors", {})) | set(getattr(odometry, "compass_biases_deg", {}))
        if isinstance(odometry, DvlGyro):
            names |= set(odometry.gyro.turn_on_biases_deg_s)
        return names | (set(self.uwb.antennas) if self.uwb is not None else set())


PRESETS: dict[str, dict] = {
    "paper": {},
    # docs/sea.md (Sensors) gives each figure's source.
    "realistic": {
        "odometry": {"kind": "water_log_compass", "scale_error_std": 0.02, "dead_band": 0.25,
                     "speed_noise_density": 0.01, "compass_bias_std_deg": 1.0, "compass_noise_deg": 0.2},
        "uwb": {"antenna": (-0.3, 0.0, 0.5),
                "dropout": {"floor": 0.01, "ceiling": 1.0, "midpoint": 60.0, "width": 10.0},
                "outlier": {"floor": 0.02, "ceiling": 0.3, "midpoint": 40.0, "width": 10.0},
                "outlier_mean": 1.0},
        "camera": {"height": 0.5, "heading_reference": "odometry"},
    },
}
PRESETS["realistic_dvl"] = {
    **PRESETS["realistic"],
    "odometry": {"kind": "dvl_gyro", "scale_error_std": 0.005, "velocity_noise_density": 0.005,
                 "gyro": {"turn_on_bias_std_deg_s": 0.01, "angle_random_walk_deg_rt_h": 0.3,
                          "rate_random_walk_deg_s_rt_s": 0.0004}},
}


def expand_preset(value):
    """A `sensors` entry with its preset expanded: 'realistic', or {preset: realistic, ...changes}."""
    if isinstance(value, str):
        value = {"preset": value}
    if isinstance(value, dict) and "preset" in value:
        rest = {key: item for key, item in value.items() if key != "preset"}
        name = value["preset"]
        if name not in PRESETS:
            raise ValueError(f"unknown sensors preset {name!r}; known: {', '.join(PRESETS)}")
        return deep_merge(PRESETS[name], rest)
    return value


# --- per-vessel odometry state ----------------------------------------------------------------------------

@dataclass(frozen=True)
class OdometryState:
    """A vessel's dead-reckoned position and heading reading, and the constants and biases of its sensors."""

    position: tuple[float, float]
    heading: float           # the reading reported (compass, or gyro-integrated), rad
    scale: float             # k of the speed log or the DVL
    bias: float              # compass bias (rad), or the gyro's current bias (rad/s)
    sway: float = 0.0        # the sway estimate v (m/s) of water_log_compass with `sway: hull`
    rate: float = 0.0        # and the yaw rate from the compass over the last step (rad/s)


def start_odometry(model: WaterLogCompass | DvlGyro, vessel: str, heading: float,
                   rng: np.random.Generator) -> OdometryState:
    """A joining vessel's state. Draws: water_log_compass k, b, then the first compass noise; dvl_gyro k,
    b_0 (each drawn even where the config gives the value, so naming one vessel leaves the others alone)."""
    if isinstance(model, WaterLogCompass):
        scale = model.scale_errors.get(vessel, rng.normal(0.0, model.scale_error_std))
        bias = model.compass_biases_deg.get(vessel, rng.normal(0.0, model.compass_bias_std_deg)) * DEG
        noise = rng.normal(0.0, model.compass_noise_deg * DEG)
        return OdometryState((0.0, 0.0), float(wrap_angle(heading + bias + noise)), float(scale), float(bias))
    gyro = model.gyro
    scale = model.scale_errors.get(vessel, rng.normal(0.0, model.scale_error_std))
    bias = gyro.turn_on_biases_deg_s.get(vessel, rng.normal(0.0, gyro.turn_on_bias_std_deg_s)) * DEG
    return OdometryState((0.0, 0.0), float(heading), float(scale), float(bias))


def advance_odometry(model: WaterLogCompass | DvlGyro, state: OdometryState, ground_velocity, water_velocity,
                     heading: float, turn: float, dt: float, rng: np.random.Generator,
                     sway: sway_kernel.SwayModel | None = None) -> OdometryState:
    """The state after one step of dt over which the hull held `heading` (rad, true) with the given velocities
    over ground and through water (world frame, m/s), then turned by `turn` (rad). The step is dead-reckoned
    with the heading reading at its start. Draws: water_log_compass the speed noise then the compass noise;
    dvl_gyro the two velocity noises, the rate noise, then the bias step.

    In plain floats, the operations of `speed_log`, `dead_reckon`, `rotate` and `gyro_heading_step` on one
    vessel (numpy's per-call overhead would cost more than the arithmetic). water_log_compass with `sway:
    hull` (then `sway` is the hull's model) dead-reckons as the driver bridge does: the yaw rate from the two
    compass readings, the sway from boat/sway.py, and the arc between the readings (`boat.sway.arc_step`)."""
    x, y = state.position
    c, s = math.cos(heading), math.sin(heading)
    if isinstance(model, WaterLogCompass):
        # One call for the step's standard normals: the same numbers, in order, as one call each.
        z_speed, z_compass = rng.standard_normal(2).tolist()
        surge = water_velocity[0] * c + water_velocity[1] * s
        noise = model.speed_noise_density / math.sqrt(dt) * z_speed
        speed = 0.0 if abs(surge) < model.dead_band else (1.0 + state.scale) * surge + noise
        reading = float(wrap_angle(heading + turn + state.bias + model.compass_noise_deg * DEG * z_compass))
        if model.sway == "none":
            x, y = x + math.cos(state.heading) * (speed * dt), y + math.sin(state.heading) * (speed * dt)
            return OdometryState((x, y), reading, state.scale, state.bias)
        turned = float(wrap_angle(reading - state.heading))
        rate = turned / dt
        v = float(sway_kernel.step(sway, state.sway, speed, rate, rate - state.rate, dt))
        x, y = sway_kernel.arc_step(x, y, state.heading, turned, speed * dt, 0.5 * (state.sway + v) * dt)
        return OdometryState((x, y), reading, state.scale, state.bias, v, rate)
    gyro = model.gyro
    z_forward, z_left, z_rate, z_bias = rng.standard_normal(4).tolist()
    gx, gy = float(ground_velocity[0]), float(ground_velocity[1])
    std = model.velocity_noise_density / math.sqrt(dt)
    # The body-frame velocity R(-psi) v_g, scaled, plus noise, turned back by the heading reading.
    forward = (1.0 + state.scale) * (c * gx + s * gy) + std * z_forward
    left = (1.0 + state.scale) * (-s * gx + c * gy) + std * z_left
    cg, sg = math.cos(state.heading), math.sin(state.heading)
    x, y = x + (cg * forward - sg * left) * dt, y + (sg * forward + cg * left) * dt
    rate_noise = gyro.angle_random_walk_deg_rt_h * ARW_UNIT / math.sqrt(dt) * z_rate
    bias_step = gyro.rate_random_walk_deg_s_rt_s * DEG * math.sqrt(dt) * z_bias
    reading = state.heading + turn + (state.bias + rate_noise) * dt
    return OdometryState((x, y), float(wrap_angle(reading)), state.scale, state.bias + bias_step)


def white_displacement_variance(model: PaperOdometry | WaterLogCompass | DvlGyro, speed: float, dt: float,
                                displacement_variance: float = 0.0) -> tuple[float, float]:
    """The variance (m^2) of one step's dead-reckoned displacement from the white noises alone, along and
    across the track, at `speed` (m/s) over dt: what a filter's R_delta of (5) stands for. The constant errors
    (scale, compass bias, gyro bias) are not white and not in it. water_log_compass: along q_s dt (n_s dt with
    n_s ~ N(0, q_s / dt)), across (s dt sigma_c)^2; dvl_gyro: q_v dt on each axis; paper: R_delta on each."""
    if isinstance(model, WaterLogCompass):
        return model.speed_noise_density**2 * dt, (speed * dt * model.compass_noise_deg * DEG) ** 2
    if isinstance(model, DvlGyro):
        return (model.velocity_noise_density**2 * dt,) * 2
    return displacement_variance, displacement_variance


def uwb_faults(model: Uwb, true_ranges: np.ndarray, measured: np.ndarray, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:
    """The measured ranges with outliers added, and which are reported (not dropped), judged at the true
    antenna ranges. Draws, as arrays over the peers: the dropout uniforms, the outlier uniforms, then the
    outliers' unit exponentials (all drawn, used or not)."""
    count = len(true_ranges)
    u_drop, u_out, excess = rng.random(count), rng.random(count), rng.standard_exponential(count)
    kept = u_drop >= (model.dropout.at(true_ranges) if model.dropout is not None else 0.0)
    outlying = u_out < (model.outlier.at(true_ranges) if model.outlier is not None else 0.0)
    return measured + np.where(outlying, model.outlier_mean * excess, 0.0), kept
