"""Hardware adapters of the driver bridge (UWB, odometry, bearing, thrusters, serial port): pure, no Zenoh."""
