"""A light FPN-style neck: fuses the backbone's stride-16 and stride-32 maps into one stride-16 map.

Forward: (C3 [N, c3, h, w], C4 [N, c4, h/2, w/2]) → [N, out_channels, h, w].
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class Stride16Neck(nn.Module):
    """1x1 laterals on C3 and C4, C4 upsampled x2 (nearest) and added, then 3x3 conv-BN-ReLU."""

    def __init__(self, in_channels: tuple[int, int], out_channels: int):
        super().__init__()
        self.lateral3 = nn.Conv2d(in_channels[0], out_channels, kernel_size=1)
        self.lateral4 = nn.Conv2d(in_channels[1], out_channels, kernel_size=1)
        self.fuse = nn.Sequential(
            nn.Conv2d(out_channels, out_channels, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, c3: torch.Tensor, c4: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(self.lateral4(c4), scale_factor=2.0, mode="nearest")
        return self.fuse(self.lateral3(c3) + up)
