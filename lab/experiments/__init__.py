"""The experiments: the estimator comparison (Experiment 1) and its bound, the scenario Monte Carlo (Tables
II-IV), real-data replay and the public UWB data sets, the cold start and the observability study."""
