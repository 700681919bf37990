"""Between the wire and the core: a contract message to the tick's record and back.

The contract (agent/contract.py) holds the messages only, so a bridge that imports it loads no part of the
core; the agent's shell, which speaks both, translates here. Time is whole nanoseconds on the wire and
seconds in the core; a pair covariance travels as its three numbers p11, p12, p22.
"""

from __future__ import annotations

import numpy as np

from agent.contract import Odometry, PairEstimate, ReceivedShare, ShareMessage, nanoseconds, seconds
from agent.core.records import OdometryReading, Share


def odometry_reading(message: Odometry) -> OdometryReading:
    return OdometryReading(seconds(message.stamp_ns), np.array(message.position, dtype=float), message.heading)


def share_from_message(message: ShareMessage | ReceivedShare,
                       neighbours: dict[str, PairEstimate] | None = None) -> Share:
    """The core's Share of a message; its pair estimates are `neighbours` if given (a `ReceivedShare`'s are
    not checked), else the message's."""
    neighbours = message.neighbours if neighbours is None else neighbours
    return Share(
        sender=message.sender,
        odometry=OdometryReading(seconds(message.stamp_ns), np.array(message.position, dtype=float),
                                 message.heading),
        velocity=np.array(message.velocity, dtype=float),
        phase=message.phase,
        target=None if message.target is None else np.array(message.target, dtype=float),
        target_covariance=None if message.target_covariance is None
        else np.array(message.target_covariance, dtype=float).reshape(4, 4),
        neighbours={j: (*map(float, e.position), *map(float, e.covariance),
                        seconds(message.stamp_ns if e.stamp_ns is None else e.stamp_ns))
                    for j, e in neighbours.items()},
        antenna=None if message.antenna is None else (float(message.antenna[0]), float(message.antenna[1])),
    )


def message_from_share(share: Share, seq: int) -> ShareMessage:
    # Validated from plain values in one call: building the nested models one by one costs half as much again.
    odometry, covariance = share.odometry, share.target_covariance
    return ShareMessage.model_validate({
        "stamp_ns": nanoseconds(odometry.stamp), "seq": seq, "sender": share.sender,
        "position": np.asarray(odometry.position, dtype=float).tolist(), "heading": float(odometry.heading),
        "velocity": np.asarray(share.velocity, dtype=float).tolist(), "phase": float(share.phase),
        "target": None if share.target is None else np.asarray(share.target, dtype=float).tolist(),
        "target_covariance": None if covariance is None else np.asarray(covariance, dtype=float).ravel().tolist(),
        "neighbours": {j: {"position": (px, py), "covariance": (p11, p12, p22), "stamp_ns": nanoseconds(stamp)}
                       for j, (px, py, p11, p12, p22, stamp) in share.neighbours.items()},
        # Absent when at the centre: a receiver that predates the field reads the share as before.
        **({} if share.antenna is None else {"antenna": [float(v) for v in share.antenna]}),
    })

