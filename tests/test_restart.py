"""A vessel's agent restarted mid-mission without initial estimates (a restarted boat has none, and the deploy
tooling writes no `initial:` section): until its neighbours are localised it keeps its distance by the ranges
alone and does not drive the formation, and it gets back into formation.

The slow test does it with real processes (`Fleet.run(restarts=...)`): the Table II fleet in lockstep, vessel
2's agent stopped with SIGTERM at 25 s and a new one started from its settings without `initial`. In lockstep
the sim runs on while the new process starts, so vessel 2 is without an agent (and stopped by the bridge's
watchdog) for however much sim time that takes: measured 0.2 s when the fleet stalls on the departed
agent's last share long enough to cover the start, else 20-50 s. Both happen; the assertions hold for both.

The fast tests are of the core change the restart needed (agent/core/membership.py, `prior_from_target`): a
pair filter starts from the two vessels' target estimates only when ours agrees with the ranges to every
neighbour. A restarted vessel's target filter, started at a guessed range, believes it long before it is
right, and pairs started from it steered vessels to within 1.6 m of each other.
"""

from __future__ import annotations

import json
import math
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import bridge_counts, wait_until

from agent.config import updated
from agent.core.build import InitialEstimates, initial_state
from agent.core.control.formation import desired_offset, neighbour_gain
from agent.core.membership import ROUTE_RANGES, prior_from_target, receive_shares, store_ranges
from agent.core.params import AgentParams
from agent.core.records import STOP, OdometryReading, Share, TickInputs
from agent.core.step import step
from agent.core.target import track_target
from agent.shell.settings import NodeSettings
from mission_log.reader import read_log
from mission_log.series import truth_of
from sim_bridge import fleet as fleet_module
from sim_bridge.fleet import Fleet
from sim_bridge.scenario import initial_estimates, select_scenario, with_duration
from sim_bridge.world import World, lost_shares, streams

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
DT = 0.1

SEED = 5            # before pairs were judged by the ranges, one run of this seed (29 s outage) brought vessel
                    # 2 within 0.9 m of another; with other outages the old code passed (the fast tests catch it)
RESTART_AT = 25.0   # s of sim time: the fleet has settled (Table II settles in about 12 s)
DURATION = 200.0    # s: room for the longest outage measured in lockstep (48 s), the slowest return after one
                    # (74 s) and SETTLED
SETTLED = 20.0      # s: the last stretch of the mission the restarted vessel must spend in formation
MIN_LEFT = 100.0    # s of mission the new agent must have had after its first tick for the test to judge it
RADIUS_BAND = 0.10  # of r*: the settling band of the paper's metrics
MAX_GAP_ERROR = math.radians(15)   # the angular gaps to its two neighbours against 2 pi / n


# ----- the core: when a pair filter may start from the target estimates -----
def _vessel_two(target_error, neighbours, ticks: int = 50, lead: float = 0.0, range_lag: float = 0.0,
                velocity=(0.0, 0.0)):
    """Vessel 2 at (15, 0) from a target at the origin, restarted: its target estimate is off by
    `target_error` with a small covariance. Its neighbours (id -> position at time 0) move at `velocity`,
    share exact target estimates stamped `lead` s after our odometry, in odometry frames of their own, and
    are ranged exactly every tick, `range_lag` s after our odometry (on wall clocks every vessel samples on a
    phase of its own)."""
    params = AgentParams()
    here = np.array([15.0, 0.0])
    state = initial_state("2", params, InitialEstimates(target=(*(here + np.asarray(target_error)), 0.0, 0.0),
                                                        target_variance=0.1))
    origin = np.array([100.0, -50.0])     # where each neighbour's odometry started: only differences count
    for k in range(ticks):
        now = k * DT
        state.own.put(now, (0.0, 0.0))
        state.motion.stamp = now
        where = {j: p + np.asarray(velocity) * (now + lead) for j, p in neighbours.items()}
        receive_shares(params, state, {j: Share(j, OdometryReading(now + lead, p - origin, 0.0), np.asarray(velocity),
                                                0.0, target=np.array([*p, 0.0, 0.0]),
                                                target_covariance=np.eye(4) * 0.01)
                                       for j, p in where.items()}, now)
        ranged = {j: p + np.asarray(velocity) * (now + range_lag) for j, p in neighbours.items()}
        store_ranges(params, state, {j: float(np.hypot(*(here - p))) for j, p in ranged.items()}, now + range_lag)
    return params, state


