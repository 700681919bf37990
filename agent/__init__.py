"""Onboard agent of one vessel: estimation, control and (later) the Zenoh runtime."""
