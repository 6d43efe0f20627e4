"""Generator stage: the discrete-diffusion decoder over the tokenizer's code grid, its samplers, training and
generation (``load_pipeline``)."""


def load_pipeline(*args, **kwargs):
    """The generation pipeline of a trained run; see :func:`vqtouch.plugins.generator.pipeline.load_pipeline`
    (imported on first use, so importing this package stays light)."""
    from .pipeline import load_pipeline as load

    return load(*args, **kwargs)
