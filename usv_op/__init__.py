"""The operator's station: `usv-op`, mission commands and the live fleet from the shore."""
