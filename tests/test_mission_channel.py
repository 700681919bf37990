"""The mission channel's bookkeeping (agent/shell/mission.py): replays judged by stamp window and session,
a bounded table of senders that never forgets one heard within the window, a queue per sender drained in
rounds, and the statuses' answers. The same attacks over real processes are in tests/test_attacks.py."""

from __future__ import annotations

import json

import numpy as np

from agent.core.params import AgentParams
from agent.shell import mission as channel
from agent.shell.mission import MissionOrders

NOW = 100.0


def orders() -> tuple[MissionOrders, list[str]]:
    counted: list[str] = []
    return MissionOrders("1", max_age=1.0, max_future=0.5, count=lambda kind, _: counted.append(kind)), counted


def body(command: str = "hold", seq: int = 1, stamp: float = NOW, sender: str = "op", session: str = "",
         **values) -> bytes:
    return json.dumps({"stamp_ns": round(stamp * 1e9), "seq": seq, "sender": sender, "command": command,
                       "session": session, **values}).encode()


def offer(mission: MissionOrders, payload: bytes, now: float = NOW) -> bool:
    return mission.offer("mission/all", payload, now, round(now * 1e9), lambda: frozenset({"2"}))


def applied(mission: MissionOrders, now: float = NOW) -> list[tuple[str, int, str]]:
    """The commands the next tick applies: (sender, seq, command)."""
    mission.apply(AgentParams(), round(now * 1e9))
    return [(a.sender, a.seq, a.command) for _, a, _ in mission.judged() if a.applied]


def test_a_seq_of_2_63_locks_out_one_session_for_one_window_and_nothing_else():
    mission, counted = orders()
    assert offer(mission, body("resume", seq=2**63 - 1))                 # session "": the attacker's
    assert offer(mission, body("hold", seq=5, session="a1b2"))           # usv-op's next invocation
    assert not offer(mission, body("hold", seq=6))                       # session "" is blocked ...
    assert counted == ["mission_replayed"]
    assert offer(mission, body("hold", seq=6, stamp=NOW + 1.6), now=NOW + 1.6)   # ... until its stamp is stale
    assert applied(mission, NOW + 1.6) == [("op", 2**63 - 1, "resume"), ("op", 5, "hold"), ("op", 6, "hold")]


def test_a_replay_within_the_window_is_refused_however_many_senders_came_between():
    mission, counted = orders()
    captured = body("hold", seq=10, session="s1")
    assert offer(mission, captured)
    assert offer(mission, body("resume", seq=11, session="s1", stamp=NOW + 0.1), now=NOW + 0.1)
    assert applied(mission, NOW + 0.1) == [("op", 10, "hold"), ("op", 11, "resume")]
    for n in range(300):                                                  # junk senders, each new
        offer(mission, body("set", seq=1, sender=f"junk{n}", radius=5.0, stamp=NOW + 0.2), now=NOW + 0.2)
    assert not offer(mission, captured, now=NOW + 0.9)                   # within the window: replayed
    assert counted.count("mission_replayed") == 1
    assert not offer(mission, captured, now=NOW + 1.2)                   # past it: stale
    assert counted.count("mission_stale") == 1
    mission.apply(AgentParams(), round((NOW + 1.2) * 1e9))
    assert not mission.held


def test_the_table_of_senders_is_bounded_and_new_senders_never_push_out_one_heard_within_the_window():
    mission, counted = orders()
    assert offer(mission, body("hold", seq=1, session="op1"))
    for n in range(channel.MAX_SENDERS - 1):
        assert offer(mission, body("set", seq=1, sender=f"s{n}", radius=5.0))
    assert len(mission._senders) == channel.MAX_SENDERS
    # Full of senders heard within the window: a new one is refused, and the operator's hold is still known.
    assert not offer(mission, body("set", seq=1, sender="late", radius=5.0))
    assert counted == ["mission_too_many_senders"]
    assert not offer(mission, body("hold", seq=1, session="op1"))
    assert counted[-1] == "mission_replayed"
    mission.apply(AgentParams(), round(NOW * 1e9))
    # A window later every one of them is forgettable: the least recently heard goes first, one per newcomer
    # (the operator, heard last with the replay, last of all).
    later = NOW + 1.6
    assert offer(mission, body("set", seq=1, sender="late", radius=5.0, stamp=later), now=later)
    assert "s0" not in mission._senders and "s1" in mission._senders
    assert offer(mission, body("set", seq=1, sender="later", radius=5.0, stamp=later), now=later)
    assert "s1" not in mission._senders and "s2" in mission._senders and "op" in mission._senders
    assert len(mission._senders) == channel.MAX_SENDERS


def test_a_sender_heard_again_moves_to_the_back_of_the_eviction_order():
    mission, _ = orders()
    for n in range(channel.MAX_SENDERS):
        assert offer(mission, body("set", seq=1, sender=f"s{n}", radius=5.0))
    assert offer(mission, body("set", seq=2, sender="s0", radius=5.0, stamp=NOW + 1.0), now=NOW + 1.0)
    mission.apply(AgentParams(), round((NOW + 1.0) * 1e9))
    later = NOW + 1.7   # s1 ... are out of the window, s0 is not
    assert offer(mission, body("set", seq=1, sender="new", radius=5.0, stamp=later), now=later)
    assert "s0" in mission._senders and "s1" not in mission._senders


