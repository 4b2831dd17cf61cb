"""The Cross-Modal Wasserstein Autoencoder: model and WAE-MMD loss."""

from .loss import cmwae_loss, mmd_imq
from .model import Cmwae, CmwaeConfig

__all__ = ["Cmwae", "CmwaeConfig", "cmwae_loss", "mmd_imq"]
