"""ResNet image backbone in plain torch, parameter names identical to torchvision's ``resnet*``.

``ResNet(block, layers, width)`` builds torchvision's layout (``conv1``, ``bn1``, ``layer1``..``layer4`` with
``downsample.0/1``); torchvision-format weights (e.g. a saved ``torchvision.models.resnet50().state_dict()``)
load from a local file with :func:`load_torchvision_weights`. Nothing is ever downloaded.

Forward: images [N, 3, H, W] (normalised) → (C3 [N, c3, H/16, W/16], C4 [N, c4, H/32, W/32]).
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn


def _conv3x3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=3, stride=stride, padding=1, bias=False)


def _conv1x1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    """torchvision's BasicBlock (ResNet-18/34)."""

    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv3x3(inplanes, planes, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """torchvision's Bottleneck (ResNet v1.5: the stride sits on the 3x3 conv)."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv1x1(inplanes, planes)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv1x1(planes, planes * self.expansion)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


class ResNet(nn.Module):
    """ResNet trunk without the classifier; returns the stride-16 and stride-32 feature maps.

    ``block``: "basic" or "bottleneck"; ``layers``: blocks per stage (ResNet-50 = (3, 4, 6, 3));
    ``width``: stem width (64 in torchvision; stage widths are width, 2w, 4w, 8w times the block expansion).
    """

    def __init__(self, block: str = "bottleneck", layers=(3, 4, 6, 3), width: int = 64):
        super().__init__()
        block_cls = {"basic": BasicBlock, "bottleneck": Bottleneck}.get(block)
        if block_cls is None:
            raise ValueError(f"block must be 'basic' or 'bottleneck', got {block!r}")
        self.inplanes = width
        self.conv1 = nn.Conv2d(3, width, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block_cls, width, layers[0], 1)
        self.layer2 = self._make_layer(block_cls, width * 2, layers[1], 2)
        self.layer3 = self._make_layer(block_cls, width * 4, layers[2], 2)
        self.layer4 = self._make_layer(block_cls, width * 8, layers[3], 2)
        self.out_channels = (width * 4 * block_cls.expansion, width * 8 * block_cls.expansion)
        for m in self.modules():  # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _make_layer(self, block_cls, planes: int, blocks: int, stride: int) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes * block_cls.expansion:
            downsample = nn.Sequential(_conv1x1(self.inplanes, planes * block_cls.expansion, stride),
                                       nn.BatchNorm2d(planes * block_cls.expansion))
        mods = [block_cls(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes * block_cls.expansion
        mods += [block_cls(self.inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*mods)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[N, 3, H, W] → (C3 [N, out_channels[0], H/16, W/16], C4 [N, out_channels[1], H/32, W/32])."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        c3 = self.layer3(self.layer2(self.layer1(x)))
        return c3, self.layer4(c3)


# torchvision keys that this backbone does not have (the classifier) and that are therefore skipped on load.
_IGNORED_PREFIXES = ("fc.",)


def load_torchvision_state_dict(backbone: ResNet, state_dict: dict, source: str = "state dict") -> None:
    """Copy torchvision-format ResNet weights into ``backbone`` (``fc.*`` ignored; everything else must match).

    Raises ``ValueError`` naming ``source`` and the offending keys on missing/unexpected keys or shape mismatch.
    """
    sd = {k.removeprefix("module."): v for k, v in state_dict.items()}
    sd = {k: v for k, v in sd.items() if not k.startswith(_IGNORED_PREFIXES)}
    own = backbone.state_dict()
    missing = sorted(set(own) - set(sd))
    unexpected = sorted(set(sd) - set(own))
    if missing or unexpected:
        raise ValueError(f"{source}: not a matching torchvision ResNet state dict; missing keys "
                         f"{missing[:5]}{'...' if len(missing) > 5 else ''}, unexpected keys "
                         f"{unexpected[:5]}{'...' if len(unexpected) > 5 else ''}")
    bad = [f"{k} {tuple(sd[k].shape)} vs {tuple(v.shape)}" for k, v in own.items() if sd[k].shape != v.shape]
    if bad:
        raise ValueError(f"{source}: shape mismatch (file vs model) for {bad[:5]}")
    backbone.load_state_dict(sd, strict=True)


def load_torchvision_weights(backbone: ResNet, path: str | Path) -> None:
    """Load a local torchvision ResNet weight file (a state dict, or {"state_dict": ...}) into ``backbone``."""
    path = Path(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise FileNotFoundError(f"backbone weight file not found: {path}") from None
    except Exception as exc:  # corrupt or non-torch file
        raise ValueError(f"{path}: cannot read backbone weights ({type(exc).__name__}: {exc})") from exc
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a state dict, got {type(obj).__name__}")
    load_torchvision_state_dict(backbone, obj, source=str(path))
