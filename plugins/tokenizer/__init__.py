"""Tokenizer stage: autoencoders (VQGAN, DM-VQGAN, MAE), quantizers, discriminators, losses, training and commands."""
