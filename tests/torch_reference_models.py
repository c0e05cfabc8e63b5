"""Plain-PyTorch twins of the models gac-jax imports weights from (helper of test_convert.py).

* :class:`TorchResNet` - a ResNet with torchvision's module names (so its ``state_dict`` has
  torchvision's keys and shapes);
* :class:`GroundAwareYolo3D` - the reference GAC detector written from reference_impl.md §3:
  ResNet trunk through layer3, cls branch, reg branch with LookGround (grid_sample with border
  padding and align_corners=True), AnchorFlatten; module names and registration order give
  the reference state dict (reference_state_dict.md §1);
* :func:`randomize_` - random BatchNorm parameters and statistics, eval mode.

Import only after ``pytest.importorskip("torch")``.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812

TORCH_BLOCKS = {18: ("basic", [2, 2, 2, 2]), 34: ("basic", [3, 4, 6, 3])}
TORCH_BLOCKS |= {50: ("bottleneck", [3, 4, 6, 3]), 101: ("bottleneck", [3, 4, 23, 3])}


# ---------------------------------------------------------------------------------------------
# plain PyTorch ResNet with torchvision's naming


class TorchBasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes, planes, stride):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = _downsample(inplanes, planes, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class TorchBottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes, planes, stride):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.downsample = _downsample(inplanes, planes * 4, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


def _downsample(inplanes, out, stride):
    if stride == 1 and inplanes == out:
        return None
    return nn.Sequential(nn.Conv2d(inplanes, out, 1, stride, bias=False), nn.BatchNorm2d(out))


class TorchResNet(nn.Module):
    """torchvision-named ResNet; forward(NCHW) -> [layer1, ..., layerN] outputs."""

    def __init__(self, depth, num_stages=4, width=64, fc=True):
        super().__init__()
        kind, blocks = TORCH_BLOCKS[depth]
        block = TorchBottleneck if kind == "bottleneck" else TorchBasicBlock
        self.conv1 = nn.Conv2d(3, width, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.num_stages = num_stages
        inplanes = width
        for s in range(num_stages):
            planes, layers = width * 2**s, []
            for b in range(blocks[s]):
                layers.append(block(inplanes, planes, 2 if (s > 0 and b == 0) else 1))
                inplanes = planes * block.expansion
            setattr(self, f"layer{s + 1}", nn.Sequential(*layers))
        if fc:
            self.fc = nn.Linear(inplanes, 1000)

    def forward(self, x):
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        outs = []
        for s in range(self.num_stages):
            x = getattr(self, f"layer{s + 1}")(x)
            outs.append(x)
        return outs


# ---------------------------------------------------------------------------------------------
# plain PyTorch GroundAwareYolo3D (reference_impl.md §3; state-dict keys of reference_state_dict.md)


class AnchorFlatten(nn.Module):
    def __init__(self, num_output):
        super().__init__()
        self.num_output = num_output

    def forward(self, x):  # [B, A*D, H, W] -> [B, H*W*A, D]
        return x.permute(0, 2, 3, 1).contiguous().view(x.shape[0], -1, self.num_output)


class LookGround(nn.Module):
    """formula 'release_1.0': h (v-cy) / 2 * (EL - h/2); 'fixed': h (v-cy) / (2 (EL - h/2))."""

    def __init__(self, channels, baseline=0.54, relative_elevation=1.65, h_mean=1.535):
        super().__init__()
        self.disp_create = nn.Sequential(nn.Conv2d(channels, 1, 3, padding=1), nn.Tanh())
        self.extract = nn.Conv2d(channels + 1, channels, 1)
        self.alpha = nn.Parameter(torch.tensor([0.0]))
        self.baseline, self.el, self.h = baseline, relative_elevation, h_mean
        self.formula = "release_1.0"

    def forward(self, x, P2):
        P2 = P2.clone()
        P2[:, 0:2] = P2[:, 0:2] / 16.0
        d0 = self.disp_create(x)
        d = 0.1 * (0.05 * d0 + 0.95 * d0.detach())  # [B,1,H,W]
        B, _, H, W = x.shape
        fy, cy, ty = P2[:, 1, 1:2], P2[:, 1, 2:3], P2[:, 1, 3:4]  # [B,1]
        v = torch.arange(H, dtype=x.dtype)[None]
        disp = F.relu(fy * self.baseline * (v - cy) / (torch.abs(fy * self.el + ty) + 1e-10))
        if self.formula == "release_1.0":
            base = self.h * (v - cy) / 2 * (self.el - self.h / 2)
        else:
            base = self.h * (v - cy) / (2 * (self.el - self.h / 2))
        base = F.relu(base) / (H / 2)  # [B,H], normalised units
        grid_y = torch.linspace(-1, 1, H)[None, :, None] + base[:, :, None] + d[:, 0]
        grid_x = torch.linspace(-1, 1, W)[None, None, :].expand(B, H, W)
        grid = torch.stack([grid_x, grid_y], dim=-1)
        G = torch.cat([disp[:, None, :, None].expand(B, 1, H, W), x], dim=1)
        S = F.grid_sample(G, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return F.relu(x + self.alpha * self.extract(S))


class FocalLossBuffers(nn.Module):
    def __init__(self, balance_weights):
        super().__init__()
        self.register_buffer("balance_weights", balance_weights)


class GroundAwareHead(nn.Module):
    def __init__(self, C, num_classes, num_anchors, cls_features, reg_features):
        super().__init__()
        balance = torch.tensor([20.0])
        self.register_buffer("balance_weights", balance)
        self.register_buffer(
            "regression_weight", torch.tensor([1.0] * 6 + [3, 1, 1] + [0.5] * 3 + [1])
        )
        self.loss_cls = FocalLossBuffers(balance)
        A, K = num_anchors, num_classes
        self.cls_feature_extraction = nn.Sequential(
            nn.Conv2d(C, cls_features, 3, padding=1), nn.Dropout2d(0.3), nn.ReLU(),
            nn.Conv2d(cls_features, cls_features, 3, padding=1), nn.Dropout2d(0.3), nn.ReLU(),
            nn.Conv2d(cls_features, A * (K + 1), 3, padding=1), AnchorFlatten(K + 1),
        )  # fmt: skip
        self.reg_feature_extraction = nn.Sequential(
            LookGround(C),
            nn.Conv2d(C, reg_features, 3, padding=1), nn.BatchNorm2d(reg_features), nn.ReLU(),
            nn.Conv2d(reg_features, reg_features, 3, padding=1), nn.BatchNorm2d(reg_features),
            nn.ReLU(), nn.Conv2d(reg_features, A * 12, 3, padding=1), AnchorFlatten(12),
        )  # fmt: skip

    def forward(self, features, P2):
        cls = self.cls_feature_extraction(features)
        reg = self.reg_feature_extraction[0](features, P2)
        for layer in self.reg_feature_extraction[1:]:
            reg = layer(reg)
        return cls, reg


class Core(nn.Module):
    def __init__(self, depth, width):
        super().__init__()
        self.backbone = TorchResNet(depth, num_stages=3, width=width, fc=False)


class GroundAwareYolo3D(nn.Module):
    def __init__(self, depth=101, width=64, num_classes=1, num_anchors=32, cls=512, reg=1024):
        super().__init__()
        C = width * 4 * (4 if TORCH_BLOCKS[depth][0] == "bottleneck" else 1)
        self.bbox_head = GroundAwareHead(C, num_classes, num_anchors, cls, reg)
        self.core = Core(depth, width)

    def forward(self, images, P2):
        return self.bbox_head(self.core.backbone(images)[-1], P2)


# ---------------------------------------------------------------------------------------------
# helpers


def randomize_(model, *inputs, seed=0):
    """Random BN affine + running stats near the real batch statistics, then eval mode.

    The last BN of each residual branch gets a small scale (U(0.1, 0.5), as in trained
    ResNets) so the random 101-layer net stays well-conditioned: float32 rounding then
    perturbs layer3 by ~1e-5 relative (it is ~1e-4 with unit scales, for torch too)."""
    torch.manual_seed(seed)
    bns = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    last = {id(m.bn3) for m in model.modules() if isinstance(m, TorchBottleneck)}
    last |= {id(m.bn2) for m in model.modules() if isinstance(m, TorchBasicBlock)}
    with torch.no_grad():
        for bn in bns:
            nn.init.uniform_(bn.weight, *((0.1, 0.5) if id(bn) in last else (0.5, 1.5)))
            nn.init.normal_(bn.bias, 0.0, 0.1)
            bn.momentum = 1.0
        model.train()
        model(*inputs)
        for bn in bns:
            bn.momentum = 0.1
            bn.running_mean.mul_(torch.empty_like(bn.running_mean).uniform_(0.8, 1.2))
            bn.running_var.mul_(torch.empty_like(bn.running_var).uniform_(0.7, 1.4))
    return model.eval()
