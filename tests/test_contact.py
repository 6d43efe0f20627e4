"""The contact region (plugins/evaluation/contact.py): the floor on noise-free images, the noise
bar under DIGIT's published camera noise, and a press recovered through that noise."""

import torch

from vqtouch.plugins.evaluation.contact import CONTACT_THRESHOLD, NOISE_FACTOR, contact_mask

NOISE = 7 / 255  # DIGIT's published camera noise (tacto's config_digit.yml)


def _press(size=64):
    background = torch.full((4, 3, size, size), 0.5)
    images = background.clone()
    images[:, :, 10:30, 20:40] += 0.3  # a press covering 400 of 4096 pixels
    return images, background


def test_noise_free_images_use_the_floor_exactly():
    images, background = _press()
    images[:, :, 40:44, :] += CONTACT_THRESHOLD * 1.5  # just above the floor
    images[:, :, 50:54, :] += CONTACT_THRESHOLD * 0.5  # just below
    mask = contact_mask(images, background)
    expected = torch.zeros(4, 64, 64, dtype=torch.bool)
    expected[:, 10:30, 20:40] = True
    expected[:, 40:44, :] = True
    assert torch.equal(mask, expected)


def test_camera_noise_alone_is_not_contact_and_a_press_shows_through_it():
    generator = torch.Generator().manual_seed(0)
    images, background = _press()
    noisy = images + NOISE * torch.randn(images.shape, generator=generator)
    noisy_background = background + NOISE * torch.randn(background.shape, generator=generator)
    flat = background + NOISE * torch.randn(background.shape, generator=generator)
    # Without the noise bar, 7/255 noise on both sides puts most pixels above the 0.02 floor.
    assert float(((flat - noisy_background).abs().mean(dim=1) > CONTACT_THRESHOLD).double().mean()) > 0.5
    assert float(contact_mask(flat, noisy_background).double().mean()) < 1e-3
    mask = contact_mask(noisy, noisy_background)
    truth = torch.zeros_like(mask)
    truth[:, 10:30, 20:40] = True
    assert float((mask & truth).sum() / (mask | truth).sum()) > 0.98  # intersection over union
    assert NOISE_FACTOR * NOISE * 2**0.5 < 0.3  # the press is well above the bar it sets
