"""``python -m vqtouch.plugins.cli``: the ``vqtouch`` command."""

from .app import main

if __name__ == "__main__":
    raise SystemExit(main())