ONE = {"1": np.array([0.0, 5.0])}
ACROSS = {**ONE, "3": np.array([-5.0, 0.0])}
# 4 m of error at right angles to the line to vessel 1: its ranges see 0.5 m of it, vessel 3's 1.6 m.
SIDEWAYS = 4.0 * np.array([5.0, 15.0]) / np.hypot(5.0, 15.0)


def test_a_true_target_route_starts_the_pair():
    params, state = _vessel_two((0.0, 0.0), ACROSS)
    prior = prior_from_target(params, state, state.tracks["1"])
    np.testing.assert_allclose(prior.position, [15.0, -5.0], atol=1e-9)
    assert np.trace(prior.covariance) < params.fleet.localised_trace      # steers at once, rightly
    assert state.health.priors_refused == 0


def test_a_target_estimate_the_ranges_contradict_does_not_start_a_pair():
    """6 m short along the bearing, as a restarted filter's guessed range leaves it: refused and counted,
    and the pair waits (to take the range after `history_ticks`, as a joiner's does)."""
    params, state = _vessel_two((-6.0, 0.0), ONE, ticks=20)
    assert prior_from_target(params, state, state.tracks["1"]) is None
    assert state.health.priors_refused == 1


@pytest.mark.parametrize("error", [(-6.0, 0.0), (5.9, -1.1), (-3.0, 2.0)])
def test_a_target_route_waits_for_ranges_to_judge_it(error):
    """A vessel heard again after its restart shares at once the estimate of its new target filter, which
    believes it long before it is right (5.9 m off with a position trace of 0.3 m^2, measured). A pair started
    from it on its first share, before any range could judge it, was localised at once on both sides, 7 m
    wrong, and never corrected: the restarted vessel came back to a circle of 1-2 m. Now the route waits
    for ROUTE_RANGES paired ranges and is refused then; a true one starts the pair then."""
    for ticks in range(1, ROUTE_RANGES):
        params, state = _vessel_two(error, ONE, ticks=ticks)
        assert prior_from_target(params, state, state.tracks["1"]) is None, f"started after {ticks} ticks"
        assert state.health.priors_refused == 0          # waiting, not refused
    params, state = _vessel_two(error, ONE, ticks=ROUTE_RANGES)
    assert prior_from_target(params, state, state.tracks["1"]) is None and state.health.priors_refused == 1
    params, state = _vessel_two((0.0, 0.0), ONE, ticks=ROUTE_RANGES)
    assert prior_from_target(params, state, state.tracks["1"]) is not None


def test_a_route_from_shares_stamped_after_our_odometry_starts_the_pair():
    """On wall clocks a neighbour's share can be stamped a few ms after our last odometry, tick after tick.
    Before: the route was judged at the share's stamp, where our odometry was never yet known, so it was
    never judged and never started (a sea-mode fleet: two vessels without each other's pair, held 3.5 m
    apart by the range guard for the rest of the mission). Now it is carried back along the neighbour's
    odometry to our last odometry's time and judged there."""
    ticks = ROUTE_RANGES + 5
    params, state = _vessel_two((0.0, 0.0), ONE, ticks=ticks, lead=0.02, range_lag=0.011, velocity=(0.5, -0.3))
    prior = prior_from_target(params, state, state.tracks["1"])
    last = (ticks - 1) * DT
    assert prior is not None and prior.stamp == pytest.approx(last, abs=1e-6)
    # p_ij at our last odometry's time: ours (15, 0) less neighbour 1's position then
    np.testing.assert_allclose(prior.position, [15.0, 0.0] - ONE["1"] - np.array([0.5, -0.3]) * last, atol=1e-9)
    assert state.health.priors_refused == 0
    # and a wrong one is still judged, and refused
    params, state = _vessel_two((-6.0, 0.0), ONE, ticks=ticks, lead=0.02, range_lag=0.011, velocity=(0.5, -0.3))
    assert prior_from_target(params, state, state.tracks["1"]) is None and state.health.priors_refused == 1


