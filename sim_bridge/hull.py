"""Fossen's 3-DOF manoeuvring model for a fleet of hulls, with its thrusters and inner loop, stepped in RK4.

    M nu_r_dot + C(nu_r) nu_r + D(nu_r) nu_r = tau,   nu_r = nu - nu_c      (Fossen 2021, 3-DOF with current)
    x_dot = cos(psi) u_r - sin(psi) v_r + c_x,  y_dot = sin(psi) u_r + cos(psi) v_r + c_y,  psi_dot = r
with nu_r = (u_r, v_r, r) the velocity through the water in the body frame (x forward, y to port), c the
current over ground, M = [[m11, 0, 0], [0, m22, m23], [0, m23, m33]] (rigid body plus added mass, m23 =
m x_g), C(nu) nu = [-(m22 v + m23 r) r, m11 u r, (m22 v + m23 r) u - m11 u v] (rigid-body and added-mass
Coriolis, skew-symmetric: nu^T C(nu) nu = 0), D(nu) = diag(d + d2 |nu|) (linear plus quadratic damping).
tau = thrust + the environment's loads. With no tau and no current the kinetic energy (1/2) nu^T M nu can
only fall: d/dt = -nu^T D nu.

`HullFleet` holds n hulls of one preset as arrays of shape (n,) and advances them by substeps of h: each
substep the environment moves to its time (`advance`), the inner loop runs (every `loop_every` substeps, on
the speed through the water u_r, as a speed log measures it, and the turn rate r),
its (X, N) go through allocation and the thrusters' lag, then one RK4 step of the model with the thrust
(its mean over the substep), the current and the loads held over the substep. Up to SMALL_FLEET hulls are
advanced one by one in plain floats (`rk4_one`), more as arrays: the same operations, the same numbers.
docs/sea.md ("Hull dynamics") holds the derivation and figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from boat import inner_loop, thrusters
from boat.presets import BoatPreset, Hull


@dataclass(frozen=True)
class Model:
    """The constant coefficients of the model, from a `Hull`."""

    m11: float
    m22: float
    m23: float
    m33: float
    inverse: np.ndarray   # (3, 3): M^-1
    linear: np.ndarray    # (3, 1): -X_u, -Y_v, -N_r
    quadratic: np.ndarray  # (3, 1): -X_|u|u, -Y_|v|v, -N_|r|r
    columns: tuple[np.ndarray, ...] = ()   # M^-1's three columns, (3, 1) each
    floats: tuple[float, ...] = ()   # the same as plain floats, for `rk4_one`: m11, m22, m23, M^-1 (9), d (3), d2 (3)

    @classmethod
    def of(cls, hull: Hull) -> Model:
        m11 = hull.mass + hull.added_mass_surge
        m22 = hull.mass + hull.added_mass_sway
        m23 = hull.mass * hull.x_g
        m33 = hull.yaw_inertia + hull.added_mass_yaw
        inverse = np.linalg.inv(np.array([[m11, 0.0, 0.0], [0.0, m22, m23], [0.0, m23, m33]]))
        linear = np.array([[hull.surge_damping], [hull.sway_damping], [hull.yaw_damping]])
        quadratic = np.array([[hull.surge_damping_quadratic], [hull.sway_damping_quadratic],
                              [hull.yaw_damping_quadratic]])
        floats = (m11, m22, m23, *inverse.ravel().tolist(), *linear.ravel().tolist(), *quadratic.ravel().tolist())
        columns = tuple(inverse[:, j:j + 1].copy() for j in range(3))
        return cls(m11, m22, m23, m33, inverse, linear, quadratic, columns, tuple(float(x) for x in floats))

    def energy(self, u: np.ndarray, v: np.ndarray, r: np.ndarray) -> np.ndarray:
        """(1/2) nu^T M nu."""
        return 0.5 * (self.m11 * u * u + self.m22 * v * v + 2 * self.m23 * v * r + self.m33 * r * r)


def derivative(model: Model, state: np.ndarray, tau: np.ndarray, current: np.ndarray) -> np.ndarray:
    """d/dt of state (6, n) = (x, y, psi, u_r, v_r, r) under tau (3, n) = (X, Y, N) and current (2, n).
    Few numpy calls, not few flops: on a fleet's short arrays each call's overhead is the cost."""
    psi, nu, u, v, r = state[2], state[3:], state[3], state[4], state[5]
    c, s = np.cos(psi), np.sin(psi)
    a = model.m22 * v + model.m23 * r
    force = tau - (model.linear + model.quadratic * np.abs(nu)) * nu     # tau - D(nu) nu
    force[0] += a * r                                                     # - C(nu) nu, row by row
    force[1] -= model.m11 * u * r
    force[2] += (model.m11 * v - a) * u
    out = np.empty_like(state)
    out[0] = c * u - s * v + current[0]
    out[1] = s * u + c * v + current[1]
    out[2] = r
    # M^-1 force as three products and two sums, in the order `rk4_one` takes in floats (a matrix product
    # rounds its own way), so that a hull's numbers do not depend on how many hulls share the fleet.
    i0, i1, i2 = model.columns
    out[3:] = i0 * force[0] + i1 * force[1] + i2 * force[2]
    return out


def rk4(model: Model, state: np.ndarray, tau: np.ndarray, current: np.ndarray, h: float) -> np.ndarray:
    """One classical Runge-Kutta step of h with tau and the current held."""
    k1 = derivative(model, state, tau, current)
    k2 = derivative(model, state + (0.5 * h) * k1, tau, current)
    k3 = derivative(model, state + (0.5 * h) * k2, tau, current)
    k4 = derivative(model, state + h * k3, tau, current)
    return state + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)


def rk4_one(model: Model, state: tuple[float, ...], tau: tuple[float, float, float], current: tuple[float, float],
            h: float) -> tuple[float, ...]:
    """`rk4` for one hull in plain floats: state (x, y, psi, u_r, v_r, r), tau (X, Y, N), current (c_x, c_y).
    The same operations in the same order as `derivative`, so the same numbers (numpy's cos and sin round as
    the C library's here; tests/test_hull.py checks); on a few hulls it costs less than numpy's calls."""
    m11, m22, m23, i00, i01, i02, i10, i11, i12, i20, i21, i22, d0, d1, d2, q0, q1, q2 = model.floats
    big_x, big_y, big_n = tau
    cx, cy = current
    cos, sin = math.cos, math.sin

    def derivative_one(psi: float, u: float, v: float, r: float) -> tuple[float, ...]:
        c, s = cos(psi), sin(psi)
        a = m22 * v + m23 * r
        f0 = (big_x - (d0 + q0 * abs(u)) * u) + a * r
        f1 = (big_y - (d1 + q1 * abs(v)) * v) - m11 * u * r
        f2 = (big_n - (d2 + q2 * abs(r)) * r) + (m11 * v - a) * u
        return (c * u - s * v + cx, s * u + c * v + cy, r,
                i00 * f0 + i01 * f1 + i02 * f2, i10 * f0 + i11 * f1 + i12 * f2, i20 * f0 + i21 * f1 + i22 * f2)

    x, y, psi, u, v, r = state
    half = 0.5 * h
    a0, a1, a2, a3, a4, a5 = derivative_one(psi, u, v, r)
    b0, b1, b2, b3, b4, b5 = derivative_one(psi + half * a2, u + half * a3, v + half * a4, r + half * a5)
    c0, c1, c2, c3, c4, c5 = derivative_one(psi + half * b2, u + half * b3, v + half * b4, r + half * b5)
    e0, e1, e2, e3, e4, e5 = derivative_one(psi + h * c2, u + h * c3, v + h * c4, r + h * c5)
    w = h / 6.0   # written out, not a loop over the six: a third less time
    return (x + w * (a0 + 2.0 * (b0 + c0) + e0), y + w * (a1 + 2.0 * (b1 + c1) + e1),
            psi + w * (a2 + 2.0 * (b2 + c2) + e2), u + w * (a3 + 2.0 * (b3 + c3) + e3),
            v + w * (a4 + 2.0 * (b4 + c4) + e4), r + w * (a5 + 2.0 * (b5 + c5) + e5))


class CalmWater:
    """The environment of a world without one: no current, no loads, level water."""

    def advance(self, t: float) -> None:
        return None

    def current(self, t: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        zero = np.zeros_like(x)
        return zero, zero

    def loads(self, t, x, y, heading, u, v, windage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        zero = np.zeros_like(x)
        return zero, zero, zero

    def attitude(self, t: float, x: np.ndarray, y: np.ndarray, heading: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        zero = np.zeros_like(x)
        return zero, zero


# Up to this many hulls advance in plain floats (`HullFleet._advance_floats`), more as arrays: one hull's
# substep costs about 18 us in floats, a fleet's about 175 us in numpy calls whatever its size: the two meet
# at about 12 hulls (docs/sea.md, "What it costs").
SMALL_FLEET = 10


class HullFleet:
    """n hulls of one preset: their state, thrusters and inner loops, advanced by `advance`."""

    def __init__(self, boat: BoatPreset, n: int, step: float, loop_every: int, environment=None) -> None:
        self.boat = boat
        self.model = Model.of(boat.hull)
        self.h = step
        self.loop_every = loop_every
        self.environment = CalmWater() if environment is None else environment
        self.state = np.zeros((6, n))             # x, y, psi, u_r, v_r, r
        self.thrust = np.zeros((2, n))            # port, starboard (N), after the lag
        self.demand = np.zeros((2, n))            # what the thrusters are asked for (N), after saturation
        self.loop = inner_loop.LoopState.zero(n)
        self.current = np.zeros((2, n))           # the current at each hull, last substep (m/s over ground)
        self.saturated_time = np.zeros(n)         # s spent with the demand beyond the thrusters' reach
        self._saturated_step = np.zeros(n)       # h where the demand was cut at the last inner-loop step
        self.substeps = 0                         # substeps taken, for the inner loop's period

    def place(self, index: int, x: float, y: float, heading: float) -> None:
        """Put hull `index` at rest in the water at (x, y, heading), its thrusters and loop idle."""
        self.state[:, index] = (x, y, heading, 0.0, 0.0, 0.0)
        self.thrust[:, index] = 0.0
        self.demand[:, index] = 0.0
        self.loop = inner_loop.LoopState(*(np.where(np.arange(self.state.shape[1]) == index, 0.0, field)
                                           for field in self.loop))

    def ground_velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """(vx, vy) over ground: R(psi) nu_r + c."""
        _, _, psi, u, v, _ = self.state
        c, s = np.cos(psi), np.sin(psi)
        return c * u - s * v + self.current[0], s * u + c * v + self.current[1]

    def body_velocity(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, r) over ground in the body frame: nu = nu_r + R(psi)^T c."""
        _, _, psi, u, v, r = self.state
        c, s = np.cos(psi), np.sin(psi)
        return u + c * self.current[0] + s * self.current[1], v - s * self.current[0] + c * self.current[1], r

    def advance(self, t: float, duration: float, speed: np.ndarray, rate: np.ndarray, commanded_at: float
                ) -> None:
        """Advance every hull from time t by `duration` (a whole number of substeps) under the command
        (speed, rate), given at time `commanded_at`."""
        boat, env, h = self.boat, self.environment, self.h
        speed, rate = inner_loop.commands(boat.inner_loop, speed, rate)
        if self.state.shape[1] <= SMALL_FLEET:
            self._advance_floats(t, round(duration / h), speed, rate, commanded_at)
            return
        calm = type(env) is CalmWater   # nothing to ask: skip the calls (the same numbers, fewer of them)
        tau = np.zeros((3, self.state.shape[1]))
        for k in range(round(duration / h)):
            now = t + k * h
            if not calm:
                env.advance(now)
                cx, cy = env.current(now, self.state[0], self.state[1])
                self.current = np.array([cx, cy], dtype=float)
            if self.substeps % self.loop_every == 0:
                # The loop holds the speed through the water (a speed log's; no GNSS) and the turn rate.
                self.loop, force, moment = inner_loop.step(
                    boat.inner_loop, boat.thrusters, self.loop, speed, rate, now - commanded_at,
                    self.state[3], self.state[5], h * self.loop_every, checked=True)
                port, starboard, saturated = thrusters.allocate(boat.thrusters, force, moment)
                self.demand = np.array([port, starboard])
                self._saturated_step = saturated * h
            self.saturated_time += self._saturated_step
            mean = thrusters.mean_over(boat.thrusters, self.thrust, self.demand, h)
            self.thrust = thrusters.lag(boat.thrusters, self.thrust, self.demand, h)
            tau[0], tau[2] = thrusters.forces(boat.thrusters, mean[0], mean[1])
            if not calm:
                u_g, v_g, _ = self.body_velocity()
                lx, ly, ln = env.loads(now, self.state[0], self.state[1], self.state[2], u_g, v_g, boat.windage)
                tau[0] += lx
                tau[1] = ly
                tau[2] += ln
            self.state = rk4(self.model, self.state, tau, self.current, h)
            self.substeps += 1

    def _advance_floats(self, t: float, steps: int, speed: np.ndarray, rate: np.ndarray, commanded_at: float
                        ) -> None:
        """`advance` hull by hull in plain floats (the same operations in the same order, so the same numbers
        as the arrays' path): on a few hulls numpy's per-call overhead costs more than the arithmetic. The
        environment is still asked once per substep for every hull at once."""
        boat, env, h, model = self.boat, self.environment, self.h, self.model
        calm = type(env) is CalmWater
        count = self.state.shape[1]
        states = self.state.T.tolist()                 # per hull: x, y, psi, u_r, v_r, r
        thrust, demand = self.thrust.T.tolist(), self.demand.T.tolist()
        loops = [inner_loop.LoopState(*fields) for fields in zip(*(field.tolist() for field in self.loop))]
        saturated_time, saturated_step = self.saturated_time.tolist(), self._saturated_step.tolist()
        currents = self.current.T.tolist()
        loads: list[tuple[float, float, float]] = []
        speeds, rates = speed.tolist(), rate.tolist()
        period = h * self.loop_every
        for k in range(steps):
            now = t + k * h
            if not calm:
                env.advance(now)
                x, y, psi = (np.array(row) for row in zip(*(state[:3] for state in states)))
                cx, cy = env.current(now, x, y)
                self.current = np.array([cx, cy], dtype=float)
                currents = self.current.T.tolist()
                u_g, v_g = self._body_velocity_of(states, currents)
                lx, ly, ln = env.loads(now, x, y, psi, np.array(u_g), np.array(v_g), boat.windage)
                loads = list(zip(*(np.broadcast_to(np.asarray(load, dtype=float), (count,)).tolist()
                                   for load in (lx, ly, ln))))
            loop_now = self.substeps % self.loop_every == 0
            for i in range(count):
                state = states[i]
                if loop_now:
                    # The loop holds the speed through the water (a speed log's; no GNSS) and the turn rate.
                    loops[i], force, moment = inner_loop.step(
                        boat.inner_loop, boat.thrusters, loops[i], speeds[i], rates[i], now - commanded_at,
                        state[3], state[5], period, checked=True)
                    port, starboard, saturated = thrusters.allocate(boat.thrusters, force, moment)
                    demand[i] = [port, starboard]
                    saturated_step[i] = saturated * h
                saturated_time[i] += saturated_step[i]
                (port, starboard), (want_port, want_starboard) = thrust[i], demand[i]
                mean_port = thrusters.mean_over(boat.thrusters, port, want_port, h)
                mean_starboard = thrusters.mean_over(boat.thrusters, starboard, want_starboard, h)
                thrust[i] = [thrusters.lag(boat.thrusters, port, want_port, h),
                             thrusters.lag(boat.thrusters, starboard, want_starboard, h)]
                force, moment = thrusters.forces(boat.thrusters, mean_port, mean_starboard)
                if calm:
                    tau = (force, 0.0, moment)
                else:
                    lx, ly, ln = loads[i]
                    tau = (force + lx, ly, moment + ln)
                states[i] = rk4_one(model, state, tau, currents[i], h)
            self.substeps += 1
        self.state = np.array(states).T.copy()
        self.thrust, self.demand = np.array(thrust).T.copy(), np.array(demand).T.copy()
        self.loop = inner_loop.LoopState(*(np.array(field) for field in zip(*loops)))
        self.saturated_time, self._saturated_step = np.array(saturated_time), np.array(saturated_step)

    @staticmethod
    def _body_velocity_of(states: list[list[float]], currents: list[list[float]]) -> tuple[list[float], list[float]]:
        """`body_velocity`'s (u, v) of hulls given as floats, in its order of operations."""
        u_g, v_g = [], []
        for (_, _, psi, u, v, _), (cx, cy) in zip(states, currents):
            c, s = math.cos(psi), math.sin(psi)
            u_g.append(u + c * cx + s * cy)
            v_g.append(v - s * cx + c * cy)
        return u_g, v_g
