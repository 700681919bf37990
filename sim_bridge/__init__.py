"""Stand-in for the hardware: world model, sensor noise, and offline experiments."""
