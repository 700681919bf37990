"""Attacks on the mission keys and on liveliness, over real processes: one agent process and usv-op, the world
played by Zenoh sessions (lab/benchmarks/fuzz.py AttackHarness, the cases `usv-lab fuzz` runs too). After each
attack the operator's own `usv-op hold` and `usv-op resume` must be applied, and no command of the agent may
be non-finite or beyond its limits."""

from __future__ import annotations

import pytest

from lab.benchmarks.fuzz import LIVELINESS_ATTACKS, MISSION_ATTACKS, run_attacks

pytestmark = pytest.mark.slow   # an agent process and usv-op over Zenoh at the pace of real time


@pytest.fixture(scope="module")
def mission_attacks(tmp_path_factory):
    return run_attacks(cases=MISSION_ATTACKS, folder=tmp_path_factory.mktemp("mission"))


@pytest.fixture(scope="module")
def liveliness_attacks(tmp_path_factory):
    return run_attacks(cases=LIVELINESS_ATTACKS, folder=tmp_path_factory.mktemp("liveliness"))


def check_sound(results) -> None:
    assert results.alive_at_end and results.exit_code == 0, results.stderr_tail
    assert results.commands > 100 and results.bad_commands == []


def check_operator(attack) -> None:
    assert not attack.detail, attack.detail
    for command, code, said in attack.operator:
        assert code == 0 and "applied" in said, (attack.name, command, said)


def test_a_seq_of_2_63_does_not_lock_the_operator_out(mission_attacks):
    check_operator(mission_attacks.by_name()["seq_lockout"])
    check_sound(mission_attacks)


def test_a_hold_replayed_within_the_window_after_300_new_senders_is_not_applied_again(mission_attacks):
    attack = mission_attacks.by_name()["junk_senders_replay"]
    assert attack.verdict and not attack.figures["held_after_replay"], attack.figures
    assert attack.figures["refused_replayed"] >= 1
    check_operator(attack)


def test_a_flood_from_one_sender_does_not_refuse_the_operators_hold(mission_attacks):
    attack = mission_attacks.by_name()["flood"]
    assert attack.figures["flood_commands"] > 1000 and attack.figures["held"], attack.figures
    check_operator(attack)


def test_300_forged_tokens_do_not_keep_a_restarted_vessel_out(liveliness_attacks):
    attack = liveliness_attacks.by_name()["spoofed_alive_restart"]
    assert attack.figures["peers_in_status"] >= 200                      # the forgeries did fill the table
    assert attack.figures["evicted"] >= 1                                # and took the place 2 left
    assert attack.figures["vessel_2_live"] and attack.figures["proven_after_s"], attack.figures
    check_operator(attack)
    check_sound(liveliness_attacks)


def test_a_process_that_declares_a_killed_vessels_token_is_not_taken_for_it(liveliness_attacks):
    attack = liveliness_attacks.by_name()["takeover_after_kill"]
    assert attack.figures["shares_with_3_in_last_half"] == 0, attack.figures
    check_operator(attack)