def test_the_range_start_takes_the_last_range_when_none_was_measured_at_the_shares_stamp():
    """Before: after `history_ticks` of refusals the pair started from the range measured at the share's
    very stamp, which a wall clock never gives (the ranges come on our phase, the shares on theirs)."""
    ticks = AgentParams().fleet.history_ticks + 1
    params, state = _vessel_two((-6.0, 0.0), ONE, ticks=ticks, lead=0.02, range_lag=0.011)
    prior = prior_from_target(params, state, state.tracks["1"])
    assert prior is not None and prior.stamp == pytest.approx((ticks - 1) * DT + 0.011, abs=1e-6)
    np.testing.assert_allclose(prior.position, [float(np.hypot(15.0, -5.0)), 0.0])


def test_every_neighbours_ranges_judge_our_target_estimate():
    """An error the pair's own ranges barely see (across its line of sight) is seen by a neighbour across
    the formation: alone, the pair starts from it; with that neighbour there, it does not."""
    params, state = _vessel_two(SIDEWAYS, ONE)
    assert prior_from_target(params, state, state.tracks["1"]) is not None
    params, state = _vessel_two(SIDEWAYS, ACROSS)
    assert prior_from_target(params, state, state.tracks["1"]) is None
    assert state.health.priors_refused == 1


def test_after_history_ticks_of_refusals_the_pair_starts_from_the_range():
    params, state = _vessel_two((-6.0, 0.0), ONE, ticks=AgentParams().fleet.history_ticks + 1)
    prior = prior_from_target(params, state, state.tracks["1"])
    distance = float(np.hypot(15.0, -5.0))
    np.testing.assert_allclose(prior.position, [distance, 0.0])
    assert np.trace(prior.covariance) > params.fleet.localised_trace      # not localised: it steers nothing


# ----- the restarted vessel's target filter -----
def test_a_target_filter_started_without_an_estimate_says_its_range_is_unknown():
    """A vessel (re)started without initial estimates starts its target filter at a guessed range along its
    first bearing. Over the first seconds its bearings come from a short arc, which barely observes the range,
    yet the filter's own covariance collapsed along its line of sight (after a restart: 3.5 m off at a
    position trace of 0.08 m^2), so its neighbours' target estimates were gated out as faults. Now the
    variance it gives along its line of sight covers its range error: over 20 seeded arcs (a moving target,
    noisy bearings), the normalised squared error along it stays within the 99.9 % bound of chi-square with
    one degree of freedom. (Across the line of sight one arc of the 20 is 0.42 m off, 4 sigma of what it
    gives: not covered here.)"""
    bound = 10.83
    params = AgentParams()
    for seed in range(20):
        rng = np.random.default_rng(seed)
        state = initial_state("2", params, InitialEstimates())
        radius, start = rng.uniform(4.0, 8.0), rng.uniform(0.0, 2 * math.pi)
        omega, target_velocity = params.control.yaw_rate, rng.normal(0.0, 0.3, size=2)
        previous = None
        for k in range(31):                     # 3 s: an arc of 0.3 rad at omega*
            angle = start + omega * k * DT
            relative = radius * np.array([math.cos(angle), math.sin(angle)])
            velocity = radius * omega * np.array([-math.sin(angle), math.cos(angle)]) + target_velocity
            seen = angle + rng.normal(0.0, math.sqrt(params.target.bearing_variance))
            change = None if previous is None else velocity - previous
            state.motion.velocity, previous = velocity, velocity
            x, P, _ = track_target(params, state, np.array([math.cos(seen), math.sin(seen)]), change)
            along = x[:2] / np.hypot(*x[:2])
            error = float(along @ (x[:2] - relative))
            normalised = error**2 / float(along @ P[:2, :2] @ along)
            assert normalised <= bound, f"seed {seed}, {k * DT:.1f} s: {error:+.2f} m along, {normalised:.0f}"


