"""Offline experiments: estimator comparison, real-data replay, benchmarks (needs the lab extra)."""
