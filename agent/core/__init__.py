"""The per-vessel core: estimators, control, fusion and the tick, as plain numpy code with no I/O."""
