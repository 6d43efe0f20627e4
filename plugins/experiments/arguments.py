"""Argument types the experiments' parsers share, light: a parser is built whenever plugins load."""

from __future__ import annotations


def feature_size_argument(text: str) -> int:
    """``--feature-size``'s type, :func:`vqtouch.plugins.evaluation.feature_networks.feature_size_argument`,
    imported when the option is given: that module imports torch, which a parser must not (same name, so
    argparse's messages are the same)."""
    from vqtouch.plugins.evaluation.feature_networks import feature_size_argument as parse

    return parse(text)