RESTART_SEEDS = range(1, 6)
RESTART_OUTAGES = (0.6, 3.0)   # s: shorter than the neighbours' timeout (they keep their pairs), and longer


def _restarted_in_process(seed: int, down: float, back: float, duration: float, vessel: str = "2"):
    """Table II (MCKF) run in process as lab/harness/runner.py runs it, with `vessel`'s core dropped at `down` (it
    sends nothing and is stopped, as the driver's watchdog stops it) and started again without initial
    estimates at `back`. Returns the times, `vessel`'s distance to the target and the closest approach of
    any two vessels at each tick."""
    _, scenario = select_scenario(CONFIGS / "table2_estimators.yaml", "mckf")
    scenario = updated(scenario, duration=duration)
    random = streams(seed)
    world = World(scenario.world, random.world)
    params = scenario.agent_params()
    agents, inbox, sent = {}, {}, {}
    times, radii, closest = [], [], []
    for k in range(int(round(duration / scenario.world.dt)) + 1):
        readings, live, truth = world.sense(), world.live(), world.truth()
        starts = initial_estimates(scenario, truth, random.initial) if k == 0 else {}
        joined = {v for v in live if v not in agents}
        away = down - 1e-9 <= truth.time < back - 1e-9
        for i in live:
            if i not in agents and not (i == vessel and away):
                agents[i] = initial_state(i, params, starts.get(i, InitialEstimates()))
        if away and vessel in agents:
            del agents[vessel]
            inbox.pop(vessel, None)
            sent.pop(vessel, None)
        senders = [j for j in sent if j in agents]
        lost = set(lost_shares(random.loss_seed, senders, live, joined, k, scenario.world.packet_loss))
        commands, outgoing = {}, {}
        for i in live:
            if i not in agents:
                commands[i] = STOP
                continue
            box = inbox.setdefault(i, {})
            box.update({j: sent[j] for j in senders if j != i and (j, i) not in lost})
            reading = readings[i]
            agents[i], output = step(params, agents[i], TickInputs(
                time=truth.time, odometry=reading.odometry, ranges=reading.ranges, shares=dict(box),
                bearing=reading.bearing, obstacle_points=reading.obstacle_points))
            commands[i] = output.command
            if output.share is not None:
                outgoing[i] = output.share
        positions = np.array([truth.positions[v] for v in live])
        distances = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
        times.append(truth.time)
        radii.append(float(np.hypot(*(truth.positions[vessel] - truth.target_position[:2]))))
        closest.append(float(distances[np.triu_indices(len(live), 1)].min()))
        sent = outgoing
        world.step(commands)
    return np.array(times), np.array(radii), np.array(closest)


@pytest.mark.slow
def test_an_agent_restarted_in_process_gets_back_onto_the_circle():
    """Vessel 2 restarted at 20 s of a 60 s Table II run: over the last 10 s within +-10 % of r*, and no two
    vessels closer than the safety distance after the restart, for every seed and outage. Before its target
    filter said its range was unknown, seeds 4 and 5 with the 3 s outage ended at 3.72-4.21 m: the restarted
    filter, sure of a range metres off, gated out every neighbour's target estimate. (Over seeds 1-10, 6 of
    20 runs ended off the circle before, 1 after: seed 6, 3 s, whose routes the ranges refuse; its pairs
    start from the ranges and take until about 140 s to localise, the slow return of long outages.)"""
    params = AgentParams()
    r_star, failures = params.control.radius, []
    for seed in RESTART_SEEDS:
        for outage in RESTART_OUTAGES:
            t, radius, closest = _restarted_in_process(seed, 20.0, 20.0 + outage, 60.0)
            last = radius[t >= t[-1] - 10.0]
            assert closest[t >= 20.0].min() >= params.control.safety_distance, (seed, outage)
            if np.abs(last - r_star).max() > RADIUS_BAND * r_star:
                failures.append(f"seed {seed}, outage {outage} s: {last.min():.2f}-{last.max():.2f} m")
    assert not failures, failures


