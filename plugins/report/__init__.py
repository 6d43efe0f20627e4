"""The demo and its report: ``vqtouch demo`` runs a scene's stages end to end and writes report.json,
report.md and a self-contained report.html; ``vqtouch report`` rebuilds the pages of a demo run.

At the top of the plugin layers (docs/architecture.md): it runs every stage through core's
``run_stage`` and reads their results by key convention only, so it imports no stage.
"""
