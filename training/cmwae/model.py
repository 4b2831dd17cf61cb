"""The Cross-Modal Wasserstein Autoencoder (PAPER.md §CMWAE).

Two AlexNet convolutional stacks (1 channel, 224x224) encode gray and depth; one FC layer per
modality embeds each, a shared FC layer fuses them into z in R^64; the decoder maps z through an
FC layer to 256x6x6 and four convolutional layers back to a 224x224 depth image in [0, 1]
(the contract's normalised depth).  Only depth is reconstructed.

A depth-only encoder (the DCE-RL stand-in of Table II) is the same network with the gray branch
removed (``modalities=("depth",)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from runtime.contract.constants import IMAGE_SIZE_PX, LATENT_DIM

MODALITIES = ("gray", "depth")
ALEXNET_FEATURES = 256 * 6 * 6


@dataclass(frozen=True)
class CmwaeConfig:
    latent_dim: int = LATENT_DIM
    embed_dim: int = 512  # per-modality FC embedding
    modalities: tuple[str, ...] = MODALITIES
    # Channel widths of the AlexNet stack; the paper's are (64, 192, 384, 256, 256).  Tests use
    # narrower ones; the last must stay 256 (the decoder's 256x6x6 mirrors it).
    alexnet_channels: tuple[int, int, int, int, int] = (64, 192, 384, 256, 256)
    decoder_channels: tuple[int, int, int] = (128, 64, 32)

    def validate(self) -> None:
        if not self.modalities or any(m not in MODALITIES for m in self.modalities):
            raise ValueError(f"modalities={self.modalities} must be a non-empty subset of {MODALITIES}")
        if self.latent_dim != LATENT_DIM:
            raise ValueError(f"latent_dim={self.latent_dim}: the runtime contract fixes it at {LATENT_DIM}")
        if len(self.alexnet_channels) != 5 or self.alexnet_channels[-1] != 256:
            raise ValueError(f"alexnet_channels={self.alexnet_channels}: five widths ending in 256")


# Network sizes: the paper's, and narrower ones for CPU-only runs and tests (same structure).
SIZE_PRESETS: dict[str, dict] = {
    "paper": {},
    "small": {"embed_dim": 256, "alexnet_channels": (32, 96, 192, 128, 256), "decoder_channels": (64, 32, 16)},
    "tiny": {"embed_dim": 32, "alexnet_channels": (8, 16, 16, 16, 256), "decoder_channels": (16, 8, 4)},
}


def make_config(size: str = "paper", modalities: tuple[str, ...] = MODALITIES) -> CmwaeConfig:
    if size not in SIZE_PRESETS:
        raise ValueError(f"size={size!r} must be one of {sorted(SIZE_PRESETS)}")
    config = CmwaeConfig(modalities=tuple(modalities), **SIZE_PRESETS[size])
    config.validate()
    return config


def alexnet_features(channels: tuple[int, int, int, int, int]) -> nn.Sequential:
    """AlexNet's convolutional stack for one input channel: 224x224 -> channels[-1] x 6 x 6."""
    c1, c2, c3, c4, c5 = channels
    return nn.Sequential(
        nn.Conv2d(1, c1, kernel_size=11, stride=4, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(c1, c2, kernel_size=5, padding=2),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(c2, c3, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(c3, c4, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(c4, c5, kernel_size=3, padding=1),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


class Encoder(nn.Module):
    """(gray, depth) [B, 1, 224, 224] each, in the contract's normalisation -> z [B, 64]."""

    def __init__(self, config: CmwaeConfig) -> None:
        super().__init__()
        config.validate()
        self.modalities = tuple(config.modalities)
        self.features = nn.ModuleDict({m: alexnet_features(config.alexnet_channels) for m in self.modalities})
        self.embed = nn.ModuleDict(
            {m: nn.Sequential(nn.Flatten(), nn.Linear(ALEXNET_FEATURES, config.embed_dim), nn.ELU()) for m in self.modalities}
        )
        self.shared = nn.Linear(config.embed_dim * len(self.modalities), config.latent_dim)

    def forward(self, gray: Tensor, depth: Tensor) -> Tensor:
        inputs = {"gray": gray, "depth": depth}
        embeddings = [self.embed[m](self.features[m](inputs[m])) for m in self.modalities]
        return self.shared(torch.cat(embeddings, dim=1))


class DepthDecoder(nn.Module):
    """z [B, 64] -> depth [B, 1, 224, 224] in [0, 1]: FC to 256x6x6, then four conv layers,
    each after a bilinear upsampling (6 -> 14 -> 28 -> 56 -> 224)."""

    SIZES = (14, 28, 56, IMAGE_SIZE_PX)

    def __init__(self, config: CmwaeConfig) -> None:
        super().__init__()
        self.fc = nn.Linear(config.latent_dim, ALEXNET_FEATURES)
        widths = (256, *config.decoder_channels, 1)
        self.convs = nn.ModuleList(nn.Conv2d(a, b, kernel_size=3, padding=1) for a, b in zip(widths[:-1], widths[1:]))

    def forward(self, z: Tensor) -> Tensor:
        # Always fp32, also under bf16 autocast: on the CPU the bf16 bilinear upsampling made a
        # training step 3x slower than fp32 here, and the reconstruction is what the loss measures.
        with torch.autocast(z.device.type, enabled=False):
            return self._decode(z.float())

    def _decode(self, z: Tensor) -> Tensor:
        x = F.elu(self.fc(z)).view(-1, 256, 6, 6)
        for i, (size, conv) in enumerate(zip(self.SIZES, self.convs)):
            x = conv(F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False))
            x = torch.sigmoid(x) if i == len(self.convs) - 1 else F.elu(x)
        return x


class Cmwae(nn.Module):
    def __init__(self, config: CmwaeConfig = CmwaeConfig()) -> None:
        super().__init__()
        self.config = config
        self.encoder = Encoder(config)
        self.decoder = DepthDecoder(config)

    def forward(self, gray: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
        """-> (z [B, 64], reconstructed depth [B, 1, 224, 224])."""
        z = self.encoder(gray, depth)
        return z, self.decoder(z)
