"""``generator.model.contact_weight``: the auxiliary loss that asks the condition grid's embedding
where the contact is.  The loss against an independent closed form, null rows left out, no head
without the weight, the contact cells against their definition, and the config refusal."""

import pytest
import torch
from torch import nn

from vqtouch.core import BuildContext, ConditionTokens, load_plugins
from vqtouch.plugins.generator.codes import contact_cells

HOST = load_plugins(autoload=False)
CONTEXT = BuildContext(image_size=32, cond_dim=8, codebook_size=16, code_grid=4)


def _generator(contact_weight):
    torch.manual_seed(0)
    options = {"depth": 1, "width": 16, "heads": 2, "num_steps": 10, "contact_weight": contact_weight}
    generator = HOST.build("generator", {"name": "vq_diffusion", **options}, CONTEXT)
    # The grid projection starts at zero (a fresh generator ignores the grid); give it weights so
    # the head's input depends on the grid.
    nn.init.normal_(generator.network.grid_proj.weight)
    return generator.eval()


def _batch(seed=1):
    draw = torch.Generator().manual_seed(seed)
    condition = ConditionTokens(
        torch.randn(3, 2, 8, generator=draw),
        torch.tensor([False, True, False]),
        torch.randn(3, 8, 2, 2, generator=draw),  # coarser than the 4 x 4 code grid: it is resized
    )
    codes = torch.randint(16, (3, 4, 4), generator=draw)
    contact = torch.rand(3, 4, 4, generator=draw) < 0.4
    return condition, codes, contact


def _reference_bce(generator, condition, contact):
    """Binary cross-entropy written out: the grid resized bilinearly to the code grid, each cell
    L2-normalised, projected, the head's logit z, and -[y log sigmoid(z) + (1 - y) log sigmoid(-z)],
    averaged over the cells of the rows that are not null."""
    rows = (~condition.is_null_B).nonzero().flatten()
    grid = torch.nn.functional.interpolate(condition.grid_BDhw[rows], size=(4, 4), mode="bilinear", align_corners=False)
    cells = grid.flatten(2).transpose(1, 2)
    cells = cells / cells.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    network = generator.network
    z = (cells @ network.grid_proj.weight.T + network.grid_proj.bias) @ generator.contact_head.weight.T
    z = (z + generator.contact_head.bias).squeeze(-1)
    y = contact[rows].flatten(1).float()
    return float(-(y * torch.log(torch.sigmoid(z)) + (1 - y) * torch.log(torch.sigmoid(-z))).mean().detach())


def test_the_contact_loss_adds_its_weight_times_the_bce_of_the_non_null_rows():
    generator = _generator(0.5)
    condition, codes, contact = _batch()
    plain, plain_scalars = generator.training_loss(codes, condition, generator=torch.Generator().manual_seed(3))
    total, scalars = generator.training_loss(
        codes, condition, generator=torch.Generator().manual_seed(3), contact_BHW=contact
    )
    expected = _reference_bce(generator, condition, contact)
    assert scalars["contact_bce"] == pytest.approx(expected, rel=1e-5)
    assert float((total - plain).detach()) == pytest.approx(0.5 * expected, rel=1e-4)
    assert "contact_bce" not in plain_scalars
    # The null row (1) carries no condition, so its cells cannot count.
    changed = contact.clone()
    changed[1] = ~changed[1]
    assert float(generator.contact_loss(condition, changed).detach()) == pytest.approx(expected, rel=1e-5)
    every_row_null = ConditionTokens(condition.tokens_BND, torch.ones(3, dtype=torch.bool), condition.grid_BDhw)
    assert generator.contact_loss(every_row_null, contact) is None
    with pytest.raises(ValueError, match=r"contact cells \(3, 2, 2\) for 3 conditions on the 4x4 code grid"):
        generator.contact_loss(condition, contact[:, :2, :2])


def test_the_head_learns_the_place_through_the_grid():
    """A few steps on the contact loss alone lower it: the gradient reaches the grid projection."""
    generator = _generator(1.0)
    condition, _, _ = _batch()
    # A place the grid tells: where its first channel, resized to the code grid, is positive.
    resized = torch.nn.functional.interpolate(condition.grid_BDhw, size=(4, 4), mode="bilinear", align_corners=False)
    contact = resized[:, 0] > 0
    optimizer = torch.optim.Adam(generator.parameters(), lr=0.05)
    first = float(generator.contact_loss(condition, contact).detach())
    for _ in range(30):
        optimizer.zero_grad()
        generator.contact_loss(condition, contact).backward()
        optimizer.step()
    assert float(generator.contact_loss(condition, contact).detach()) < 0.3 * first


def test_no_head_is_built_without_the_weight_and_the_cells_are_then_ignored():
    generator = _generator(0.0)
    assert generator.contact_head is None
    assert not [key for key in generator.state_dict() if key.startswith("contact_head")]
    assert {"contact_head.weight", "contact_head.bias"} <= set(_generator(1.0).state_dict())
    condition, codes, contact = _batch()
    draws = [torch.Generator().manual_seed(3) for _ in range(2)]
    with torch.no_grad():
        plain = generator.training_loss(codes, condition, generator=draws[0])[0]
        given = generator.training_loss(codes, condition, generator=draws[1], contact_BHW=contact)[0]
    assert float(plain) == float(given)
    with pytest.raises(ValueError, match="contact_loss needs generator.model.contact_weight > 0"):
        generator.contact_loss(condition, contact)


class _FixedTokenizer:
    """A stand-in tokenizer whose encoder gives one fixed code grid, whatever the image."""

    device = torch.device("cpu")

    def __init__(self, codes_HW):
        self.codes_HW = codes_HW

    def encode_codes(self, images_B3HW):
        return self.codes_HW.expand(len(images_B3HW), -1, -1)


def test_contact_cells_are_the_cells_whose_code_is_not_the_backgrounds():
    background_codes = torch.tensor([[1, 2], [3, 4]])
    codes = torch.tensor([[[1, 2], [3, 4]], [[1, 9], [3, 4]], [[0, 0], [0, 0]]])
    cells = contact_cells(codes, _FixedTokenizer(background_codes), torch.zeros(3, 8, 8))
    assert cells.tolist() == [[[False, False], [False, False]], [[False, True], [False, False]], [[True] * 2] * 2]
    with pytest.raises(ValueError, match=r"the background's code grid \(2, 2\) is not the codes' \(3, 3\)"):
        contact_cells(torch.zeros(1, 3, 3, dtype=torch.long), _FixedTokenizer(background_codes), torch.zeros(3, 8, 8))
