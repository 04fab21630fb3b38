"""Hybrid contact model (paper §4.4, after Jiang et al. 2022): learned friction wrench plus our own frictionless LCP."""

from contactbench.models.hybrid.dynamics import SingleBodyError
from contactbench.models.hybrid.inverse import compare_with_bullet_contacts
from contactbench.models.hybrid.lcp import ContactSettings
from contactbench.models.hybrid.module import HybridContactModel, HybridDataModule, HybridModule

__all__ = [
    "ContactSettings",
    "HybridContactModel",
    "HybridDataModule",
    "HybridModule",
    "SingleBodyError",
    "compare_with_bullet_contacts",
]
