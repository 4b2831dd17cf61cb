"""The exported model's variants and where they are written.  The naming is the runtime's
(``runtime.config.variant_path``: ``cmnav fly`` selects a variant with ``policy.variant``), so
``cmnav bench runtime`` and the Jetson find them without torch."""

from __future__ import annotations

from runtime.config import MODEL_VARIANTS, variant_path

VARIANTS = tuple(v for v in MODEL_VARIANTS if v != "fp32")

__all__ = ["VARIANTS", "variant_path"]
