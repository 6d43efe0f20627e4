"""Evaluation: image metrics and the frozen feature networks behind them."""
