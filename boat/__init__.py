"""The boat below the agent's command: hull presets, twin-thruster allocation and the inner loop (pure numpy).

Shared by the sim bridge (which simulates the hull, `sim_bridge/hull.py`) and the driver bridge (which runs
the same inner loop on a real twin-thruster hull). It imports only `agent.config` and `agent.angles`.
"""
