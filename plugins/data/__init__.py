"""Data stage: the embedded procedural dataset, readers of public datasets and `vqtouch data` commands."""
