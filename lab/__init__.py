"""The lab behind `usv-lab` (needs the lab extra): `harness` (the in-process runner, parallel engines),
`experiments`, `benchmarks` and `report` (tables and figures); `cli` lists every subcommand."""
