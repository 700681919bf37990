"""Circumnavigation control, Sec. IV: coupled oscillator (28), formation controller (27), (29), (31), (33),
obstacle avoidance (34); agent/core/command.py assembles (30), (32), (35) from them."""
