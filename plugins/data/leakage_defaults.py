"""The leakage check's defaults, light so that the ``vqtouch data leakage`` parser shows them (the check, in
leakage.py, imports torch)."""

#: Side of the square images are compared at.
COMPARE_SIZE = 32
#: Near-duplicate threshold, mean absolute difference in 8-bit levels (measured: see leakage.py's docstring).
DEFAULT_THRESHOLD = 0.25
