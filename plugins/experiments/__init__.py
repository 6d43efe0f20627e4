"""Experiments across stages: the drivers that combine what several stages made.

``downstream`` (the paper's Table 3: recognition from generated images) and ``pipeline_tradeoff``
(the whole pipeline's speed/accuracy trade) train and load tokenizers and generators and score them
with the evaluation library.  They sit at the top of the plugin layers (docs/architecture.md): they
import the stage packages' public APIs and the evaluation library, and nothing imports them.

Each experiment's entry point is a light ``*_plugin`` module (its options, its stage's section and their
registration); the experiment itself is imported when its command or stage runs.
"""
