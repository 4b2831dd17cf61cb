"""CMWAE architecture and the WAE-MMD loss."""

import pytest
import torch

from training.cmwae import Cmwae, CmwaeConfig, cmwae_loss, mmd_imq
from training.cmwae.loss import IMQ_SCALES

TINY = CmwaeConfig(embed_dim=32, alexnet_channels=(8, 16, 16, 16, 256), decoder_channels=(16, 8, 4))


def _mmd_by_loops(x, y):
    n, d = x.shape
    total = 0.0
    for s in IMQ_SCALES:
        c = 2.0 * d * s
        k = lambda a, b: c / (c + float(((a - b) ** 2).sum()))  # noqa: E731
        within = sum(k(x[i], x[j]) + k(y[i], y[j]) for i in range(n) for j in range(n) if i != j) / (n * n - n)
        cross = sum(k(x[i], y[j]) for i in range(n) for j in range(n)) * 2.0 / (n * n)
        total += within - cross
    return total


def test_mmd_matches_the_reference_formula():
    g = torch.Generator().manual_seed(0)
    x, y = torch.randn(6, 5, generator=g, dtype=torch.float64), torch.randn(6, 5, generator=g, dtype=torch.float64)
    assert float(mmd_imq(x, y)) == pytest.approx(_mmd_by_loops(x, y), rel=1e-9)


def test_mmd_separates_distributions():
    g = torch.Generator().manual_seed(1)
    prior = torch.randn(256, 64, generator=g)
    same = mmd_imq(torch.randn(256, 64, generator=g), prior)
    shifted = mmd_imq(torch.randn(256, 64, generator=g) + 1.0, prior)
    assert abs(float(same)) < 0.02 < float(shifted)


def test_shapes_range_and_latent_size():
    model = Cmwae(TINY)
    z, recon = model(torch.rand(3, 1, 224, 224), torch.rand(3, 1, 224, 224))
    assert z.shape == (3, 64) and recon.shape == (3, 1, 224, 224)
    assert 0.0 <= float(recon.detach().min()) and float(recon.detach().max()) <= 1.0


def test_paper_size_alexnet_maps_224_to_256x6x6():
    model = Cmwae()
    assert model.encoder.features["gray"](torch.zeros(1, 1, 224, 224)).shape == (1, 256, 6, 6)


def test_depth_only_encoder_ignores_gray():
    model = Cmwae(CmwaeConfig(**{**TINY.__dict__, "modalities": ("depth",)}))
    gray = torch.rand(2, 1, 224, 224, requires_grad=True)
    z, _ = model(gray, torch.rand(2, 1, 224, 224))
    z.sum().backward()
    assert gray.grad is None


def test_loss_trains_down():
    torch.manual_seed(0)
    model = Cmwae(TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    # Learnable scenes: vertical ramps of different offsets (a wall seen at different distances).
    ramp = torch.linspace(0.0, 0.5, 224).view(1, 1, 224, 1).expand(8, 1, 224, 224)
    depth = ramp + torch.linspace(0.1, 0.4, 8).view(8, 1, 1, 1)
    gray = 1.0 - depth
    losses = []
    for _ in range(30):
        z, recon = model(gray, depth)
        out = cmwae_loss(recon, depth, z, mmd_weight=10.0)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["recon_mse"].detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="modalities"):
        Cmwae(CmwaeConfig(modalities=("rgb",)))
    with pytest.raises(ValueError, match="latent_dim=32"):
        Cmwae(CmwaeConfig(latent_dim=32))
