"""Built-in conditioners: each module is one plugin registered through the conditioner hook.

- ``label``: a learned embedding per class label;
- ``tactile`` and ``visual_cnn``: one small convolutional encoder trained from scratch
  (:mod:`.image_cnn`), of the paired sensor's tactile image or of the visual image;
- ``tactile_codes``: the paired sensor's tactile image as its codes under that sensor's own
  frozen tokenizer (another run), embedded;
- ``visual``: the frozen ImageNet EfficientNet-Lite0 that installs offline, for visual images;
- ``clip``: a frozen, locally supplied open_clip image encoder for visual images;
- ``text``: the frozen text tower of a locally supplied open_clip model, per-token states projected;
- ``text_scratch``: a small word-level text encoder trained from scratch (hashed words, offline).
"""
