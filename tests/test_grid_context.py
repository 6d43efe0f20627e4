"""The condition grid's context stack (``grid_context``): residual dilated convolutions that let
each code's cell see the image around it before the generator reads it."""

import pytest
import torch

from vqtouch.conditioners.grid_context import GridContext, grid_context_for
from vqtouch.core import BuildContext, ConfigError, load_plugins

HOST = load_plugins(autoload=False)
CONTEXT = BuildContext(image_size=64, num_classes=3, codebook_size=16, code_grid=16, cond_dim=24)


def build(**options):
    torch.manual_seed(0)
    return HOST.build("conditioner", {"name": "visual_cnn"} | options, CONTEXT)


def randomise(stack: GridContext) -> None:
    with torch.no_grad():
        for block in stack.blocks:
            block[-1].weight.normal_(0, 0.2)
        if stack.widen is not None:
            stack.widen.weight.normal_(0, 0.2)


@pytest.mark.parametrize("width", [None, 8])
def test_a_fresh_context_stack_leaves_the_grid_as_it_was(width):
    plain, with_context = build(), build(grid_context=[1, 2, 4, 8], grid_context_width=width)
    with_context.load_state_dict(plain.state_dict(), strict=False)
    images = torch.rand(2, 3, 64, 64)
    tokens, grid = with_context.encode_with_grid(images)
    torch.testing.assert_close(grid, plain.encode_with_grid(images)[1])
    torch.testing.assert_close(tokens, plain.encode_with_grid(images)[0])


@pytest.mark.parametrize("width", [None, 4])
@pytest.mark.parametrize("dilations", [[1], [1, 2], [1, 2, 4], [1, 2, 4, 8], [3, 3], [2, 5]])
def test_a_cell_sees_exactly_the_offsets_its_dilated_kernels_reach(dilations, width):
    torch.manual_seed(0)
    stack = GridContext(6, dilations, width)
    randomise(stack)
    grid = torch.randn(1, 6, 41, 41)
    touched = grid.clone()
    touched[..., 20, 20] += 1.0  # the centre: no path of the kernel leaves the grid
    changed_hw = (stack(touched) - stack(grid)).abs().amax(1)[0] > 1e-7
    # Each block's kernel reaches -d, 0 or +d along each axis; a cell sees the sums of those.
    offsets = {0}
    for dilation in dilations:
        offsets = {o + step for o in offsets for step in (-dilation, 0, dilation)}
    reached = torch.zeros(41, dtype=torch.bool)
    reached[[20 + o for o in offsets]] = True
    assert torch.equal(changed_hw, reached[:, None] & reached[None, :])


@pytest.mark.parametrize(
    "block", [{"name": "visual_cnn"}, {"name": "tactile", "reads": "tactile"}, {"name": "visual", "input_size": 64}]
)
def test_gradients_reach_the_zero_initialised_stack(block):
    torch.manual_seed(0)
    conditioner = HOST.build("conditioner", block | {"grid_context": [1, 2]}, CONTEXT)
    conditioner.encode_with_grid(torch.rand(2, 3, 64, 64))[1].square().sum().backward()
    for layer in conditioner.grid_context.blocks:
        assert layer[-1].weight.grad.abs().sum() > 0


@pytest.mark.parametrize(
    "block", [{"name": "visual_cnn"}, {"name": "tactile", "reads": "tactile"}, {"name": "visual", "input_size": 64}]
)
def test_every_grid_conditioner_builds_its_stack_at_the_configured_width(block):
    conditioner = HOST.build("conditioner", block | {"grid_context": [1, 2], "grid_context_width": 8}, CONTEXT)
    assert conditioner.grid_context.narrow.out_channels == 8
    assert conditioner.grid_context.widen.out_channels == CONTEXT.cond_dim


def test_a_narrow_stack_trains_its_blocks_once_its_up_projection_moves():
    torch.manual_seed(0)
    stack = GridContext(24, [1, 2], width=8)
    optimiser = torch.optim.SGD(stack.parameters(), lr=0.1)
    grid = torch.randn(2, 24, 16, 16)
    for _ in range(2):
        optimiser.zero_grad()
        stack(grid).square().sum().backward()
        assert stack.widen.weight.grad.abs().sum() > 0
        optimiser.step()
    for block in stack.blocks:
        assert block[-1].weight.grad.abs().sum() > 0


def test_a_narrow_stack_costs_the_square_of_its_width_ratio():
    def block_weights(stack: GridContext) -> int:
        return sum(block[-1].weight.numel() for block in stack.blocks)

    full, narrow = GridContext(256, [1, 2, 4, 8]), GridContext(256, [1, 2, 4, 8], width=64)
    assert block_weights(full) == 4 * 9 * 256 * 256
    assert block_weights(narrow) * 16 == block_weights(full)
    assert narrow.narrow.weight.shape == (64, 256, 1, 1) and narrow.widen.weight.shape == (256, 64, 1, 1)
    assert GridContext(256, [1], width=256).narrow is None  # the grid's own width: no projections


@pytest.mark.parametrize("width", [None, 8])
def test_a_state_dict_round_trip_keeps_the_stack(width):
    conditioner = build(grid_context=[1, 2], grid_context_width=width)
    randomise(conditioner.grid_context)
    copy = build(grid_context=[1, 2], grid_context_width=width)
    copy.load_state_dict(conditioner.state_dict())
    images = torch.rand(1, 3, 64, 64)
    torch.testing.assert_close(copy.encode_with_grid(images)[1], conditioner.encode_with_grid(images)[1])


@pytest.mark.parametrize(
    "block, message",
    [
        ({"name": "visual_cnn", "grid_context": [0]}, "greater than or equal to 1"),
        ({"name": "tactile", "grid_context": [17]}, "less than or equal to 16"),
        ({"name": "visual_cnn", "grid_context": [1], "spatial": False}, "set spatial=true or grid_context=[]"),
        ({"name": "visual", "grid_context": [1], "grid_stage": None}, "set grid_stage or grid_context=[]"),
        ({"name": "visual_cnn", "grid_context_width": 16}, "grid_context_width sets the width"),
        ({"name": "visual", "grid_context_width": 16}, "grid_context_width sets the width"),
        ({"name": "tactile", "grid_context": [1], "grid_context_width": 4}, "greater than or equal to 8"),
    ],
)
def test_bad_context_settings_are_one_line_errors(block, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        HOST.build("conditioner", block, CONTEXT)


def test_a_stack_built_in_python_checks_what_the_config_checks():
    with pytest.raises(ValueError, match="less than or equal to 16"):
        GridContext(4, [1, 17])
    with pytest.raises(ValueError, match="grid_context needs a condition grid"):
        grid_context_for(4, [1], has_grid=False)
    assert grid_context_for(4, [], has_grid=False) is None
    with pytest.raises(ValueError, match="grid_context_width sets the width"):
        grid_context_for(4, [], has_grid=True, width=8)
