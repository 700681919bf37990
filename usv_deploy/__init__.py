"""Operator tooling for real boats: fleet inventory to per-vessel configuration, certificates, the shore router."""