SWEEP_SEEDS = range(1, 7)
SWEEP_OUTAGES = (0.3, 0.6, 1.0, 3.0, 5.0, 8.0, 12.0, 20.0, 45.0)   # s


@pytest.mark.slow
@pytest.mark.parametrize("seed", SWEEP_SEEDS)
def test_no_restart_of_the_sweep_comes_closer_than_the_safety_distance(seed):
    """Vessel 2 down at 25 s for each outage of the sweep, then 45 s more: no two vessels closer than the
    safety distance after 25 s. Outages from 5 s on are long enough that its neighbours drop their pairs with
    it, so for a while no vessel of those pairs has an estimate and only the ranges keep them apart. Before
    the range guard (a stop on the ticks whose raw range was under 3 m alone) every seed 1-6 came to
    2.00-2.95 m with 12 s; with it, before the restarted target filter took its range from the neighbours
    (D20), seed 4 with 8 s came to 0.91 m. Now the 54 runs keep 3.45 m or more (this machine)."""
    closest = {}
    for outage in SWEEP_OUTAGES:
        t, _, near = _restarted_in_process(seed, 25.0, 25.0 + outage, 70.0 + outage)
        closest[outage] = round(float(near[t >= 25.0].min()), 2)
    assert min(closest.values()) >= AgentParams().control.min_separation, closest


@pytest.mark.slow
def test_a_restart_whose_pairs_start_from_the_ranges_keeps_the_safety_distance():
    """Seed 4, an 8 s outage: vessels 1 and 2 came to 0.91 m, their pair filters started from ranges, not
    localised in bearing, with only the per-tick stop between them. The restarted vessel's pairs waited on
    target routes that waited on its target range (D19), which waited on pairs. Its target filter now takes
    its range from the neighbours' target estimates and the ranges to them (D20), the routes start the
    pairs, and the run keeps 4.40 m (docs/reliability.md has the sweep over seeds and outages)."""
    t, _, closest = _restarted_in_process(4, 25.0, 33.0, 70.0)
    assert closest[t >= 25.0].min() >= AgentParams().control.min_separation


# ----- with real processes -----
@pytest.mark.slow
def test_an_agent_that_ignores_sigterm_is_killed_for_its_restart_and_its_token_waited_out(
        tmp_path, short_scenario, monkeypatch):
    """The launcher's side of a restart, with a stand-in agent that ignores SIGTERM: SIGKILL after
    STOP_SECONDS, then no new agent until the old one's liveliness token is gone (the new one would refuse
    to start); the new agent's settings are the vessel's without `initial`, logging to a file of its own."""
    monkeypatch.setattr(fleet_module, "STOP_SECONDS", 0.5)
    fleet = Fleet(short_scenario, None, tmp_path / "runs")
    stubborn = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    fleet.agents = {"2": fleet._start("agent-2", [sys.executable, "-c", stubborn])}
    assert wait_until(lambda: "up" in (fleet.folder / "agent-2.log").read_text(), 20)
    token = type("Reply", (), {"ok": object()})()
    answers = [[token], [token], []]      # the token outlives the process for two looks
    liveliness = type("Liveliness", (), {"get": lambda self, key, timeout: answers.pop(0)})()
    session = type("Session", (), {"liveliness": lambda self: liveliness})()
    fleet.stop_for_restart("2", session)
    assert fleet.agents["2"].returncode == -signal.SIGKILL and fleet.hard_killed == ["agent-2"]
    assert answers == [] and fleet.down == {"2"}
    started = []
    monkeypatch.setattr(fleet, "start_agent", lambda vessel: started.append(fleet._name(vessel)))
    fleet.start_again("2")
    assert started == ["agent-2-restart1"] and fleet.down == set()
    original = yaml.safe_load((fleet.folder / "agent-2.yaml").read_text())
    settings = yaml.safe_load((fleet.folder / "agent-2-restart1.yaml").read_text())
    assert original["initial"] and "initial" not in settings
    assert settings.pop("log") == str(fleet.folder / "agent-2-restart1.mcap")
    # The launch's short look for a namesake goes too: an agent with this id has just been there.
    assert original["id_check"] < NodeSettings().id_check and "id_check" not in settings
    assert settings == {k: v for k, v in original.items() if k not in ("initial", "log", "id_check")}
    for console in fleet.consoles.values():
        console.close()


