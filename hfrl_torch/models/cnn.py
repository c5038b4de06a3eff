"""One value per action from an image, on TorchRL's ``ConvNet`` and ``MLP``: Q or Deep TAMER's H^ for a task
whose observation is a frame (an Atari game's ``[210, 160, 3]`` uint8 screen).

The frame is shrunk inside the network (channels averaged to grey, then area-averaged to ``size`` x
``size``, as DQN's and Deep TAMER's 84 x 84 grey inputs), so the env, the replay buffers and the saved
policies keep the task's own observation and no transform has to be saved beside the weights. The layers
are DQN's (Mnih et al. 2015): 32 8x8 filters at stride 4, 64 4x4 at stride 2, 64 3x3 at stride 1, then the
hidden widths ``cells``. Deep TAMER (Warnell et al. 2018) pre-trains its encoder as an autoencoder on
random play; here it learns from the feedback alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F
from torchrl.modules import MLP, ConvNet

from hfrl_torch.common.frames import image_shape

__all__ = ["ActionCNN"]

PIXEL_SCALE = 1.0 / 255.0  # uint8 frames to [0, 1]


class ActionCNN(nn.Module):
    """One value per action from frames: ``[..., H, W, C] -> [..., A]`` (any dtype; uint8 pixels are read
    as 0-255).

    :param frame: ``(H, W, C)`` of one frame.
    :param actions: A.
    :param cells: hidden widths after the convolutions.
    :param size: the side the grey frame is shrunk to before the convolutions.
    """

    def __init__(
        self, frame: Sequence[int], actions: int, cells: Sequence[int] = (256,), size: int = 84
    ) -> None:
        super().__init__()
        shape = image_shape(frame)
        if shape is None or actions < 1 or size < 36:
            raise ValueError(
                f"ActionCNN needs a frame [height >= 8, width >= 8, 1, 3 or 4 channels], actions >= 1 and "
                f"size >= 36; got {list(frame)}, {actions}, {size}"
            )
        self.frame, self.actions, self.size = shape, int(actions), int(size)
        self.conv = ConvNet(
            num_cells=[32, 64, 64], kernel_sizes=[8, 4, 3], strides=[4, 2, 1], activation_class=nn.ReLU
        )
        with torch.no_grad():
            flat = self.conv(torch.zeros(1, 1, self.size, self.size)).shape[-1]
        self.head = MLP(
            in_features=flat, out_features=self.actions, num_cells=list(cells), activation_class=nn.ReLU
        )

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        lead = frames.shape[:-3]
        if tuple(frames.shape[-3:]) != self.frame:
            raise ValueError(f"ActionCNN reads frames of shape {list(self.frame)}, got {list(frames.shape)}")
        x = frames.reshape(-1, *self.frame).to(torch.float32) * PIXEL_SCALE
        grey = x.mean(-1, keepdim=True).permute(0, 3, 1, 2)  # [N, 1, H, W]
        small = F.adaptive_avg_pool2d(grey, self.size)
        return self.head(self.conv(small)).reshape(*lead, self.actions)

    def chosen(self, inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The value ``[N]`` of the stored frames ``inputs`` [N, H, W, C] at the actions ``action`` [N]."""
        return self(inputs).gather(-1, action.reshape(-1, 1).to(torch.int64)).squeeze(-1)

    @staticmethod
    def select(inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """What a replay entry keeps of a decision: the frame (the action is stored beside it)."""
        return inputs
