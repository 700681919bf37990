"""Benchmarks: estimator cost, fleet and runtime cost, the shells in process, the transport floor, the
cluster, the sea mode, and the fuzz campaigns over Zenoh and serial lines."""