def _gaps(positions: np.ndarray, target: np.ndarray, vessel: int) -> np.ndarray:
    """(T,) the larger departure of `vessel`'s angular gaps to its neighbours ahead and behind on the circle
    from 2 pi / n."""
    angles = np.arctan2(positions[..., 1] - target[:, None, 1], positions[..., 0] - target[:, None, 0])
    others = [j for j in range(positions.shape[1]) if j != vessel]
    ahead = (angles[:, others] - angles[:, [vessel]]) % (2 * math.pi)
    even = 2 * math.pi / positions.shape[1]
    return np.maximum(np.abs(ahead.min(axis=1) - even), np.abs(2 * math.pi - ahead.max(axis=1) - even))


def _formation_from_localised(params: AgentParams, estimates: dict, shares: dict) -> np.ndarray:
    """The formation velocity (33) of one logged tick rebuilt from the target and the neighbours logged as
    localised alone (agent/core/command.py)."""
    c = params.control
    phase = estimates["phase"]
    offset = np.array(desired_offset(c.radius, phase))
    localised = [j for j, n in estimates["neighbours"].items() if n["localised"]]
    gain = neighbour_gain(len(localised), c.gain_neighbour, c.neighbour_gain_cap)
    total = np.zeros(2)
    for j in localised:
        share = shares[j]
        phase_j = share["phase"] + c.yaw_rate * (estimates["time"] - share["odometry"]["stamp"])
        total += gain * (offset - desired_offset(c.radius, phase_j) - np.array(estimates["neighbours"][j]["position"]))
    if estimates["target_state"] is not None:
        total += c.gain_target * (offset - np.array(estimates["target_state"][:2]))
    return total


