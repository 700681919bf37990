"""What the experiments run on: the in-process fleet runner, the parallel engines (process pool, Dask
cluster), running error moments, and the operator's mission plan of an in-process run."""
