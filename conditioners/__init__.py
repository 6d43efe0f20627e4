"""Built-in conditioners: each module is one plugin registered through the conditioner hook.

- ``label``: a learned embedding per class label;
- ``tactile``: a small trainable convolutional encoder of a tactile image;
- ``clip``: a frozen, locally supplied open_clip image encoder for visual images.
"""