@pytest.mark.slow
def test_a_restarted_agent_without_initial_estimates_rejoins_without_coming_too_close(tmp_path):
    """Measured in lockstep runs of seeds 1-6 (outages 0.2-61 s): closest approach after the restart 3.7-6.9 m
    (the least while vessel 2 lay stopped, its neighbours held off by their range guard); back in formation
    0-74 s after the new agent's first tick, the slowest after long outages, where vessel 2 comes back
    unlocalised and waits on its own bearing-only target estimate; once back, radius 4.76-5.29 m and gap
    error at most 3.6 deg. Runs of the old core that went wrong ended 15-40 m from the target, 79-263 deg
    out, after approaches of 0.6-0.9 m."""
    path = with_duration(CONFIGS / "table2_estimators.yaml", tmp_path, DURATION)
    fleet = Fleet(path, "mckf", tmp_path / "runs", seed=SEED)
    folder = fleet.run(timeout=600, restarts={"2": (RESTART_AT, RESTART_AT)})

    # (c) The run ended cleanly, every tick done, each agent stopped with SIGTERM and exiting 0; the restart
    # ran from settings without `initial` and wrote a second log, both finished.
    assert bridge_counts((folder / "bridge.log").read_text())["ticks"] == fleet.planned_ticks
    assert all(p.returncode == 0 for p in fleet.agents.values()) and fleet.hard_killed == []
    ((stopped, started),) = fleet.restarted["2"]
    assert RESTART_AT <= stopped < RESTART_AT + 1.0 and started >= stopped
    assert "agent-2-restart1" in json.loads((folder / "processes.json").read_text())
    for name in ("agent-2", "agent-2-restart1"):   # each agent of vessel 2 said it stopped, on SIGTERM
        assert "usv-agent 2: stopped after" in (folder / f"{name}.log").read_text()
    settings = yaml.safe_load((folder / "agent-2-restart1.yaml").read_text())
    assert "initial" not in settings and settings["log"].endswith("agent-2-restart1.mcap")
    first, second = read_log(folder / "agent-2.mcap"), read_log(folder / "agent-2-restart1.mcap")
    assert not first.unfinished and not second.unfinished
    assert first.topic("summary") and second.topic("summary")
    first_ticks, second_ticks = [t * 1e-9 for t, _ in first.topic("estimates")], [t * 1e-9 for t, _ in
                                                                                  second.topic("estimates")]
    assert max(first_ticks) <= stopped + 1.0 and min(second_ticks) > max(first_ticks)
    back_on = min(second_ticks)
    assert DURATION - back_on >= MIN_LEFT, f"the new agent ticked first at {back_on:.1f} s: too late to judge"

    truth = truth_of(read_log(folder / "sim.mcap"))
    t = truth.t_ns * 1e-9
    ids = list(truth.vessels)
    positions = np.stack([truth.vessels[v] for v in ids], axis=1)          # (T, n, 2)
    params = AgentParams.model_validate(settings["agent"])

    # (a) From the restart on, no two vessels ever closer than control.min_separation.
    after = t >= stopped
    distances = np.linalg.norm(positions[:, :, None] - positions[:, None, :], axis=-1)
    pairs = np.triu_indices(len(ids), 1)
    closest = distances[:, pairs[0], pairs[1]][after]
    assert closest.min() >= params.control.min_separation, f"closest approach {closest.min():.2f} m"

    # (b) Vessel 2 back in formation: for the last SETTLED s, within +-10 % of r* of the target and its gaps
    # to its neighbours on the circle within 15 degrees of 2 pi / n.
    two = ids.index("2")
    radius = np.linalg.norm(positions[:, two] - truth.target, axis=1)
    gaps = _gaps(positions, truth.target, two)
    in_formation = (np.abs(radius - params.control.radius) <= RADIUS_BAND * params.control.radius) & (
        gaps <= MAX_GAP_ERROR)
    last = t >= t[-1] - SETTLED
    assert in_formation[last].all(), (f"last {SETTLED:.0f} s: radius {radius[last].min():.2f}-"
                                      f"{radius[last].max():.2f} m, gap error up to {np.degrees(gaps[last].max()):.1f} deg")
    out = np.flatnonzero(~in_formation & (t >= back_on))
    back = t[out[-1] + 1] if len(out) else back_on

    # (d) The restarted agent drove the formation from the target and its localised neighbours only: each
    # tick's logged formation velocity is what those alone give; and it did have unlocalised ones.
    inputs = {stamp: message for stamp, message in second.topic("inputs")}
    latest: dict[str, dict] = {}
    unlocalised_ticks = 0
    for stamp, estimates in second.topic("estimates"):
        for j, share in inputs[stamp]["shares"].items():
            if j not in latest or share["odometry"]["stamp"] >= latest[j]["odometry"]["stamp"]:
                latest[j] = share
        np.testing.assert_allclose(estimates["velocity"]["formation"],
                                   _formation_from_localised(params, estimates, latest), rtol=0, atol=1e-9,
                                   err_msg=f"at {stamp * 1e-9:.1f} s")
        # Localised: P_ij small enough and the estimate agreeing with the median of the last ranges
        # (agent/core/step.py `_localised`; unit-tested in tests/test_step.py).
        unlocalised_ticks += len(inputs[stamp]["shares"]) > sum(
            n["localised"] for n in estimates["neighbours"].values())
    assert unlocalised_ticks > 0

    print(f"restart: agent down at {stopped:.1f} s, new agent's first tick {back_on:.1f} s (outage "
          f"{back_on - stopped:.1f} s); closest approach after the restart {closest.min():.2f} m; back in "
          f"formation {back - back_on:.1f} s after its first tick; last {SETTLED:.0f} s radius "
          f"{radius[last].min():.2f}-{radius[last].max():.2f} m, gap error <= {np.degrees(gaps[last].max()):.1f} deg; "
          f"{unlocalised_ticks} ticks with an unlocalised neighbour")
