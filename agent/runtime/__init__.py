"""What every process of the product shares: Zenoh session settings, the vessel-process command line, MCAP logs and Foxglove messages."""
