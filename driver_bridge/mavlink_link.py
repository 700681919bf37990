"""The MAVLink connection of `mavlink_vehicle` (pymavlink's mavutil): opened by URL, read without blocking.

`open_link(url, baud, system, component)` -> a `Link` whose `fd` the driver's select waits on, `messages()`
the parsed messages waiting (garbage comes out as BAD_DATA, which the vehicle counts), `send(msg)` and
`mav`, the encoder. MAVLink 2 is spoken (ArduPilot answers in the version it hears). pymavlink is in the
optional extra `driver`; without it `open_link` raises one clear line (MissingExtra).
"""

from __future__ import annotations

import os

MISSING = ("the MAVLink vehicle needs pymavlink, in the optional extra 'driver': "
           "pip install 'usv-circumnav[driver]'")
MAX_PER_READ = 256   # messages taken per call, so that a flood cannot hold the loop


class MissingExtra(RuntimeError):
    pass


def mavlink_module():
    """pymavlink's MAVLink 2 dialect of ArduPilot, and mavutil; MissingExtra without the extra."""
    os.environ.setdefault("MAVLINK20", "1")   # mavutil picks the wire version from the environment
    try:
        from pymavlink import mavutil
        from pymavlink.dialects.v20 import ardupilotmega
    except ImportError:
        raise MissingExtra(MISSING) from None
    return mavutil, ardupilotmega


class Link:
    def __init__(self, url: str, baud: int, system: int, component: int) -> None:
        mavutil, _ = mavlink_module()
        try:
            self.connection = mavutil.mavlink_connection(url, baud=baud, source_system=system,
                                                         source_component=component, autoreconnect=True)
        except ImportError as error:   # mavutil opens a serial device with pyserial (the extra's, not its own)
            raise MissingExtra(f"a serial MAVLink link ({url}) needs pyserial, in the optional extra 'driver': "
                               f"pip install 'usv-circumnav[driver]' ({error.msg})") from None
        self.mav = self.connection.mav
        self.fd = self.connection.fd

    def messages(self) -> list:
        out = []
        while len(out) < MAX_PER_READ:
            msg = self.connection.recv_msg()
            if msg is None:
                break
            out.append(msg)
        return out

    def send(self, msg) -> None:
        self.mav.send(msg)

    def close(self) -> None:
        self.connection.close()


def open_link(url: str, baud: int, system: int, component: int) -> Link:
    return Link(url, baud, system, component)
