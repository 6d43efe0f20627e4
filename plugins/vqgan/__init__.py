"""VQGAN and DM-VQGAN tokenizer autoencoders."""
