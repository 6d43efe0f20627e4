"""Built-in model, metric and scene plugins, each registered through the vqtouch hooks."""
