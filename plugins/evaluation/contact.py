"""Where a tactile image shows a contact: the pixels that differ from the sensor's no-contact image.

Tactile images are mostly static background, so scores and checks that matter look at the
contact region.  A pixel is in it when its mean absolute difference from the background over the
RGB channels exceeds both a fixed floor and what the camera's noise alone would produce: the noise
level is estimated from the differences themselves (1.4826 x their median absolute value, the
normal-consistent median absolute deviation: most pixels of a tactile image are background, so
the median sees noise, not contact), and the mean absolute value of three channels of pure
Gaussian noise exceeds :data:`NOISE_FACTOR` sigma on about 6e-5 of the pixels.  Noise-free
renders (GelSight) keep the floor exactly; DIGIT's published 7/255 camera noise raises the bar
instead of turning every pixel into "contact".
"""

from __future__ import annotations

import torch

#: A pixel is in contact where it differs from the background by more than this (mean absolute
#: difference over the channels, images in [0, 1]), when the noise allows no less.
CONTACT_THRESHOLD = 0.02
#: ... and by more than this many standard deviations of the estimated noise.
NOISE_FACTOR = 2.5


def contact_mask(images_B3HW: torch.Tensor, background_B3HW: torch.Tensor,
                 threshold: float = CONTACT_THRESHOLD) -> torch.Tensor:
    """(B, H, W) bool: the pixels of ``images_B3HW`` in contact, given the no-contact image(s)
    ``background_B3HW`` (broadcast against the images; see the module docstring)."""
    difference = images_B3HW.detach().float().cpu() - background_B3HW.detach().float().cpu()
    noise_sigma = 1.4826 * float(difference.abs().median())
    return difference.abs().mean(dim=1) > max(threshold, NOISE_FACTOR * noise_sigma)
