"""Cross-sensor stages: sensor-family clustering, unseen-sensor assignment and few-shot adaptation."""
