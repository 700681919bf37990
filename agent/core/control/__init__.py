"""Circumnavigation control, Sec. IV: coupled oscillator, formation controller, obstacle avoidance."""
