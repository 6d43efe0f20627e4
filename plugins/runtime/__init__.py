"""Run folders and command outputs.

- :mod:`.run_dir`: :class:`~.run_dir.RunDir`, a run's folder (config, products, checkpoints, metrics);
- :mod:`.records`: what a run records of its config and environment;
- :mod:`.interruptions`: what a training command stopped by Ctrl-C or SIGTERM says, and its exit status;
- :mod:`.outputs`: every command's output folder, staged and moved into place, never inside what it reads.
"""
