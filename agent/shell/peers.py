"""Who counts as a neighbour: the table of live liveliness tokens, bounded, and the proof a vessel id owes
when it comes back.

A token (`usv/<id>/alive`) says nothing about who declared it, so the table (at most MAX_PEERS ids) is
not first come, first served:
- evidence ranks the entries: our own UWB module ranging to an id (`ranged`, within RANGED_WITHIN s). A
  new token evicts, when the table is full, the oldest entry without that evidence (unproven before
  proven); an entry both ranged and proven is never evicted (`peers_evicted` counts those that made room);
- an id declared for the first time in this agent's life is taken at its word; an id declared again is
  watched for its session: its claimed odometry is judged against our ranges (agent/core/vetting.py).
  SUSTAIN agreements in a row prove it; DOUBT disagreements in a row before that, or one misfit beyond
  REFUTE, refute it: its shares and ranges no longer reach the core for the rest of its session.

More: docs/reliability.md §4, `agent/shell/peers.py`.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from agent.contract import MAX_PEERS
from agent.core.median import median
from agent.core.records import TickInputs, TickRecord
from agent.core.vetting import range_residuals, residual_trend

RANGED_WITHIN = 2.0      # s: a range to an id this recent is evidence of it
MAX_SEEN = 4 * MAX_PEERS  # ids remembered as declared before (a forged token's id is forgotten first)
HISTORY = 64             # odometry samples (own, and each candidate's claimed) kept for pairing with ranges
WINDOW = 50              # paired samples a proof is judged over (5 s at 10 Hz)
MIN_SAMPLES = 30         # paired samples before a proof with a learnt offset is judged
MIN_FREE_SAMPLES = 50    # ... and without one (the offset fitted too)
TOLERANCE = 1.0          # m: the median |range - predicted| a proof allows
# m: how far the residuals may move over the window (vetting.py residual_trend). Genuine claims leave only the
# noise's trend: under Table II's ranges the two medians of 16 spread it by about 0.33 m, so 0.6 m (1.8 of
# that) failed 7 % of honest windows and refuted about 1 % of honest sessions per neighbour (20 failures in a
# row of overlapping windows; two of 73 restart process tests). 1.0 m is about three spreads: 0.3 % of honest
# windows fail, and no honest session of 4000 simulated was refuted.
TREND = 1.0
STILL_MARGIN = 0.2       # m: how much worse than a hull lying still the claims may fit the ranges
SUSTAIN = 30             # judgements in a row that must agree (a lie agreeing by chance for a moment does not)
REFUTE = 2.0             # a misfit beyond this many tolerances refutes an id declared again, for its session
DOUBT = 20               # judgements in a row that disagree refute an id not yet proven
PAIR_GAP = 0.5           # s: the widest gap between two odometry samples a range is interpolated across
OFFSET_MAX_AGE = 600.0   # s: an offset learnt longer ago than this is not used


class Entry:
    __slots__ = ("agreed", "claimed", "declared", "doubted", "pending", "proven", "refuted", "samples", "watched")

    def __init__(self, declared: int, proven: bool) -> None:
        self.declared = declared          # the order of its declaration (oldest first out)
        self.proven = proven
        self.watched = not proven         # declared again: judged by its ranges for the whole session
        self.agreed = 0                   # judgements in a row that found its claims in agreement
        self.doubted = 0                  # ... and that did not
        self.refuted = False              # its claims were found far from the ranges: not for this session
        self.claimed: deque[tuple[float, float, float]] = deque(maxlen=HISTORY)   # (stamp, x, y) it claims
        self.pending: deque[tuple[float, float]] = deque(maxlen=HISTORY)          # (stamp, range) to pair
        self.samples: deque[tuple[float, float, float, float, float]] = deque(maxlen=WINDOW)


class PeerTable:
    """Live tokens and their standing. `declare`/`undeclare` run on Zenoh's threads, `vet`/`learn` on the
    tick thread."""

    def __init__(self, ranged: Callable[[str], bool], max_peers: int = MAX_PEERS,
                 tolerance: float = TOLERANCE) -> None:
        self._ranged = ranged
        self.max_peers = max_peers
        self.tolerance = tolerance
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._entries: dict[str, Entry] = {}
        self._declarations = 0
        self._seen: OrderedDict[str, None] = OrderedDict()   # ids declared before (ranged ones kept longest)
        self._offsets: dict[str, tuple[np.ndarray, float]] = {}   # id -> (c, when learnt): vetting.py
        self._own: deque[tuple[float, float, float]] = deque(maxlen=HISTORY)
        self._withheld: frozenset[str] = frozenset()

    # ----- tokens (Zenoh's threads) -----
    def declare(self, peer: str) -> tuple[bool, list[str]]:
        """A token of `peer` came: (admitted, the ids evicted to make room)."""
        with self._lock:
            if peer in self._entries:
                return True, []
            evicted = []
            if len(self._entries) >= self.max_peers:
                victim = self._victim(self._ranged(peer))
                if victim is None:
                    self.counts["peers_refused"] += 1
                    return False, []
                del self._entries[victim]
                evicted.append(victim)
                self.counts["peers_evicted"] += 1
            again = peer in self._seen
            self._seen[peer] = None
            self._seen.move_to_end(peer)
            while len(self._seen) > MAX_SEEN:
                # An id that was never ranged goes first: forged tokens cannot wash a vessel out of memory.
                old = next((i for i in self._seen if i not in self._offsets and not self._ranged(i)),
                           next(iter(self._seen)))
                del self._seen[old]
            self._declarations += 1
            self._entries[peer] = Entry(self._declarations, proven=not again)
            if again:
                self.counts["peers_to_prove"] += 1
            self._update()
            return True, evicted

    def token(self, peer: str, alive: bool, gate) -> bool:
        """`peer`'s token came (`alive`) or went; the input `gate` forgets what it holds of the ids that leave
        the table and of `peer`'s earlier session (nothing of it counts). Whether the live ids changed."""
        if not alive:
            self.undeclare(peer)
            gate.forget(peer)
            return True
        if peer in self._entries:
            return False
        admitted, evicted = self.declare(peer)
        for other in evicted:
            gate.forget(other)
        if not admitted:
            gate.count("too_many_peers", f"liveliness: {peer}")
            return False
        gate.forget(peer)
        return True

    def undeclare(self, peer: str) -> None:
        with self._lock:
            self._entries.pop(peer, None)
            self._update()

    def counted(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)

    def live(self) -> frozenset[str]:
        with self._lock:
            return frozenset(self._entries)

    def withheld(self) -> frozenset[str]:
        """The ids whose shares and ranges do not reach the core (refuted)."""
        return self._withheld

    def unproven(self) -> frozenset[str]:
        """The ids declared again whose claims have not (yet) agreed with the ranges long enough."""
        with self._lock:
            return frozenset(p for p, e in self._entries.items() if e.watched and not e.proven)

    def _victim(self, newcomer_ranged: bool) -> str | None:
        """The entry a new token evicts: the oldest without ranges, unproven before proven; for a ranged
        newcomer then the oldest unproven with ranges; None: keep them all."""
        ranked = sorted(self._entries.items(), key=lambda item: item[1].declared)
        unranged = [(p, e) for p, e in ranked if not self._ranged(p)]
        for peer, entry in unranged:
            if not entry.proven:
                return peer
        if not newcomer_ranged:
            return None
        if unranged:
            return unranged[0][0]
        return next((p for p, e in ranked if not e.proven), None)

    # ----- the tick -----
    def vet(self, inputs: TickInputs) -> TickInputs:
        """Gather the evidence of this tick for each id declared again and judge it; the inputs without the
        shares and ranges of those refuted (the inputs themselves when there is none)."""
        if inputs.odometry is not None and (not self._own or inputs.odometry.stamp > self._own[-1][0]):
            self._own.append((inputs.odometry.stamp, *map(float, inputs.odometry.position)))
        with self._lock:
            entries = {p: e for p, e in self._entries.items() if e.watched and not e.refuted}
        if entries:
            self._judge(inputs, entries)
        withheld = self._withheld
        if not withheld:
            return inputs
        return replace(inputs, shares={p: s for p, s in inputs.shares.items() if p not in withheld},
                       ranges={p: r for p, r in inputs.ranges.items() if p not in withheld},
                       earlier_ranges=tuple((t, {p: r for p, r in ranges.items() if p not in withheld})
                                            for t, ranges in inputs.earlier_ranges))

    def _judge(self, inputs: TickInputs, entries: dict[str, Entry]) -> None:
        sets = [*inputs.earlier_ranges, (inputs.time if inputs.range_stamp is None else inputs.range_stamp,
                                         inputs.ranges)]
        verdicts = {}
        for peer, entry in entries.items():
            share = inputs.shares.get(peer)
            if share is not None and (not entry.claimed or share.odometry.stamp > entry.claimed[-1][0]):
                entry.claimed.append((share.odometry.stamp, *map(float, share.odometry.position)))
            entry.pending.extend((stamp, float(ranges[peer])) for stamp, ranges in sets if peer in ranges)
            self._pair(entry)
            judged = self._misfit(peer, entry, inputs.time)
            if judged is None:
                continue
            if judged[0] > REFUTE * self.tolerance:
                verdicts[peer] = "refuted"
                continue
            agrees = judged[0] <= self.tolerance and abs(judged[1]) <= TREND and judged[2] <= STILL_MARGIN
            entry.agreed, entry.doubted = (entry.agreed + 1, 0) if agrees else (0, entry.doubted + 1)
            if not entry.proven and entry.doubted >= DOUBT:
                verdicts[peer] = "refuted"
            elif not entry.proven and entry.agreed >= SUSTAIN:
                verdicts[peer] = "proven"
        with self._lock:
            for peer, verdict in verdicts.items():
                entry = entries[peer]
                if self._entries.get(peer) is not entry:
                    continue   # gone (or declared again) meanwhile
                if verdict == "refuted":
                    entry.refuted, entry.proven = True, False
                else:
                    entry.proven = True
                self.counts[f"peers_{verdict}"] += 1
            self._update()

    def _update(self) -> None:
        """(with the lock) The ids whose shares and ranges are withheld from the core: refuted ones."""
        self._withheld = frozenset(p for p, e in self._entries.items() if e.refuted)

    def learn(self, inputs: TickInputs, record: TickRecord | None) -> None:
        """The offset c between our odometry frame and each localised neighbour's (agent/core/vetting.py):
        c = p_ij - a + b at the tick's time, from the core's estimate p_ij, our odometry a and the neighbour's
        b carried to the tick with its commanded velocity."""
        if record is None or inputs.odometry is None:
            return
        own = np.asarray(inputs.odometry.position, dtype=float)
        for peer, neighbour in record.neighbours.items():
            share = inputs.shares.get(peer)
            if not neighbour.localised or share is None:
                continue
            theirs = (np.asarray(share.odometry.position, dtype=float)
                      + np.asarray(share.velocity, dtype=float) * (inputs.time - share.odometry.stamp))
            offset = np.asarray(neighbour.position, dtype=float) - own + theirs
            if np.all(np.isfinite(offset)):
                self._offsets[peer] = (offset, inputs.time)
        if len(self._offsets) > MAX_PEERS:
            oldest = sorted(self._offsets, key=lambda p: self._offsets[p][1])
            for peer in oldest[:len(self._offsets) - MAX_PEERS]:
                del self._offsets[peer]

    def _pair(self, entry: Entry) -> None:
        """Each pending range whose time both odometries cover becomes a sample; one neither will cover
        (older than what is kept) is dropped."""
        keep = deque(maxlen=HISTORY)
        for stamp, value in entry.pending:
            own, claimed = _at(self._own, stamp), _at(entry.claimed, stamp)
            if own is not None and claimed is not None:
                entry.samples.append((*own, *claimed, value))
            elif self._own and stamp >= self._own[0][0] and (not entry.claimed or stamp >= entry.claimed[0][0]):
                keep.append((stamp, value))
        entry.pending = keep

    def _misfit(self, peer: str, entry: Entry, now: float) -> tuple[float, float, float] | None:
        """(the median |range - predicted| (m), how far the residuals moved over the window (m), how much worse
        the claims fit than a hull lying still (m)) of the latest WINDOW samples: at the offset learnt while it
        was here, else at the offset that fits them best; None while there are too few samples."""
        samples = np.asarray(entry.samples, dtype=float).reshape(-1, 5)[-WINDOW:]
        learnt = self._offsets.get(peer)
        if learnt is not None and now - learnt[1] > OFFSET_MAX_AGE:
            learnt = None
        if len(samples) < (MIN_SAMPLES if learnt is not None else MIN_FREE_SAMPLES):
            return None
        residuals = range_residuals(samples[:, 0:2], samples[:, 2:4], samples[:, 4],
                                    None if learnt is None else learnt[0])
        misfit = median(np.abs(residuals))
        # The simpler story: a hull lying still where the ranges put it. Claims of motion that fit the ranges
        # worse than that are not believed (a dead vessel's slot on the circle, claimed while its hull drifts).
        still = median(np.abs(range_residuals(samples[:, 0:2], np.zeros((len(samples), 2)), samples[:, 4])))
        return misfit, residual_trend(residuals), misfit - still


def _at(history: deque, stamp: float) -> tuple[float, float] | None:
    """The (x, y) of `history` ((stamp, x, y), oldest first) at `stamp`, interpolated between the samples
    around it when they are at most PAIR_GAP apart; None outside it."""
    if not history or stamp < history[0][0] - 1e-9 or stamp > history[-1][0] + 1e-9:
        return None
    for (t0, x0, y0), (t1, x1, y1) in zip(list(history)[-1::-1][1:], list(history)[::-1]):
        if t0 - 1e-9 <= stamp:
            if abs(stamp - t1) <= 1e-9:
                return x1, y1
            if t1 - t0 > PAIR_GAP:
                return None
            w = (stamp - t0) / (t1 - t0) if t1 > t0 else 0.0
            return x0 + w * (x1 - x0), y0 + w * (y1 - y0)
    t0, x0, y0 = history[0]
    return (x0, y0) if abs(stamp - t0) <= 1e-9 else None
