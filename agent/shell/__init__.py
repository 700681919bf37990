"""The agent process: the Zenoh node, its input gate, its settings and its tick log."""
