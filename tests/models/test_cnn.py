"""DQN's CNN over frames (``ActionCNN``): shapes, the frame it reads, and a value that follows the picture."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.common.frames import image_shape
from hfrl_torch.models.cnn import ActionCNN


def test_frames_of_any_leading_shape_give_one_value_per_action():
    torch.manual_seed(0)
    net = ActionCNN((210, 160, 3), 6, cells=[32])
    frames = torch.randint(0, 256, (2, 3, 210, 160, 3), dtype=torch.uint8)
    values = net(frames)
    assert values.shape == (2, 3, 6) and bool(torch.isfinite(values).all())
    assert torch.allclose(net(frames[1, 2]), values[1, 2], atol=1e-5)  # one unbatched frame
    chosen = net.chosen(frames[0], torch.tensor([0, 5, 2]))
    assert torch.allclose(chosen, values[0].gather(-1, torch.tensor([[0], [5], [2]])).squeeze(-1), atol=1e-5)


def test_only_frames_are_accepted():
    assert image_shape((84, 84, 1)) == (84, 84, 1) and image_shape([210, 160, 3]) == (210, 160, 3)
    assert image_shape((4,)) is None and image_shape((84, 84)) is None and image_shape((84, 84, 2)) is None
    with pytest.raises(ValueError, match="ActionCNN needs a frame"):
        ActionCNN((84, 84), 3)
    net = ActionCNN((16, 16, 1), 2, cells=[8])
    with pytest.raises(ValueError, match=r"reads frames of shape \[16, 16, 1\], got \[1, 16, 15, 1\]"):
        net(torch.zeros(1, 16, 15, 1))


def test_a_few_steps_of_regression_learn_which_half_of_the_picture_is_lit():
    """Trained on frames lit on the left (value 1 for action 0) or the right (value 1 for action 1), the
    network ranks the actions by where the light is: it reads the picture, not a constant."""
    torch.manual_seed(1)
    net = ActionCNN((16, 16, 1), 2, cells=[16], size=36)
    side = torch.arange(16) % 2  # 0: the left half lit, 1: the right half
    frames = torch.zeros(16, 16, 16, 1, dtype=torch.uint8)
    frames[side == 0, :, :8] = 255
    frames[side == 1, :, 8:] = 255
    target = torch.nn.functional.one_hot(side, 2).float()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(60):
        opt.zero_grad()
        loss = ((net(frames) - target) ** 2).mean()
        loss.backward()
        opt.step()
    assert torch.equal(net(frames).argmax(-1), side)
