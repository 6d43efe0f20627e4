"""Generator stage: the discrete-diffusion decoder over the tokenizer's code grid, its conditioners and samplers."""