def test_a_flood_from_one_sender_neither_refuses_nor_delays_another_senders_hold():
    mission, counted = orders()
    for n in range(3000):
        offer(mission, body("set", seq=n + 1, sender="flood", session="f", radius=5.0))
    assert offer(mission, body("hold", seq=1, session="op1"))
    assert ("op", 1, "hold") in applied(mission) and mission.held        # at the very next tick
    flood = [k for k in counted if k == "mission_flood"]
    assert len(flood) == 3000 - channel.MAX_PENDING_PER_SENDER           # the flood's own, and only those


def test_a_hold_is_never_refused_for_a_full_queue_even_its_own_senders():
    mission, counted = orders()
    for n in range(channel.MAX_PENDING_PER_SENDER):
        assert offer(mission, body("set", seq=n + 1, radius=5.0))
    assert not offer(mission, body("resume", seq=100))
    assert offer(mission, body("hold", seq=101))
    assert counted == ["mission_flood", "mission_flood"]                 # the resume, and the oldest set
    for _ in range(3):
        mission.apply(AgentParams(), round(NOW * 1e9))
    assert mission.held
    # Beyond the ids a window may hold, only a hold goes on being taken.
    for n in range(channel.MAX_IDS_PER_SENDER):
        offer(mission, body("set", seq=200 + n, radius=5.0))
        mission.apply(AgentParams(), round(NOW * 1e9))
    assert not offer(mission, body("resume", seq=1000))
    assert offer(mission, body("hold", seq=1001))


def test_the_tick_drains_the_queues_in_rounds_one_command_of_each_sender_a_round():
    mission, _ = orders()
    for n in range(10):
        assert offer(mission, body("set", seq=n + 1, sender="a", radius=5.0))
    assert offer(mission, body("hold", seq=1, sender="b"))
    first = applied(mission)
    assert ("b", 1, "hold") in first and len(first) == 11                # under DRAIN_PER_TICK: all of them
    for n in range(channel.MAX_SENDERS):
        offer(mission, body("set", seq=1, sender=f"r{n}", radius=5.0, stamp=NOW + 0.01), now=NOW + 0.01)
    taken = applied(mission, NOW + 0.01)
    assert len(taken) == channel.MAX_SENDERS - 2                         # one round of every sender with one waiting


def test_an_applied_answer_reaches_a_status_through_a_storm_of_refused_senders():
    mission, _ = orders()
    assert offer(mission, body("hold", seq=1, session="op1"))
    mission.apply(AgentParams(), round(NOW * 1e9))
    for n in range(2000):                                                 # stale commands of new senders
        offer(mission, body("set", seq=1, sender=f"j{n}", radius=5.0, stamp=NOW - 5.0))
    shown = mission.acks()
    assert len(shown) == channel.STATUS_ACKS and ("op", 1) in [(a.sender, a.seq) for a in shown]
    assert len(mission._acks) <= channel.MAX_SENDERS


def test_random_traffic_keeps_every_table_bounded_and_applies_no_command_twice():
    """Seeded random senders, sessions, seqs, stamps and replays of earlier payloads over a moving clock."""
    for seed in (1, 2):
        rng = np.random.default_rng(seed)
        mission, _ = orders()
        sent: list[bytes] = []
        applied_at: dict[tuple, float] = {}
        replays = 0
        now = NOW
        for tick in range(300):
            now += 0.1
            for _ in range(int(rng.integers(0, 40))):
                if sent and rng.random() < 0.3:
                    payload = sent[int(rng.integers(len(sent)))]       # a replay of anything sent before
                    replays += 1
                else:
                    sender = f"s{int(rng.integers(0, 400))}"
                    payload = body(str(rng.choice(["hold", "resume", "start"])), seq=int(rng.integers(0, 50)),
                                   sender=sender, session=str(rng.choice(["", "x", "y"])),
                                   stamp=now + float(rng.uniform(-1.2, 0.7)))
                    sent.append(payload)
                offer(mission, payload, now)
            mission.apply(AgentParams(), round(now * 1e9))
            for message, ack, _ in mission.judged():
                if ack.applied:
                    # The same command (a replay is the same payload, stamp included) is applied once at most.
                    name = (message.sender, message.session, message.seq, message.stamp_ns)
                    assert name not in applied_at, name
                    applied_at[name] = now
            assert len(mission._senders) <= channel.MAX_SENDERS and len(mission._acks) <= channel.MAX_SENDERS
            assert all(len(s.ids) <= channel.MAX_IDS_PER_SENDER and len(s.pending) <= channel.MAX_PENDING_PER_SENDER
                       for s in mission._senders.values())
            assert len(mission.acks()) <= channel.STATUS_ACKS
        assert replays > 1000 and len(applied_at) > 1000
