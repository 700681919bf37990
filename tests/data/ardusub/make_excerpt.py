"""Cut tests/data/ardusub/excerpt.tlog from clydemcqueen/ardusub_log_tools testing/small.tlog (README.md).

Keeps whole tlog records (8-byte big-endian microsecond stamp + the MAVLink frame as received), in order:
the autopilot's (system 1, component 1) records of the types the test reads, from START_S to END_S after the
log's first record, and the PARAM_VALUE giving EK3_GYRO_P_NSE. Each record is checked to be in the source byte
for byte. Usage: python make_excerpt.py SMALL_TLOG OUT
"""

import os
import struct
import sys

START_S, END_S = 20.0, 50.0
TYPES = {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "TIMESYNC",
         "EKF_STATUS_REPORT"}
PARAMS = {"EK3_GYRO_P_NSE"}


def main(source: str, out: str) -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    raw = open(source, "rb").read()
    log = mavutil.mavlink_connection(source, dialect="ardupilotmega")
    first, records = None, []
    while (msg := log.recv_msg()) is not None:
        first = msg._timestamp if first is None else first
        if (msg.get_srcSystem(), msg.get_srcComponent()) != (1, 1):
            continue
        kind, since = msg.get_type(), msg._timestamp - first
        if (kind in TYPES and START_S <= since < END_S) or (kind == "PARAM_VALUE" and msg.param_id in PARAMS):
            record = struct.pack(">Q", round(msg._timestamp * 1e6)) + bytes(msg.get_msgbuf())
            assert record in raw, "a record not byte for byte in the source"
            records.append(record)
    with open(out, "wb") as f:
        f.write(b"".join(records))
    print(f"{len(records)} records, {sum(map(len, records))} bytes")


if __name__ == "__main__":
    main(*sys.argv[1:3])
