"""The ``vqtouch`` command line: core's commands and every plugin's, through ``vqtouch_add_commands``."""

from .app import main

__all__ = ["main"]
